"""The reference pages, generated from the code at each build (docs/conf.py writes them): the command line
from `rig.cli.build_parser`, the rig config and the protocol steps from their dataclasses (the one
schema source: fields, types, defaults, ranges and the comments beside them), the log's messages
from `rig.recording.messages`, and the effects catalogue from `rig.models.catalogue`. Nothing
here is written by hand: an option or a field added in the code is on the site at the next build.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import io
import tokenize
import typing
from collections.abc import Callable

PAGES: dict[str, Callable[[], str]] = {}


def page(path: str) -> Callable[[Callable[[], str]], Callable[[], str]]:
    def register(fn: Callable[[], str]) -> Callable[[], str]:
        PAGES[path] = fn
        return fn
    return register


def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


# --- the command line ------------------------------------------------------------------------

def _subparsers(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            out.extend((name, helps.get(name, ""), sub) for name, sub in action.choices.items())
    return out


def _arguments(parser: argparse.ArgumentParser) -> list[str]:
    rows = []
    for a in parser._actions:
        if isinstance(a, argparse._HelpAction | argparse._SubParsersAction | argparse._VersionAction):
            continue
        name = ", ".join(f"`{o}`" for o in a.option_strings) or f"`{a.metavar or a.dest}`"
        if a.option_strings and a.nargs != 0:
            name += f" `{a.metavar or a.dest.upper()}`" if not isinstance(a.metavar, tuple) else ""
        shown = a.option_strings and a.default not in (None, False, argparse.SUPPRESS)
        # an empty string is "empty", not a pair of backticks with nothing between them
        default = ("empty" if a.default == "" else f"`{a.default}`") if shown else ""
        choices = f" (one of: {', '.join(map(str, a.choices))})" if a.choices and not isinstance(
            a.choices, dict) else ""
        helptext = (a.help or "").replace("%(default)s", str(a.default)).replace("%%", "%")
        rows.append(f"| {_cell(name)} | {_cell(helptext + choices)} | {_cell(default)} |")
    if not rows:
        return []
    return ["| argument | what it does | default |", "|---|---|---|", *rows, ""]


def _command(parser: argparse.ArgumentParser, path: list[str], level: int) -> list[str]:
    title = " ".join(path)
    lines = [f"{'#' * level} `{title}`", ""]
    if parser.description:
        lines += [parser.description.strip(), ""]
    usage = parser.format_usage().strip().removeprefix("usage: ")
    lines += ["```text", usage, "```", ""]
    lines += _arguments(parser)
    if parser.epilog:
        lines += ["```text", parser.epilog.strip(), "```", ""]
    for name, _help, sub in _subparsers(parser):
        lines += _command(sub, [*path, name], min(level + 1, 4))
    return lines


@page("reference/cli.md")
def cli_page() -> str:
    from rig.cli import build_parser

    parser = build_parser()
    lines = ["# Command line", "",
             "Every command of `rig` and its options, generated from the program's own parser: "
             "`rig COMMAND --help` prints the same.", ""]
    lines += ["| command | what it does |", "|---|---|"]
    lines += [f"| [`rig {name}`](#rig-{name}) | {_cell(h)} |" for name, h, _ in _subparsers(parser)]
    lines.append("")
    for name, _help, sub in _subparsers(parser):
        lines += _command(sub, ["rig", name], 2)
    return "\n".join(lines)


# --- dataclass schemas -------------------------------------------------------------------------

def _field_comments(cls: type) -> dict[str, str]:
    """The comments beside each field of a dataclass's source: the block just above it and the one
    at the end of its line."""
    try:
        source = inspect.getsource(cls)
    except (OSError, TypeError):
        return {}
    names = {f.name for f in dataclasses.fields(cls)}
    notes: dict[str, str] = {}
    block: list[str] = []
    tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    for i, tok in enumerate(tokens):
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            line_start = tok.line[: tok.start[1]].strip() == ""
            if line_start:
                block.append(text)
            else:
                owner = tok.line.split(":", 1)[0].strip()
                if owner in names:
                    notes[owner] = " ".join(filter(None, [notes.get(owner, ""), text]))
        elif tok.type == tokenize.NAME and tok.start[1] == 4 and tok.string in names and \
                i + 1 < len(tokens) and tokens[i + 1].string == ":":
            if block:
                notes[tok.string] = " ".join(block)
            block = []
        elif tok.type == tokenize.NAME and tok.string == "def":
            block = []
    return notes


def _type_name(tp: object) -> str:
    if isinstance(tp, str):
        return tp
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        return f"`{f.default!r}`" if f.default is not None else "unset"
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        value = f.default_factory()  # type: ignore[misc]
        return "" if dataclasses.is_dataclass(value) else f"`{value!r}`"
    return "required"


def _range(meta: typing.Mapping) -> str:
    parts = []
    for key, sign in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
        if key in meta:
            parts.append(f"{sign} {meta[key]}")
    if "choices" in meta:
        parts.append("one of " + ", ".join(f"`{c}`" for c in meta["choices"]))
    return ", ".join(parts)


def _dataclass_table(cls: type, skip: tuple[str, ...] = ()) -> list[str]:
    hints = typing.get_type_hints(cls)
    notes = _field_comments(cls)
    rows = ["| field | type | default | allowed | what it is |", "|---|---|---|---|---|"]
    for f in dataclasses.fields(cls):
        if f.name in skip or not f.init or f.repr is False:
            continue
        tp = hints.get(f.name, f.type)
        if dataclasses.is_dataclass(tp):
            continue
        rows.append(f"| `{f.name}` | {_cell(_type_name(tp))} | {_cell(_default(f))} | "
                    f"{_cell(_range(f.metadata))} | {_cell(notes.get(f.name, ''))} |")
    return [*rows, ""]


def _sections(cls: type) -> list[tuple[str, type]]:
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        tp = hints.get(f.name)
        inner = [a for a in typing.get_args(tp) if dataclasses.is_dataclass(a)] or [tp]
        if dataclasses.is_dataclass(inner[0]):
            out.append((f.name, inner[0]))
    return out


def _doc(cls: type) -> list[str]:
    """A dataclass's own docstring as a paragraph (not the signature dataclass writes for one
    without)."""
    if cls.__doc__ and not cls.__doc__.startswith(cls.__name__ + "("):
        return [inspect.cleandoc(cls.__doc__), ""]
    return []


def _nested(cls: type, prefix: str, level: int) -> list[str]:
    lines = []
    for name, sub in _sections(cls):
        lines += [f"{'#' * level} `{prefix}{name}:`", ""]
        lines += _doc(sub) + _dataclass_table(sub)
        lines += _nested(sub, f"{prefix}{name}.", min(level + 1, 4))
    return lines


@page("reference/config.md")
def config_page() -> str:
    from rig.specs.config import RigConfig

    lines = ["# Rig configuration", "",
             "A rig config is YAML; every field left out keeps the default below, so a config names "
             "only what differs from the built-in simulated rig. Generated from the dataclasses in "
             "`rig.specs.config` that read the file (`rig config` writes one for a real rig).", "",
             "## Top level", "", *_dataclass_table(RigConfig, skip=("source_text", "source_path"))]
    lines += _nested(RigConfig, "", 2)
    return "\n".join(lines)


@page("reference/protocol.md")
def protocol_page() -> str:
    from rig.specs import protocol as p

    lines = ["# Protocol files", "",
             "A protocol is YAML: a `name`, an optional `description`, `steps` run in order, and "
             "optionally `repeat` with `rest_s` between repeats and `limits` tighter than the rig's. "
             "Positions are in mm from the trial's zero (the start position, or the contact an "
             "`approach` step found). Generated from the dataclasses in `rig.specs.protocol`; "
             "`rig check FILE` validates a file and prints its plan.", "",
             "## The file", "", *_dataclass_table(p.Protocol, skip=("steps", "source_path", "source_text",
                                                                  "limits", "name", "description")),
             "## `limits:`", "", *_dataclass_table(p.ProtocolLimits), "## Steps", "",
             "Each step is a mapping with one key, its kind (`- ramp: {to_mm: 8, speed_mm_s: 2}`).", ""]
    for cls in typing.get_args(p.Step):
        kind = next(f.default for f in dataclasses.fields(cls) if f.name == "kind")
        lines += [f"### `{kind}`", ""]
        lines += _doc(cls) + _dataclass_table(cls, skip=("line", "kind"))
    return "\n".join(lines)


# --- the log -----------------------------------------------------------------------------------

@page("reference/log.md")
def log_page() -> str:
    from rig.recording.messages import MESSAGES

    lines = ["# The log's messages", "",
             "Every trial is one MCAP file; each topic below is a channel with a JSON schema stored "
             "in the file (so Foxglove, the `mcap` tools and any MCAP reader open it). Generated "
             "from `rig.recording.messages`, the one definition the loop writes, the live view "
             "sends and `rig replay` reads.", "",
             "Metadata `trial` (specimen, operator, protocol, start time, software version, config "
             "digest, clock) is written first and `outcome` last; the protocol and config files are "
             "attached exactly as run. A writer thread does the encoding, compression and disk I/O, "
             "and flushes and fsyncs about once a second, so a crash loses at most about a second. "
             "A log without `outcome` was interrupted: `rig replay` reads it up to its last flush, "
             "and the daemon rewrites it as a finished file marked `interrupted` when it next "
             "starts.", ""]
    lines += ["| topic | schema | what it is |", "|---|---|---|"]
    lines += [f"| [`{m.topic}`](#{m.title.lower().replace('.', '')}) | `{m.title}` | {_cell(m.description)} |"
              for m in MESSAGES]
    lines.append("")
    for m in MESSAGES:
        lines += [f"## {m.title}", "", f"Topic `{m.topic}`. {m.description}", "",
                  "| field | type | required | what it is |", "|---|---|---|---|"]
        for f in m.fields:
            required = "yes" if f.required else ("in some messages" if f.sparse else "in some logs")
            lines.append(f"| `{f.name}` | {f.type} | {required} | {_cell(f.description)} |")
        lines.append("")
    return "\n".join(lines)


# --- the effects -------------------------------------------------------------------------------

@page("reference/effects.md")
def effects_page() -> str:
    from rig.models.catalogue import CATALOGUE, catalogue_json, named_models

    data = catalogue_json(dict(CATALOGUE))
    lines = ["# The effects catalogue", "",
             "A force model is a sum of effects; each effect is a term with its equation, its "
             "parameters (units and bounds) and the signature its absence leaves in a trial's "
             "residual, which is how `--explain` names what a model is missing. Generated from "
             "`rig.models.catalogue`; `rig models` prints the same.", "",
             "| effect | stage | equation | its absence shows as |", "|---|---|---|---|"]
    for name, e in data["effects"].items():
        lines.append(f"| [`{name}`](#{name.replace('_', '_')}) | {e['stage']} | `{_cell(e['equation'])}` | "
                     f"{_cell(e['signature'])} |")
    lines.append("")
    for name, e in data["effects"].items():
        lines += [f"## {name}", "", f"`{e['equation']}` ({e['stage']}): {e['signature']}.", "",
                  "| parameter | unit | start | lower | upper |", "|---|---|---|---|---|"]
        lines += [f"| `{p['name']}` | {p['unit']} | {p['init']:g} | {p['lo']:g} | {p['hi']:g} |"
                  for p in e["params"]]
        lines.append("")
    models = named_models(dict(CATALOGUE))
    lines += ["## Named models", "", "`--model NAME` of `rig analyze` takes these:", "",
              *[f"- `{m}`" for m in models], ""]
    return "\n".join(lines)

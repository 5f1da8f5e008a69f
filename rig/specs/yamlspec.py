"""YAML with positions: every value keeps its line and column so errors can say where.

`load_marked` parses with `yaml.SafeLoader` (no arbitrary objects) into `Marked` nodes;
`MapView` reads fields from a mapping with type and range checks, and reports unknown
keys with the nearest valid spelling. `bind` fills a dataclass tree from a mapping,
using the dataclass fields (and their `metadata`) as the schema.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any

import yaml

from rig.errors import SpecError, did_you_mean


@dataclass
class Marked:
    """A YAML value (plain Python for scalars, dict/list of Marked otherwise) with its position."""

    value: Any
    line: int  # 1-based
    column: int  # 1-based
    key_line: int | None = None  # where the key naming this value sits, for "unknown key" errors
    key_column: int | None = None

    def plain(self) -> Any:
        """The value with all marks stripped."""
        if isinstance(self.value, dict):
            return {k: v.plain() for k, v in self.value.items()}
        if isinstance(self.value, list):
            return [v.plain() for v in self.value]
        return self.value


# A YAML alias repeats a node without copying it: nested aliases grow exponentially as they
# are expanded ("billion laughs"), and an alias inside its own anchor never ends. No rig file
# comes near these limits; a file past them is refused before any time is spent on it.
MAX_NODES = 10_000  # values after every alias is expanded
MAX_DEPTH = 64  # mappings and lists nested in each other


class _Expansion:
    def __init__(self, path: str) -> None:
        self.path = path
        self.nodes = 0
        self.open: set[int] = set()  # ids of the nodes being expanded (a cycle revisits one)

    def fail(self, node: yaml.Node, message: str) -> SpecError:
        return SpecError(message, path=self.path, line=node.start_mark.line + 1,
                         column=node.start_mark.column + 1)


def _from_node(node: yaml.Node, path: str, ex: _Expansion | None = None, depth: int = 0) -> Marked:
    ex = ex or _Expansion(path)
    ex.nodes += 1
    if ex.nodes > MAX_NODES:
        raise ex.fail(node, f"more than {MAX_NODES} values once its aliases (*name) are expanded: "
                            "too many repeats of an anchor (&name)")
    if depth > MAX_DEPTH:
        raise ex.fail(node, f"nested more than {MAX_DEPTH} levels deep")
    if id(node) in ex.open:
        raise ex.fail(node, "an alias (*name) inside its own anchor (&name): the value would never end")
    line, col = node.start_mark.line + 1, node.start_mark.column + 1
    if isinstance(node, yaml.MappingNode):
        ex.open.add(id(node))
        out: dict[str, Marked] = {}
        for knode, vnode in node.value:
            if not isinstance(knode, yaml.ScalarNode):
                raise SpecError("mapping keys must be plain names", path=path,
                                line=knode.start_mark.line + 1, column=knode.start_mark.column + 1)
            key = str(knode.value)
            if key in out:
                raise SpecError(f"key '{key}' appears twice", path=path,
                                line=knode.start_mark.line + 1, column=knode.start_mark.column + 1)
            child = _from_node(vnode, path, ex, depth + 1)
            child.key_line = knode.start_mark.line + 1
            child.key_column = knode.start_mark.column + 1
            out[key] = child
        ex.open.discard(id(node))
        return Marked(out, line, col)
    if isinstance(node, yaml.SequenceNode):
        ex.open.add(id(node))
        items = [_from_node(n, path, ex, depth + 1) for n in node.value]
        ex.open.discard(id(node))
        return Marked(items, line, col)
    # Scalars: let SafeLoader resolve the tag (int, float, bool, null, str) exactly as safe_load would.
    loader = yaml.SafeLoader("")
    try:
        value = loader.construct_object(node, deep=True)
    finally:
        loader.dispose()
    return Marked(value, line, col)


def read_text(path: str | Path, what: str = "file") -> str:
    """A text file's contents, or a `SpecError` saying why it cannot be read."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecError(f"{what} not found", path=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(f"cannot read {what}: {exc}", path=str(path)) from None


def load_marked(path: str | Path, text: str | None = None) -> Marked:
    """Parse a YAML file into marked nodes. Syntax errors become `SpecError` with file:line:col."""
    path = str(path)
    if text is None:
        text = read_text(path)
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = exc.problem or exc.context or "invalid YAML"
        raise SpecError(f"YAML syntax error: {problem}", path=path,
                        line=mark.line + 1 if mark else None,
                        column=mark.column + 1 if mark else None) from None
    except yaml.YAMLError as exc:
        raise SpecError(f"YAML error: {exc}", path=path) from None
    if node is None:
        raise SpecError("file is empty", path=path, line=1, column=1)
    return _from_node(node, path)


_TYPE_NAMES = {bool: "true/false", int: "an integer", float: "a number", str: "text"}


class MapView:
    """Checked access to the fields of one YAML mapping."""

    def __init__(self, node: Marked, path: str, where: str = "") -> None:
        if not isinstance(node.value, dict):
            raise SpecError(f"expected a mapping (key: value), got {_describe(node.value)}",
                            path=path, line=node.line, column=node.column, field=where or None)
        self.node = node
        self.path = path
        self.where = where

    def _field(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def error(self, key: str | None, message: str) -> SpecError:
        node = self.node.value.get(key) if key else None
        target = node or self.node
        return SpecError(message, path=self.path, line=target.line, column=target.column,
                         field=self._field(key) if key else (self.where or None))

    def check_keys(self, allowed: typing.Iterable[str]) -> None:
        allowed = list(allowed)
        for key, child in self.node.value.items():
            if key not in allowed:
                hint = did_you_mean(key, allowed) or f" (expected one of: {', '.join(allowed)})"
                raise SpecError(f"unknown key '{key}'{hint}", path=self.path,
                                line=child.key_line or child.line,
                                column=child.key_column or child.column,
                                field=self.where or None)

    def has(self, key: str) -> bool:
        return key in self.node.value and self.node.value[key].value is not None

    def get(self, key: str) -> Marked | None:
        return self.node.value.get(key)

    def require(self, key: str) -> Marked:
        if not self.has(key):
            raise SpecError(f"missing required field '{key}'", path=self.path,
                            line=self.node.line, column=self.node.column,
                            field=self.where or None)
        return self.node.value[key]

    def number(self, key: str, default: float | None = None, *, required: bool = False,
               gt: float | None = None, ge: float | None = None, le: float | None = None) -> float | None:
        if not self.has(key):
            if required:
                self.require(key)
            return default
        value = self.node.value[key].value
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, f"expected a number, got {_describe(value)}{exponent_hint(value)}")
        value = float(value)
        _check_range(self, key, value, gt=gt, ge=ge, le=le)
        return value

    def integer(self, key: str, default: int | None = None, *, ge: int | None = None) -> int | None:
        if not self.has(key):
            return default
        value = self.node.value[key].value
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {_describe(value)}"
                                  f"{exponent_hint(value, integer=True)}")
        _check_range(self, key, value, ge=ge)
        return value

    def text(self, key: str, default: str | None = None, *, required: bool = False) -> str | None:
        if not self.has(key):
            if required:
                self.require(key)
            return default
        value = self.node.value[key].value
        if not isinstance(value, str):
            raise self.error(key, f"expected text, got {_describe(value)}")
        return value


def range_problem(value: float, gt: float | None = None, ge: float | None = None,
                  le: float | None = None, *, finite: bool = True) -> str | None:
    """What is wrong with `value` against the bounds, or None.

    NaN is never a value; infinity only where a field says it accepts it (`finite=False`): a
    limit of .inf switches a check off without a word, and a duration of .inf never ends.
    """
    if value != value:  # NaN
        return "must be a number, not NaN (.nan)"
    if finite and math.isinf(value):
        return f"must be a finite number, not {'-' if value < 0 else ''}.inf"
    if gt is not None and not value > gt:
        return f"must be greater than {gt:g}, got {value:g}"
    if ge is not None and not value >= ge:
        return f"must be at least {ge:g}, got {value:g}"
    if le is not None and not value <= le:
        return f"must be at most {le:g}, got {value:g}"
    return None


def _check_range(view: MapView, key: str, value: float, *, gt: float | None = None,
                 ge: float | None = None, le: float | None = None) -> None:
    problem = range_problem(value, gt, ge, le)
    if problem:
        raise view.error(key, problem)


# YAML 1.1 (PyYAML's) reads a float only with a dot in the mantissa and a sign in the exponent:
# 1e12, 1.5e3 and 1.0e12 are text there. The error says how to write the number instead.
_EXPONENT_TEXT = re.compile(r"[-+]?(?:[0-9][0-9_]*)?(?:\.[0-9_]*)?[eE][-+]?[0-9]+")


def exponent_hint(value: Any, *, integer: bool = False) -> str:
    """For text that is a number in exponent notation YAML 1.1 does not read as one: how to
    write it (' (YAML reads 1e12 as text: write 1.0e+12 or 1000000000000)'); else ''. Where an
    integer is expected only its digits will do."""
    if not isinstance(value, str) or not _EXPONENT_TEXT.fullmatch(value.strip()):
        return ""
    text = value.strip().replace("_", "")
    try:
        number = float(text)
    except ValueError:
        return ""
    mantissa, exponent = re.split("[eE]", text)
    if not math.isfinite(number) or not any(c.isdigit() for c in mantissa):
        return ""
    sign, digits = (mantissa[0], mantissa[1:]) if mantissa[0] in "+-" else ("", mantissa)
    whole, _, fraction = digits.partition(".")
    mantissa = f"{sign}{whole or '0'}.{fraction or '0'}"
    if exponent[0] not in "+-":
        exponent = "+" + exponent
    plain = format(Decimal(repr(number)), "f")  # positional: repr would give 1e-20 back
    plain = plain.removesuffix(".0") if number == int(number) else plain
    if integer:
        fits = number == int(number) and len(plain) <= 24
        return f" (YAML reads {value.strip()} as text: write {plain})" if fits else ""
    also = f" or {plain}" if len(plain) <= 24 else ""
    return f" (YAML reads {value.strip()} as text: write {mantissa}e{exponent}{also})"


def _describe(value: Any) -> str:
    if value is None:
        return "nothing (null)"
    if isinstance(value, bool):
        return f"{str(value).lower()} (true/false)"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, str):
        return f"text '{value}'"
    return f"{type(value).__name__} {value!r}"


# ---------------------------------------------------------------- dataclass binding

def bind(cls: type, node: Marked | None, path: str, where: str = "") -> Any:
    """Build dataclass `cls` from a mapping node; absent fields keep their defaults.

    Field metadata understood: `gt`, `ge`, `le` (numeric bounds), `choices` (allowed strings),
    `infinite_ok` (the field accepts .inf; no field does today), `why` (appended to a bound's
    message: what the bound protects).
    """
    if node is None:
        return cls()
    view = MapView(node, path, where)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    node = _renamed(cls, node, view)
    view = MapView(node, path, where)
    view.check_keys(fields)
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, child in node.value.items():
        kwargs[name] = _bind_value(hints[name], child, view, name, fields[name].metadata)
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as exc:
        raise SpecError(str(exc), path=path, line=node.line, column=node.column,
                        field=where or None) from None


class DeprecatedKey(FutureWarning):
    """A config key written under its old name: still read, under its new one."""


def _renamed(cls: type, node: Marked, view: MapView) -> Marked:
    """`node` with the keys `cls.RENAMED_KEYS` (old name -> new) under their new names, each
    old one warned about (DeprecatedKey) with where it stands; both names at once are an error."""
    renamed = getattr(cls, "RENAMED_KEYS", {})
    if not isinstance(node.value, dict) or not renamed.keys() & node.value.keys():
        return node
    import warnings

    items = {}
    for key, child in node.value.items():
        new = renamed.get(key)
        if new is None:
            items[key] = child
            continue
        if new in node.value:
            raise view.error(key, f"'{key}' is the old name of '{new}': give one of them")
        warnings.warn(f"{view.path}:{child.key_line}: {view._field(key)} is deprecated, read as "
                      f"{view._field(new)}: write '{new}' (the fitted parameter's name)", DeprecatedKey,
                      stacklevel=4)
        items[new] = child
    return dataclasses.replace(node, value=items)


def _bind_value(tp: Any, child: Marked, view: MapView, name: str, meta: typing.Mapping) -> Any:
    field = view._field(name)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if child.value is None and type(None) in args:
            return None
        tp = next(a for a in args if a is not type(None))
        origin, args = typing.get_origin(tp), typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return bind(tp, child, view.path, field)
    if origin in (list, tuple):
        if not isinstance(child.value, list):
            raise view.error(name, f"expected a list, got {_describe(child.value)}")
        item_tp = args[0]
        fixed = origin is tuple and len(args) > 1 and args[1] is not Ellipsis
        if fixed and len(child.value) != len(args):
            raise view.error(name, f"expected a list of {len(args)} values, got {len(child.value)}")
        items = [_scalar(item_tp, c, view.path, f"{field}[{i}]", meta) for i, c in enumerate(child.value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        sub = MapView(child, view.path, field)
        return {k: _bind_value(args[1], v, sub, k, meta) for k, v in child.value.items()}
    return _scalar(tp, child, view.path, field, meta)


def _scalar(tp: Any, child: Marked, path: str, field: str, meta: typing.Mapping) -> Any:
    value = child.value

    def fail(msg: str) -> SpecError:
        return SpecError(msg, path=path, line=child.line, column=child.column, field=field)

    if tp is Any:
        return child.plain()
    if tp is bool:
        if not isinstance(value, bool):
            raise fail(f"expected true/false, got {_describe(value)}")
        return value
    if tp in (int, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise fail(f"expected {_TYPE_NAMES[tp]}, got {_describe(value)}"
                       f"{exponent_hint(value, integer=tp is int)}")
        if tp is int and not isinstance(value, int):
            raise fail(f"expected an integer, got {value!r}")
        value = tp(value)
        problem = range_problem(value, meta.get("gt"), meta.get("ge"), meta.get("le"),
                                finite=not meta.get("infinite_ok", False))
        if problem:
            raise fail(problem + (f": {meta['why']}" if "why" in meta else ""))
        return value
    if tp is str:
        if not isinstance(value, str):
            raise fail(f"expected text, got {_describe(value)}")
        if "choices" in meta and value not in meta["choices"]:
            raise fail(f"'{value}' is not one of: {', '.join(meta['choices'])}"
                       f"{did_you_mean(value, meta['choices'])}")
        return value
    raise fail(f"unsupported field type {tp}")  # pragma: no cover - schema bug, not user error

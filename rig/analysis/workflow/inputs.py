"""The records of one `rig analyze` read and prepared, with the effects it may use and the indenter
they name: what every analysis starts from (`load_inputs`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.analysis.trials.data import SEGMENTS, TrialData, prepare
from rig.errors import RigError, SpecError
from rig.models.catalogue import (
    CATALOGUE,
    CONTACT,
    CONTACT_POINT,
    NAMED_MODELS,
    build_model,
    contact_effect,
)
from rig.models.contact import Indenter, parse_indenter
from rig.models.core import Effect
from rig.models.instrument import ADHESION, BOTTOM_EFFECTS, BOTTOM_SHAPES, bottom_effect
from rig.models.plugins import check_plugin_effect, load_plugin
from rig.models.viscoelastic import MODELS as VISCOELASTIC_EFFECTS
from rig.records import ReadOptions, Record, read_record


@dataclass
class Inputs:
    """The records of one request prepared as trials (fitted, and held out), the effects it may use (the
    catalogue, the indenter's, the plugins'), and the indenter with where it came from and Poisson's ratio."""

    trials: list[TrialData]
    holdout: list[TrialData]
    registry: dict[str, Effect]
    indenter: Indenter | None = None
    indenter_from: str = ""  # where the geometry came from: the command line, a file's header, a config
    poisson: float = 0.5


ROUND = ("paraboloid", "sphere")  # a bare shape that takes a file's radius


def _named_indenter(trials: list[Record]) -> tuple[Indenter, str] | None:
    """The indenter the records name (an instrument's header, a rig log's config), and where from;
    records that name different ones are refused rather than one of them chosen."""
    found = [(parse_indenter(t.meta["indenter"]), t) for t in trials if t.meta.get("indenter")]
    if not found:
        return None
    if len({ind for ind, _ in found}) > 1:
        raise RigError("the records name different indenters (" + ", ".join(f"{Path(t.name).name}: {ind.spec()}"
                       for ind, t in found) + "): analyse them apart, or give --indenter")
    ind, t = found[0]
    name = Path(t.name).name
    where = f"the config in {name}" if t.source == "mcap" else f"the header of {name}"
    return ind, where


def load_inputs(paths: list[str], holdout: list[str], plugins: list[str],
                options: ReadOptions | int | None = None, *, indenter: str | None = None,
                poisson: float = 0.5, segment: str = "all", records: list[Record] | None = None,
                form: str = "auto", approach: bool = False) -> Inputs:
    """The records prepared, and the catalogue with the user's effects and, when the indenter
    is known (`indenter`, else the first record that names its own), its elastic contact.
    `records`, when given, are the inputs already read (one per path: a batch reads a map once).
    `segment` "auto": an instrument's approach segment alone where the record has one and
    `approach` says the model is an elastic contact alone (what AFM tools fit), else all of it."""
    if not (math.isfinite(poisson) and -1.0 < poisson <= 0.5):
        raise RigError(f"--poisson {poisson:g}: Poisson's ratio lies in (-1, 0.5] (0.5: incompressible, "
                       "the usual choice for tissue and cells)")
    registry = dict(CATALOGUE)
    for p in plugins:
        for e in load_plugin(p):
            if e.name in CATALOGUE:
                raise RigError(f"{p}: effect '{e.name}' would replace the catalogue's; rename it")
            registry[e.name] = e
    recs = records if records is not None else [read_record(p, options) for p in paths]
    if segment not in (*SEGMENTS, "auto"):
        raise RigError(f"--segment {segment}: expected auto, {' or '.join(SEGMENTS)}")
    ind, source = None, ""
    named = _named_indenter(recs)
    shape = (indenter or "").strip().lower()
    if shape in ROUND and named and named[0].kind in ROUND:
        # a round shape alone takes its size from the file: `--indenter paraboloid` on a file that
        # names a sphere fits Hertz's approximation with the sphere's radius
        ind = parse_indenter(f"{shape}:R={named[0].R_m}m")
        source = f"--indenter, its radius from {named[1]}"
    elif indenter:
        try:
            ind, source = parse_indenter(indenter), "--indenter"
        except SpecError as exc:
            raise RigError(f"--indenter: {exc.message}") from None
    elif named:
        ind, source = named
    if ind is not None:
        registry[CONTACT] = contact_effect(ind, poisson)
        registry[CONTACT_POINT.name] = CONTACT_POINT
    # a pull on the way out is kept where adhesion can describe it: with an indenter's contact
    pull = ind is not None
    trials = [prepare(r, str(p), _segment(r, segment, approach), form, keep_pull=pull)
              for r, p in zip(recs, paths, strict=True)]
    thick = {t.meta.get("thickness_m") for t in trials}
    if ind is not None and ind.kind in BOTTOM_SHAPES and len(thick) == 1 and None not in thick:
        # the specimen's thickness, which the logs' header keeps: the bottom effect's, not fitted
        h = thick.pop()
        registry.update({n: bottom_effect(ind, poisson, bonded, h) for n, bonded in BOTTOM_EFFECTS.items()})
    held = []
    for p in holdout:
        r = read_record(p, options)
        held.append(prepare(r, str(p), _segment(r, segment, approach), "force" if form == "force" else "auto",
                            keep_pull=pull))
    for e in registry.values():
        if e.source == "plugin":
            m = build_model("linear_elastic", [e.name], registry)
            check_plugin_effect(e, lambda m=m: m.predict({p.name: p.init for p in m.params}, trials[0].motion))
    return Inputs(trials, held, registry, ind, source, poisson)


def _segment(rec: Record, segment: str, approach: bool) -> str:
    """The segment `prepare` is given for `rec` (see `load_inputs`)."""
    if segment != "auto":
        return segment
    has = rec.segment is not None and bool(np.any(rec.segment == "approach"))
    return "approach" if approach and has else "all"


# what a reader of the file recorded that qualifies every number fitted to it (rig.records): said in
# the text, the table and the map report, not only in --json's notes
CAVEAT_PHRASES = ("no spring constant", "t_s is the sample number", "does not mark the approach",
                  "no time column")


def caveats(t: TrialData) -> list[str]:
    """The record's notes that qualify what is fitted to it (no spring constant, time as the
    sample number, segments guessed)."""
    return [n for n in t.notes if any(p in n for p in CAVEAT_PHRASES)]


def elastic_only(model: str, add: list[str]) -> bool:
    """Whether a model is an indenter's elastic contact with nothing that needs the way out: no
    adhesion (the pull-off), no viscoelastic contact (the relaxation it shows on the retract)."""
    names = NAMED_MODELS.get(model, [model]) + list(add)
    return CONTACT in names and not any(n == ADHESION or n in VISCOELASTIC_EFFECTS.values() for n in names)

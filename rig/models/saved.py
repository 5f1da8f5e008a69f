"""A fitted model on disk (`rig analyze ... --save MODEL.json`), and back.

The file carries what it takes to run the model again and to judge it: the effects, the
parameters (SI, with units and standard errors), the trials and noise it was fitted on,
and the software version. Only catalogue effects are saved: a plugin's code is not.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from rig import __version__
from rig.errors import RigError
from rig.models.catalogue import CATALOGUE
from rig.models.core import Model, Param

FORMAT = "indentation-rig model 1"


@dataclass
class SavedModel:
    """A fitted model as `rig analyze --save` writes it for the loop: the model, its values (SI)
    and standard errors, the trials it was fitted on, the noise and the error there. The records'
    own parameters (where each surface and zero lay) are not kept: the loop knows its own."""

    model: Model
    values: dict[str, float]  # SI
    stderr: dict[str, float | None] = field(default_factory=dict)
    trials: list[str] = field(default_factory=list)
    noise_N: float | None = None
    rmse_N: float | None = None
    software_version: str = __version__
    source: str = ""

    def as_dict(self) -> dict:
        units = {p.name: p.unit for p in self.model.params}
        return {"format": FORMAT, "model": self.model.name, "effects": self.model.effect_names,
                "parameters": {k: {"value": v, "unit": units[k], "stderr": self.stderr.get(k)}
                               for k, v in self.values.items()},
                "fitted_on": {"trials": self.trials, "noise_N": self.noise_N, "rmse_N": self.rmse_N},
                "software_version": self.software_version}

    def text(self) -> str:
        return json.dumps(self.as_dict(), indent=2) + "\n"

    def describe(self) -> str:
        lines = [f"model     {self.model.name}  ({' + '.join(self.model.effect_names)})"]
        if self.source:
            lines.insert(0, f"file      {self.source}")
        for p in self.model.params:
            err = self.stderr.get(p.name)
            e = f" +/- {err:.3g}" if err is not None else ""
            lines.append(f"  {p.name:<18} {self.values[p.name]:>12.5g}{e}  {p.unit}")
        if self.trials:
            lines.append(f"fitted on {', '.join(self.trials)}")
        if self.noise_N is not None and self.rmse_N is not None:
            lines.append(f"          RMSE {self.rmse_N:.4g} N, noise {self.noise_N:.4g} N")
        lines.append(f"software  indentation-rig {self.software_version}")
        return "\n".join(lines)


def savable(model) -> str | None:
    """Why `model` cannot be saved to run in the loop, or None: the loop rebuilds a saved model
    from the catalogue alone, so a plugin's effect or an indenter's contact (hertz) stays out."""
    indenter = [e.name for e in model.effects if e.source.startswith("indenter")]
    if indenter:
        return (f"effect(s) {', '.join(indenter)} hold the indenter's geometry, which a saved model does "
                "not carry yet; save a model of catalogue effects")
    plugin = [e.name for e in model.effects
              if e.source != "catalogue" and not e.of_record]
    if plugin:
        return f"effect(s) {', '.join(plugin)} come from a plugin; only catalogue effects can be saved"
    return None


def from_fit(res, trials: list[str]) -> SavedModel:
    """The `SavedModel` of a fit, or `RigError` if its model cannot run in the loop."""
    why = savable(res.model)
    if why:
        raise RigError(f"--save: {why}")
    # the records' own parameters (where each record's surface and zero lay) describe those
    # records, not the tissue: the loop knows its own surface and tare
    model = Model([e for e in res.model.effects if not e.of_record], res.model.name)
    keep = set(model.param_names)
    stderr = {k: (e if e is not None and math.isfinite(e) else None)
              for k, e in res.stderr.items() if k in keep}
    values = {k: v for k, v in res.values.items() if k in keep}
    return SavedModel(model, values, stderr, trials, res.noise_N, res.overall.rmse_N)


def save(saved: SavedModel, path: str | Path) -> Path:
    """Write `saved` to `path` as JSON; `RigError` if it cannot be written."""
    path = Path(path)
    try:
        path.write_text(saved.text())
    except OSError as exc:
        raise RigError(f"cannot write {path}: {exc.strerror}") from None
    return path


def loads(text: str, source: str = "<model>") -> SavedModel:
    """The saved model in `text`, checked: `RigError` naming `source` and what is wrong."""
    def bad(msg: str) -> RigError:
        return RigError(f"{source}: {msg}")

    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise bad(f"not JSON (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise bad(f"not a saved model (expected \"format\": \"{FORMAT}\"; write one with "
                  "`rig analyze ... --save MODEL.json`)")
    effects = data.get("effects")
    if not isinstance(effects, list) or not effects:
        raise bad("\"effects\" must be a non-empty list")
    missing = [e for e in effects if e not in CATALOGUE]
    if missing:
        raise bad(f"unknown effect(s) {', '.join(map(str, missing))} (`rig models` lists the catalogue)")
    try:
        model = Model([CATALOGUE[e] for e in effects], name=str(data.get("model") or ""))
    except ValueError as exc:
        raise bad(str(exc)) from None
    params = data.get("parameters")
    if not isinstance(params, dict):
        raise bad("\"parameters\" must be an object")
    values, stderr = {}, {}
    for name in model.param_names:
        entry = params.get(name)
        value = entry.get("value") if isinstance(entry, dict) else None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad(f"parameter '{name}' needs a numeric \"value\"")
        values[name] = float(value)
        problem = _out_of_bounds(next(p for p in model.params if p.name == name), float(value))
        if problem:
            raise bad(f"parameter '{name}' {problem}")
        err = entry.get("stderr")
        stderr[name] = float(err) if isinstance(err, int | float) and not isinstance(err, bool) else None
    fitted = data.get("fitted_on") or {}
    return SavedModel(model, values, stderr, list(fitted.get("trials") or []), fitted.get("noise_N"),
                      fitted.get("rmse_N"), str(data.get("software_version", "?")), source)


def _out_of_bounds(p: Param, value: float) -> str | None:
    """What is wrong with a saved value against its parameter's bounds, or None.

    Catalogue bounds are in the fitted record's own scales, which a saved model does not keep:
    what holds at any scale is checked (the sign a bound of zero or beyond sets, and every bound
    of a dimensionless parameter); a parameter in SI is checked against its bounds as written.
    """
    unit = "" if p.unit == "1" else f" {p.unit}"
    if not math.isfinite(value):
        return f"= {value}{unit}: not a finite number"
    lo, hi = p.lo, p.hi
    if p.relative and p.unit != "1":
        lo = 0.0 if lo >= 0 else -math.inf
        hi = 0.0 if hi <= 0 else math.inf
    strict_lo = p.relative and p.unit != "1" and p.lo > 0
    strict_hi = p.relative and p.unit != "1" and p.hi < 0
    if value < lo or value > hi or (strict_lo and value <= lo) or (strict_hi and value >= hi):
        low = f"{'>' if strict_lo else '>='} {lo:g}" if lo > -math.inf else ""
        high = f"{'<' if strict_hi else '<='} {hi:g}" if hi < math.inf else ""
        return f"= {value:g}{unit} is outside its bounds ({', '.join(filter(None, (low, high)))}{unit})"
    return None


def runnable(saved: SavedModel) -> SavedModel:
    """`saved`, if every effect has a one-step form for the loop; `RigError` naming those that do not."""
    from rig.models.online import check_online

    check_online(saved.model)
    return saved


def model_for_run(config, path: str | None = None) -> SavedModel | None:
    """The model a trial runs: `path` (the command line), else the config's `model:` (relative to
    the config file); None when neither names one."""
    if not path and config.model:
        source = Path(config.source_path)
        base = source.parent if source.suffix in (".yaml", ".yml") else Path()
        path = str(base / config.model)
    return runnable(load(path)) if path else None


def load(path: str | Path) -> SavedModel:
    """The saved model in the file at `path` (`loads`)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise RigError(f"cannot read model file {path}: {exc.strerror}") from None
    return loads(text, str(path))

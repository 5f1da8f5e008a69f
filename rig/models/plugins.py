"""User effects: a decorated function in a Python file, loaded with `--plugin FILE.py`.

    import numpy as np
    from rig.models import Param, effect

    @effect(stage="sensor", params=[Param("pump_N", "N", 0.05), Param("pump_Hz", "Hz", 1.0, 0.05, 20.0)],
            equation="a sin(2 pi f t)", signature="residual oscillating at a fixed frequency")
    def pump(m, force, pump_N, pump_Hz):
        return pump_N * np.sin(2 * np.pi * pump_Hz * m.t_s)

The function's arguments after the stage's inputs are the parameters, by name.
"""

from __future__ import annotations

import importlib.util
import sys
import traceback
from collections.abc import Callable
from pathlib import Path

from rig.errors import RigError
from rig.models.core import STAGES, Effect, Param

_LOADING: list[Effect] = []


def effect(*, stage: str, params: list[Param], equation: str = "", signature: str = "",
           name: str | None = None) -> Callable:
    """Turn a function into an `Effect` (and register it while a plugin file loads)."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}")

    def wrap(fn: Callable) -> Effect:
        e = Effect(name=name or fn.__name__, stage=stage, params=tuple(params), fn=fn,
                   equation=equation or fn.__doc__ or fn.__name__,
                   signature=signature or "(user effect)", source="plugin")
        _LOADING.append(e)
        return e

    return wrap


def load_plugin(path: str | Path) -> list[Effect]:
    """Run a plugin file and return the effects it defines; errors name the file and line."""
    path = Path(path).resolve()
    if not path.is_file():
        raise RigError(f"{path}: plugin file not found")
    spec = importlib.util.spec_from_file_location(f"rig_plugin_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    _LOADING.clear()
    try:
        spec.loader.exec_module(module)
    except SyntaxError as exc:
        raise RigError(f"{path}:{exc.lineno}: syntax error: {exc.msg}") from None
    except Exception as exc:  # noqa: BLE001 - any error in user code becomes one clear line
        line = next((f.lineno for f in reversed(traceback.extract_tb(sys.exc_info()[2]))
                     if Path(f.filename).resolve() == path), None)
        where = f"{path}:{line}" if line else str(path)
        raise RigError(f"{where}: {type(exc).__name__}: {exc}") from None
    found = list(_LOADING)
    _LOADING.clear()
    if not found:
        raise RigError(f"{path}: defines no effect (decorate a function with @effect(...))")
    return found


def check_plugin_effect(e: Effect, call: Callable[[], object]) -> None:
    """Run an effect once on real data so a broken one fails with its file and line."""
    try:
        call()
    except Exception as exc:  # noqa: BLE001
        code = getattr(e.fn, "__code__", None)
        tb = traceback.extract_tb(sys.exc_info()[2])
        frame = next((f for f in reversed(tb) if code and f.filename == code.co_filename), None)
        where = f"{frame.filename}:{frame.lineno}" if frame else e.name
        raise RigError(f"{where}: effect '{e.name}' failed: {type(exc).__name__}: {exc}") from None

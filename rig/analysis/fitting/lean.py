"""The prediction of the commonest AFM model, an elastic contact from a fitted contact point
over the record's zero, computed without the general model's machinery.

A map's curve is fitted by some hundred predictions (the contact point's scan and search, the
Newton polish, the Jacobians), and the general `Model.predict` spends most of each on what this
model does not use: the velocity switched on at contact, the stages it lacks. Here the same
operations are done in the same order on the same numbers, so the forces are the same to the
bit; that is checked on the record itself before the fit uses it (`predictor`), and any model
of another form, or one whose forces differ, keeps `Model.predict`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rig.models.catalogue import CONTACT_POINT, RECORD_ZERO
from rig.models.core import Model, Motion

__all__ = ["predictor"]

Predict = Callable[[dict, Motion], np.ndarray]
CHECKED = 64  # samples or so of each record the lean prediction is checked on


def predictor(model: Model, motions: list[Motion], at: dict[str, float]) -> Predict:
    """`model.predict`, or a leaner function giving the same forces for `model` on `motions`
    (checked there at the values `at`, with the contact point also moved to a quarter of each
    record's travel so that the check sees samples on both sides of it)."""
    lean = _lean(model)
    if lean is None:
        return model.predict
    x_c = CONTACT_POINT.params[0].name
    for m in motions:
        inside = float(np.quantile(m.x_m, 0.25))
        # every CHECKED-th sample or so: the lean prediction does the same operations sample by
        # sample, so a model it does not describe (a rate or history term) differs on any
        # stretch, and the whole record's check cost a map a twentieth of its time
        step = max(1, len(m.x_m) // CHECKED)
        part = Motion(m.t_s[::step], m.x_m[::step], m.v_m_s[::step], m.dt_s * step, m.record)
        for values in (at, {**at, x_c: inside}):
            with np.errstate(all="ignore"):
                if not np.array_equal(lean(values, part), model.predict(values, part), equal_nan=True):
                    return model.predict
    return lean


def _lean(model: Model) -> Predict | None:
    """The lean prediction of a model of exactly this form, else None."""
    if model.records != 1 or len(model.effects) != 3:
        return None
    by_stage = {e.stage: e for e in model.effects}
    geometry, drive, sensor = by_stage.get("geometry"), by_stage.get("drive"), by_stage.get("sensor")
    if (geometry is None or drive is None or sensor is None or geometry.fn is not CONTACT_POINT.fn
            or sensor.fn is not RECORD_ZERO.fn or geometry.needs_force or drive.needs_force
            or not drive.linear or len(drive.params) != 1 or not hasattr(drive.fn, "indenter")):
        return None
    contact_fn = drive.fn
    (x_c,), (modulus,), (offset,) = ([p.name for p in e.params] for e in (geometry, drive, sensor))

    def predict(values: dict, m: Motion) -> np.ndarray:
        # as Model.predict: the geometry (its velocity term feeds only rate effects, absent
        # here), the tissue's drive switched on at contact and kept from pulling, the sensor
        d = np.maximum(m.x_m - values[x_c], 0.0)
        contact = d > 0
        xc = np.where(contact, d, 0.0)
        drive_N = np.where(contact, np.zeros_like(xc) + contact_fn(xc, None, values[modulus]), 0.0)
        force = np.maximum(drive_N, 0.0)
        return force + np.full_like(force, values[offset])

    # what rig.analysis.fitting.contact_fit solves this model from: the parameters' names and g, the
    # force per unit modulus at each depth
    predict.parts = (x_c, modulus, offset, lambda d: contact_fn(d, None, 1.0), contact_fn)
    return predict

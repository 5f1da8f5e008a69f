"""A simulated AFM force map: approach-retract force-distance curves on a grid, written in
afmformats' own HDF5 format (one group per curve, as `AFMData.export_data(fmt="hdf5")` writes
it), with the truth beside it as JSON. afmformats reads it like a map an instrument wrote,
and through it rig (rig.records.afm) and nanite.

The sample: a paraboloidal (Hertz) tip of radius R indents an elastic sample whose Young's
modulus varies smoothly over the map (a gradient across x, in log E, and a soft blob), on a
surface that is tilted and uneven, so the contact point differs from curve to curve. Every
curve is taken as a JPK map takes it: the piezo starts at one height for the whole map,
approaches at constant speed until the force has risen by the setpoint (relative to the force
at the start, noise aside), and retracts at constant speed by the same travel. The cantilever is in series
with the sample: the tip lags the piezo by its deflection (force / k), so the force follows
F = f(travel - contact - F/k). The deflection signal carries a baseline offset (a different
one on every curve) and white noise of a set rms, optionally low-passed.

A hidden region of the map carries one effect the rest does not (`MapSpec.region`):

- thin_layer: the sample is a layer of finite thickness bonded to (or lying on) a hard
  substrate, the bottom effect of Dimitriadis et al. 2002 (Biophys. J. 82:2798; their series
  for an incompressible layer under a paraboloid):
  F = F_Hertz (1 + c1 chi + c2 chi^2 + c3 chi^3 + c4 chi^4), chi = sqrt(R delta) / h: stiffer
  with depth;
- drift: the deflection's baseline drifts linearly in time during the curve;
- tilt: virtual deflection, a force linear in the piezo's travel, in and out of contact;
- adhesion: on the retract, the tip stays stuck to the sample past the contact point and the
  force goes negative, linearly, down to the adhesion force, where it lets go;
- drag: hydrodynamic drag on the cantilever, a force proportional to the piezo's velocity, in
  and out of contact (+b v on the approach, -b v on the retract).

The sample is elastic: no relaxation or creep, so the retract retraces the approach (but for
adhesion). The truth file (`<map>.truth.json`) gives per curve the modulus, the contact point,
whether the curve is in the region, the baseline and what the force law was; and the map's
settings and seed. The map is the same for the same settings and seed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.errors import RigError

if TYPE_CHECKING:
    import numpy as np

PROGRESS_AFTER_S = 10.0  # `rig sim-map` says how far it is once a write has taken this long

REGIONS = ("thin_layer", "drift", "tilt", "adhesion", "drag")

# Dimitriadis et al. 2002, an incompressible layer bonded to the substrate (True) or lying on
# it (False), under a paraboloid: the bracket's coefficients of chi, chi^2, chi^3, chi^4 as the
# paper gives them for nu = 0.5
DIMITRIADIS = {True: (1.133, 1.283, 0.769, 0.0975), False: (0.884, 0.781, 0.386, 0.0048)}

# The converters' steps (0.45 pN, 0.015 nm: far below the noise) are powers of two, so the
# stored doubles end in zero bits and gzip halves the file
FORCE_STEP_N = 2.0**-41
HEIGHT_STEP_M = 2.0**-36

COLUMNS = ("force", "height (measured)", "height (piezo)", "segment", "time")


@dataclass(frozen=True)
class MapSpec:
    """What the simulated map holds. Lengths in µm, forces in pN or nN as named, moduli in Pa.

    The modulus: log E runs from `E_range_Pa[0]` to `E_range_Pa[1]` across x, and a soft blob
    (Gaussian, width `blob_width` of the map, at a place the seed picks) pulls it down towards
    the low end by the fraction `blob_depth`. The surface: a plane of slopes `surface_slope`
    (dz/dx, dz/dy) plus three smooth bumps of height up to `surface_bumps_um`. `gap_um` is the
    distance from the start of every curve to the highest point of the surface.
    """

    grid: tuple[int, int] = (8, 8)  # (columns along x, rows along y)
    size_um: tuple[float, float] = (50.0, 50.0)  # the grid's extent, pixel size = size / grid
    center_um: tuple[float, float] = (120.0, -40.0)  # where on the stage the grid is
    radius_um: float = 5.0  # the paraboloid's radius of curvature
    poisson: float = 0.5
    E_range_Pa: tuple[float, float] = (1e3, 20e3)
    blob_depth: float = 0.7
    blob_width: float = 0.18
    spring_constant_N_per_m: float = 0.03
    sensitivity_m_per_V: float = 60e-9
    setpoint_nN: float = 2.0
    rate_Hz: float = 2000.0
    speed_um_per_s: float = 5.0  # approach and retract
    gap_um: float = 2.0
    surface_slope: tuple[float, float] = (0.01, -0.006)
    surface_bumps_um: float = 0.3
    piezo_start_um: float = 40.0  # "height (piezo)" at the start of every curve
    sensor_offset_um: float = 17.5  # "height (measured)" - "height (piezo)": another zero
    noise_pN: float = 10.0  # rms of the deflection noise, in force
    noise_cutoff_Hz: float | None = None  # a first-order low-pass on the noise; None: white
    height_noise_nm: float = 0.0  # rms of the height sensor's own noise
    quantize: bool = True  # force and heights on the steps FORCE_STEP_N and HEIGHT_STEP_M
    baseline_pN: float = -250.0  # the deflection's zero, in force: mean over the map
    baseline_spread_pN: float = 60.0  # and its scatter from curve to curve
    region: str | None = None  # one of REGIONS, or None for none
    region_fraction: float = 0.2  # the region's share of the map's area
    layer_thickness_um: float = 2.0  # thin_layer
    layer_bonded: bool = True  # thin_layer: bonded to the substrate, or lying on it
    drift_pN_per_s: float = 300.0  # drift
    tilt_pN_per_um: float = 150.0  # tilt: virtual deflection per µm of piezo travel
    adhesion_pN: float = 400.0  # adhesion: the force at which the tip lets go
    adhesion_length_nm: float = 300.0  # adhesion: the piezo's travel past contact when it does
    drag_pN_s_per_um: float = 20.0  # drag: force per µm/s of the piezo's velocity (approach positive)

    def problem(self) -> str:
        """What is wrong with the settings, or ''."""
        nx, ny = self.grid
        positive = ("radius_um", "spring_constant_N_per_m", "sensitivity_m_per_V", "setpoint_nN", "rate_Hz",
                    "speed_um_per_s", "gap_um", "layer_thickness_um", "adhesion_length_nm", "blob_width")
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                return f"{name} must be a positive number, not {v!r}"
        if not (isinstance(nx, int) and isinstance(ny, int) and nx >= 1 and ny >= 1):
            return f"grid must be two positive whole numbers, not {self.grid!r}"
        if not all(s > 0 for s in self.size_um):
            return f"size_um must be positive, not {self.size_um!r}"
        lo, hi = self.E_range_Pa
        if not 0 < lo <= hi:
            return f"E_range_Pa must be 0 < low <= high, not {self.E_range_Pa!r}"
        if not 0 <= self.poisson < 0.5 + 1e-12:
            return f"poisson must be in [0, 0.5], not {self.poisson!r}"
        if not 0 <= self.blob_depth < 1:
            return f"blob_depth must be in [0, 1), not {self.blob_depth!r}"
        for name in ("noise_pN", "height_noise_nm", "baseline_spread_pN", "surface_bumps_um", "adhesion_pN"):
            if getattr(self, name) < 0:
                return f"{name} must not be negative"
        if self.noise_cutoff_Hz is not None and not 0 < self.noise_cutoff_Hz < self.rate_Hz / 2:
            return f"noise_cutoff_Hz must be between 0 and half the sample rate ({self.rate_Hz / 2:g} Hz)"
        if self.region is not None and self.region not in REGIONS:
            return f"region must be one of {', '.join(REGIONS)} (or none), not {self.region!r}"
        if not 0 < self.region_fraction < 1:
            return f"region_fraction must be in (0, 1), not {self.region_fraction!r}"
        if self.region == "thin_layer" and abs(self.poisson - 0.5) > 1e-9:
            return "thin_layer: the bottom-effect correction (Dimitriadis et al. 2002) is for an " \
                   "incompressible layer: poisson must be 0.5"
        return ""


# -- the sample over the map --------------------------------------------------------------------


def _pixels(spec: MapSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Grid indices (ix, iy) and positions (m) of every curve in raster order, x fastest, at
    the pixels' centres (afmformats maps a position to an index that way)."""
    import numpy as np

    nx, ny = spec.grid
    iy, ix = np.divmod(np.arange(nx * ny), nx)
    x = (spec.center_um[0] - spec.size_um[0] / 2 + (ix + 0.5) * spec.size_um[0] / nx) * 1e-6
    y = (spec.center_um[1] - spec.size_um[1] / 2 + (iy + 0.5) * spec.size_um[1] / ny) * 1e-6
    return ix, iy, x, y


def _fields(spec: MapSpec, rng: np.random.Generator) -> dict[str, Any]:
    """The sample: modulus, surface height and region over the map, from the seed's draws."""
    import numpy as np

    nx, ny = spec.grid
    ix, iy, _, _ = _pixels(spec)
    u = (ix + 0.5) / nx  # the map in unit coordinates
    v = (iy + 0.5) / ny
    blob = rng.uniform(0.25, 0.75, size=2)
    r2 = (u - blob[0]) ** 2 + (v - blob[1]) ** 2
    s = u * (1 - spec.blob_depth * np.exp(-r2 / (2 * spec.blob_width**2)))
    lo, hi = spec.E_range_Pa
    E = lo * (hi / lo) ** s
    bumps = rng.uniform(0.15, 0.85, size=(3, 2))
    heights = rng.uniform(0.3, 1.0, size=3) * spec.surface_bumps_um
    sx, sy = spec.surface_slope
    z_um = sx * (u - 0.5) * spec.size_um[0] + sy * (v - 0.5) * spec.size_um[1]
    for (bu, bv), hb in zip(bumps, heights, strict=True):
        z_um = z_um + hb * np.exp(-((u - bu) ** 2 + (v - bv) ** 2) / (2 * 0.2**2))
    radius = math.sqrt(spec.region_fraction / math.pi)
    center = rng.uniform(min(radius, 0.5), max(1 - radius, 0.5), size=2)
    d2 = (u - center[0]) ** 2 + (v - center[1]) ** 2
    region = np.zeros(nx * ny, dtype=bool)
    if spec.region is not None:
        region = d2 <= radius**2
        if not region.any():  # a coarse grid: the pixel nearest the centre
            region[int(np.argmin(d2))] = True
        if region.all() and region.size > 1:  # some curves must stay outside
            region[int(np.argmax(d2))] = False
    return {"E_Pa": E, "surface_um": z_um, "region": region,
            "blob_center": blob.tolist(), "region_center": center.tolist(), "region_radius": radius}


# -- one curve ----------------------------------------------------------------------------------


def _contact_force(p: np.ndarray, a: float, b: float,
                   coeffs: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """F(p) = a p^1.5 (1 + sum c_n (b sqrt(p))^n) for p > 0, and dF/dp."""
    import numpy as np

    p = np.maximum(p, 0.0)
    f = np.zeros_like(p)
    df = np.zeros_like(p)
    for n, c in enumerate((1.0, *coeffs)):
        if c:
            e = 1.5 + 0.5 * n
            f += c * b**n * p**e
            df += c * b**n * e * p ** (e - 1)
    return a * f, a * df


def _solve_contact(u: np.ndarray, k: float, a: float, b: float, coeffs: tuple[float, ...]) -> np.ndarray:
    """The contact force where the cantilever (k) and the sample balance: F = f(u - F/k), u the
    piezo's travel past the contact point. Newton from p = u down: g(p) = f(p) + k p - k u is
    increasing and convex in p (every coefficient is positive), so it converges from above."""
    import numpy as np

    F = np.zeros_like(u)
    inside = u > 0
    if not inside.any():
        return F
    uu = u[inside]
    p = uu.copy()
    for _ in range(60):
        f, df = _contact_force(p, a, b, coeffs)
        step = (f + k * p - k * uu) / (df + k)
        p = np.maximum(p - step, 0.0)
        if np.max(np.abs(step)) < 1e-16:
            break
    F[inside] = k * (uu - p)
    return F


def _lowpass(x: np.ndarray, cutoff_Hz: float, rate_Hz: float) -> np.ndarray:
    """First-order low-pass, scaled back to the rms it had (the spec's noise is what is written)."""
    from scipy.signal import lfilter

    alpha = 1 - math.exp(-2 * math.pi * cutoff_Hz / rate_Hz)
    # started at its steady state, scaled by the filter's variance gain for white input,
    # alpha / (2 - alpha)
    y, _ = lfilter([alpha], [1, alpha - 1], x, zi=[(1 - alpha) * x[0]])
    return y * math.sqrt((2 - alpha) / alpha)


def _artefact(spec: MapSpec, effect: str | None, t: np.ndarray, travel: np.ndarray,
              velocity: np.ndarray | None = None) -> np.ndarray:
    """What the deflection shows that the sample does not push: drift in time, virtual
    deflection with the piezo's travel (both nil at the curve's start), or drag with its
    velocity (m/s, towards the sample positive)."""
    if effect == "drag":
        v = spec.speed_um_per_s * 1e-6 + 0.0 * t if velocity is None else velocity
        return spec.drag_pN_s_per_um * 1e-6 * v
    if effect == "drift":
        return spec.drift_pN_per_s * 1e-12 * t
    if effect == "tilt":
        return spec.tilt_pN_per_um * 1e-6 * travel
    return 0.0 * t


def _curve(spec: MapSpec, E: float, contact_m: float, effect: str | None, rng: np.random.Generator) -> dict:
    """Columns and truth of one curve; `contact_m` is the piezo's travel from the start to the
    surface, `effect` the region's effect or None."""
    import numpy as np

    k = spec.spring_constant_N_per_m
    R = spec.radius_um * 1e-6
    a = 4.0 / 3.0 * E / (1 - spec.poisson**2) * math.sqrt(R)
    coeffs: tuple[float, ...] = ()
    b = 0.0
    if effect == "thin_layer":
        coeffs = DIMITRIADIS[spec.layer_bonded]
        b = math.sqrt(R) / (spec.layer_thickness_um * 1e-6)
    setpoint = spec.setpoint_nN * 1e-9
    v = spec.speed_um_per_s * 1e-6
    dt = 1.0 / spec.rate_Hz
    # far enough for the plain law to reach the setpoint, with room to spare: every effect
    # here reaches it sooner or not much later
    depth = (setpoint / a) ** (2 / 3) + setpoint / k
    n_max = math.ceil((contact_m + 1.5 * depth + 0.5e-6) / (v * dt)) + 2
    t = np.arange(n_max) * dt
    travel = v * t
    F_contact = _solve_contact(travel - contact_m, k, a, b, coeffs)
    # the trigger sees the artefacts too (not the noise): they start from nil
    reached = np.nonzero(F_contact + _artefact(spec, effect, t, travel) >= setpoint)[0]
    if not len(reached):
        raise RigError(f"a curve does not reach the setpoint ({spec.setpoint_nN:g} nN) within "
                       f"{travel[-1] * 1e6:.3g} µm of travel: lower the setpoint or the region's effect")
    n_app = int(reached[0]) + 1
    turn = travel[n_app - 1]
    n_ret = max(round(turn / v / dt), 1)
    t_ret = t[n_app - 1] + dt * np.arange(1, n_ret + 1)
    travel_ret = turn - v * dt * np.arange(1, n_ret + 1)
    F_ret = _solve_contact(travel_ret - contact_m, k, a, b, coeffs)
    if effect == "adhesion":
        # stuck past contact: the force falls linearly with the piezo's travel to -adhesion,
        # where the tip lets go
        past = contact_m - travel_ret
        stuck = (past > 0) & (past < spec.adhesion_length_nm * 1e-9)
        F_ret[stuck] = -spec.adhesion_pN * 1e-12 * past[stuck] / (spec.adhesion_length_nm * 1e-9)
    t_all = np.concatenate([t[:n_app], t_ret])
    travel_all = np.concatenate([travel[:n_app], travel_ret])
    F_true = np.concatenate([F_contact[:n_app], F_ret])
    velocity = np.concatenate([np.full(n_app, v), np.full(n_ret, -v)])
    F_art = _artefact(spec, effect, t_all, travel_all, velocity)
    baseline = (spec.baseline_pN + spec.baseline_spread_pN * rng.standard_normal()) * 1e-12
    noise = rng.standard_normal(len(t_all))
    if spec.noise_cutoff_Hz is not None:
        noise = _lowpass(noise, spec.noise_cutoff_Hz, spec.rate_Hz)
    force = F_true + F_art + baseline + spec.noise_pN * 1e-12 * noise
    piezo = spec.piezo_start_um * 1e-6 - travel_all
    measured = piezo + spec.sensor_offset_um * 1e-6
    if spec.height_noise_nm:
        measured = measured + spec.height_noise_nm * 1e-9 * rng.standard_normal(len(t_all))
    if spec.quantize:
        force = np.round(force / FORCE_STEP_N) * FORCE_STEP_N
        piezo = np.round(piezo / HEIGHT_STEP_M) * HEIGHT_STEP_M
        measured = np.round(measured / HEIGHT_STEP_M) * HEIGHT_STEP_M
    segment = np.concatenate([np.zeros(n_app, dtype=np.uint8), np.ones(n_ret, dtype=np.uint8)])
    deepest = turn - contact_m - F_true[n_app - 1] / k
    truth = {
        "E_Pa": E,
        "contact_travel_m": contact_m,
        "contact_height_piezo_m": spec.piezo_start_um * 1e-6 - contact_m,
        "baseline_N": baseline,
        "approach_samples": n_app,
        "retract_samples": n_ret,
        "max_indentation_m": deepest,
        "max_force_N": float(F_true[n_app - 1]),
        "z_range_m": turn,
    }
    columns = {"force": force, "height (measured)": measured, "height (piezo)": piezo, "segment": segment,
               "time": t_all}
    return {"columns": columns, "truth": truth}


# -- the map ------------------------------------------------------------------------------------


def _exporter(h5: Any) -> Callable[[dict, dict], None]:
    """A function writing one curve into the open HDF5 file `h5` as afmformats' own export writes it
    (`AFMData.export_data(h5, fmt="hdf5")`: a group named by the enum, each column a gzip'd and
    checksummed dataset with its unit, the metadata as afmformats parses it in the group's
    attributes, the file's "software" attributes), written in the same order and with the same
    types, so that afmformats, nanite and rig read the same map.

    afmformats' own writer spends 9 ms a curve setting the attributes through h5py's general path
    (39 of them, each type guessed anew), which made a 256x256 map a ten-minute write; here each
    attribute's HDF5 type is made once and the metadata parsed once for what every curve shares."""
    import h5py
    import numpy as np
    from afmformats import __version__ as af_version
    from afmformats.afm_data import column_units
    from afmformats.meta import MetaData
    from h5py import h5a, h5s, h5t

    scalar = h5s.create(h5s.SCALAR)
    types = {}
    for dtype in (np.dtype("<f8"), np.dtype("<i8"), h5py.string_dtype()):
        types[dtype] = (h5t.py_create(dtype, logical=True), h5t.py_create(dtype), dtype)

    def attribute(target, name: str, value: Any) -> None:
        if isinstance(value, str):
            logical, memory, dtype = types[h5py.string_dtype()]
        elif isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
            target.attrs[name] = value  # a type the map does not write: h5py's general path
            return
        elif isinstance(value, (int, np.integer)):
            logical, memory, dtype = types[np.dtype("<i8")]
        else:
            logical, memory, dtype = types[np.dtype("<f8")]
        attr = h5a.create(target.id, name.encode(), logical, scalar)
        attr.write(np.asarray(value, dtype=dtype), mtype=memory)

    parsed: dict[tuple, MetaData] = {}

    h5.attrs["software"] = "afmformats"  # the file's, as afmformats' export sets them before its group
    h5.attrs["software version"] = af_version

    def export(meta: dict, columns: dict) -> None:
        enum = meta["enum"]
        group = h5.create_group(str(enum))
        for col in sorted(columns):  # afmformats' `columns`: sorted, the index column not stored
            data = columns[col]
            if col == "segment":
                data = np.asarray(data, dtype=np.uint8)
            ds = group.create_dataset(name=col, data=data, compression="gzip", fletcher32=True)
            ds.attrs["unit"] = column_units[col]
        # afmformats parses every key (MetaData) and may add some (the segment count); the keys
        # every curve shares are parsed once
        shared = tuple((k, v) for k, v in meta.items() if k not in _PER_CURVE)
        if shared not in parsed:
            parsed.clear()
            parsed[shared] = MetaData(dict(shared))
        md = parsed[shared].__copy__()
        md.update({k: v for k, v in meta.items() if k in _PER_CURVE})
        md["enum"] = int(enum)
        for key in md:
            value = dict.__getitem__(md, key)
            attribute(group, key, str(value) if key == "path" else value)

    return export


# the metadata that differs from curve to curve (everything else is parsed once a map)
_PER_CURVE = frozenset({"path", "enum", "curve id", "grid index x", "grid index y", "position x", "position y",
                        "point count", "duration", "duration approach", "duration retract", "z range"})


def truth_path(path: str | Path) -> Path:
    """Where the truth of the map at `path` is written: `<map>.truth.json` beside it."""
    path = Path(path)
    return path.with_name(path.stem + ".truth.json")


def force_law(spec: MapSpec, in_region: bool) -> dict:
    """The truth's force law for a curve in or out of the region, in words and numbers."""
    law = {"model": "hertz", "indenter": f"paraboloid:R={spec.radius_um:g}um", "poisson": spec.poisson,
           "equation": "F = 4/3 E/(1-nu^2) sqrt(R) d^1.5, d = travel - contact - F/k (tip indentation)"}
    if in_region and spec.region == "thin_layer":
        how = "bonded to" if spec.layer_bonded else "lying on"
        law.update({"bottom_effect": f"Dimitriadis et al. 2002, an incompressible layer {how} a hard substrate",
                    "equation": law["equation"] + " x (1 + c1 chi + c2 chi^2 + c3 chi^3 + c4 chi^4), "
                                                  "chi = sqrt(R d) / h",
                    "coefficients": list(DIMITRIADIS[spec.layer_bonded]),
                    "thickness_m": spec.layer_thickness_um * 1e-6})
    elif in_region and spec.region == "drift":
        law["artefact"] = {"what": "baseline drift linear in time from the curve's start",
                           "N_per_s": spec.drift_pN_per_s * 1e-12}
    elif in_region and spec.region == "tilt":
        law["artefact"] = {"what": "virtual deflection linear in the piezo's travel from the curve's start",
                           "N_per_m": spec.tilt_pN_per_um * 1e-6}
    elif in_region and spec.region == "drag":
        law["artefact"] = {"what": "hydrodynamic drag on the cantilever: N_s_per_m times the piezo's velocity "
                                   "(towards the sample positive: +b v on the approach, -b v on the retract)",
                           "N_s_per_m": spec.drag_pN_s_per_um * 1e-6}
    elif in_region and spec.region == "adhesion":
        law["adhesion"] = {"what": "on the retract, past the contact point the force falls linearly with the "
                                   "piezo's travel to -force_N at length_m, then the tip lets go",
                           "force_N": spec.adhesion_pN * 1e-12, "length_m": spec.adhesion_length_nm * 1e-9}
    return law


def write_map(path: str | Path, spec: MapSpec | None = None, seed: int = 0,
              progress: Callable[[int], None] | None = None) -> Path:
    """Write the map as afmformats' HDF5 (`path`, conventionally .h5) and its truth beside it
    (`truth_path(path)`); the same settings and seed give the same curves. `progress(1)` is
    called as each curve is written. Returns `path`."""
    import numpy as np

    spec = spec or MapSpec()
    why = spec.problem()
    if why:
        raise RigError(f"map settings: {why}")
    try:
        import h5py
        from afmformats import __version__ as af_version
    except ImportError:
        raise RigError("writing an AFM map needs the afmformats package (pip install 'indentation-rig[afm]')") \
            from None
    from rig import __version__

    path = Path(path)
    rng = np.random.default_rng(seed)
    sample = _fields(spec, rng)
    ix, iy, x, y = _pixels(spec)
    top = float(np.max(sample["surface_um"]))
    contact = (spec.gap_um + top - sample["surface_um"]) * 1e-6
    n = len(ix)
    session = f"rig-sim-map-seed{seed}"
    base_meta = {
        "imaging mode": "force-distance",
        "feedback mode": "contact",
        "spring constant": spec.spring_constant_N_per_m,
        "sensitivity": spec.sensitivity_m_per_V,
        "setpoint": spec.setpoint_nN * 1e-9,
        "rate approach": spec.rate_Hz,
        "rate retract": spec.rate_Hz,
        "speed approach": spec.speed_um_per_s * 1e-6,
        "speed retract": spec.speed_um_per_s * 1e-6,
        "grid shape x": spec.grid[0],
        "grid shape y": spec.grid[1],
        "grid size x": spec.size_um[0] * 1e-6,
        "grid size y": spec.size_um[1] * 1e-6,
        "grid center x": spec.center_um[0] * 1e-6,
        "grid center y": spec.center_um[1] * 1e-6,
        "instrument": "rig sim-map (simulated)",
        "software": "rig sim-map",
        "software version": __version__,
        "session id": session,
    }
    curves = []
    path.parent.mkdir(parents=True, exist_ok=True)
    # written beside the target and renamed: a reader never sees half a map
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        # track_order: the groups list in raster order, as the curves were taken
        with h5py.File(tmp, "w", track_order=True) as h5:
            export = _exporter(h5)
            for i in range(n):
                effect = spec.region if sample["region"][i] else None
                c = _curve(spec, float(sample["E_Pa"][i]), float(contact[i]), effect, rng)
                cols = c["columns"]
                n_app, n_ret = c["truth"]["approach_samples"], c["truth"]["retract_samples"]
                meta = dict(base_meta)
                meta.update({
                    "path": path, "enum": i, "curve id": f"{session}:{i}",
                    "grid index x": int(ix[i]), "grid index y": int(iy[i]),
                    "position x": float(x[i]), "position y": float(y[i]),
                    "point count": n_app + n_ret,
                    "duration": (n_app + n_ret) / spec.rate_Hz,
                    "duration approach": n_app / spec.rate_Hz,
                    "duration retract": n_ret / spec.rate_Hz,
                    "z range": c["truth"]["z_range_m"],
                })
                export(meta, cols)
                curves.append({"enum": i, "grid_index": [int(ix[i]), int(iy[i])],
                               "position_m": [float(x[i]), float(y[i])], "in_region": bool(sample["region"][i]),
                               **c["truth"]})
                if progress is not None:
                    progress(1)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    in_region = [c["enum"] for c in curves if c["in_region"]]
    truth = {
        "file": path.name,
        "format": "afmformats HDF5 (one group per curve, named by its enum)",
        "written_by": f"rig {__version__} sim-map",
        "afmformats_version": af_version,
        "seed": seed,
        "spec": asdict(spec),
        "region": {"effect": spec.region, "curves": in_region,
                   "center_unit": sample["region_center"] if spec.region else None,
                   "radius_unit": sample["region_radius"] if spec.region else None},
        "force_law": force_law(spec, False),
        "force_law_in_region": force_law(spec, True) if spec.region else None,
        "modulus_field": {"what": "log E from E_range_Pa[0] to [1] across x; a Gaussian soft blob pulls the "
                                  "fraction blob_depth of it back", "blob_center_unit": sample["blob_center"]},
        "noise": {"rms_N": spec.noise_pN * 1e-12, "cutoff_Hz": spec.noise_cutoff_Hz,
                  "height_rms_m": spec.height_noise_nm * 1e-9, "what": "added to the force column (deflection "
                  "noise in force units); white, or first-order low-passed at cutoff_Hz, at the rms given",
                  "force_step_N": FORCE_STEP_N if spec.quantize else None,
                  "height_step_m": HEIGHT_STEP_M if spec.quantize else None},
        "columns": {"force": "N, baseline and noise included", "height (piezo)": "m, falls as the tip goes in",
                    "height (measured)": "m, height (piezo) + sensor_offset_um",
                    "time": "s from the curve's start", "segment": "0 approach, 1 retract"},
        "curve_fields": {
            "E_Pa": "Young's modulus of the sample under the curve",
            "contact_travel_m": "the piezo's travel from the curve's first sample to where the tip meets the "
                                "surface (the deflection is nil there: also the tip's travel)",
            "contact_height_piezo_m": "height (piezo) at contact",
            "baseline_N": "the force column's zero on this curve (the drift and tilt artefacts start from it)",
            "max_indentation_m": "the tip's indentation at the turn (piezo travel - contact - force / k)",
            "max_force_N": "the contact force at the turn, without baseline, artefact or noise",
            "z_range_m": "the piezo's travel from the start to the turn",
        },
        "curves": curves,
    }
    truth_path(path).write_text(json.dumps(truth, indent=1) + "\n")
    return path


# -- command line -------------------------------------------------------------------------------


def _grid(text: str) -> tuple[int, int]:
    parts = text.lower().replace("×", "x").split("x")
    try:
        nx, ny = (int(p) for p in parts) if len(parts) == 2 else (int(parts[0]),) * 2
    except ValueError:
        raise argparse.ArgumentTypeError(f"grid must be like 8x8 or 64, not {text!r}") from None
    if nx < 1 or ny < 1:
        raise argparse.ArgumentTypeError(f"grid must be positive, not {text!r}")
    return nx, ny


def _region(text: str) -> str | None:
    if text.lower() in ("none", ""):
        return None
    if text not in REGIONS:
        raise argparse.ArgumentTypeError(f"region must be one of {', '.join(REGIONS)} or none, not {text!r}")
    return text


def _pair(text: str) -> tuple[float, float]:
    parts = text.replace(",", ":").split(":")
    try:
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"give two numbers, like 1000:20000, not {text!r}") from None
    return lo, hi


def add_map_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add `sim-map OUT.h5 [...]` to a `rig` subparsers object; returns the new parser."""
    d = MapSpec()
    p = subparsers.add_parser(
        "sim-map", help="write a simulated AFM force map (afmformats HDF5) and its truth",
        description="Write a grid of simulated approach-retract force-distance curves (a paraboloid indenting "
                    "an elastic sample whose modulus varies smoothly over the map, on an uneven surface, with "
                    "noise and a baseline) as afmformats' HDF5 force map, which rig, nanite and PyJibe read, "
                    "and OUT.truth.json beside it: every curve's modulus, contact point and region. A hidden "
                    "region may carry one effect the rest does not: thin_layer (bottom effect, Dimitriadis "
                    "2002), drift, tilt (virtual deflection), adhesion or drag (on the cantilever).")
    p.add_argument("out", metavar="OUT.h5", help="the map to write (afmformats reads it only as .h5)")
    p.add_argument("--grid", type=_grid, default=d.grid, help="columns x rows (default 8x8)")
    p.add_argument("--region", type=_region, default=None, help=f"{', '.join(REGIONS)} or none (default none)")
    p.add_argument("--seed", type=int, default=0, help="the same seed writes the same map (default 0)")
    p.add_argument("--noise-pN", type=float, default=d.noise_pN,
                   help=f"rms force noise (default {d.noise_pN:g})")
    p.add_argument("--noise-cutoff-Hz", type=float, default=None, help="low-pass the noise (default white)")
    p.add_argument("--radius-um", type=float, default=d.radius_um,
                   help=f"the paraboloid's radius (default {d.radius_um:g} µm)")
    p.add_argument("--E-range-Pa", type=_pair, default=d.E_range_Pa, metavar="LOW:HIGH",
                   help="the modulus's range over the map (default 1000:20000)")
    p.add_argument("--size-um", type=_pair, default=d.size_um, metavar="X:Y",
                   help="the grid's extent (default 50:50 µm)")
    p.add_argument("--spring-constant", type=float, default=d.spring_constant_N_per_m,
                   help=f"N/m (default {d.spring_constant_N_per_m:g})")
    p.add_argument("--setpoint-nN", type=float, default=d.setpoint_nN, help=f"default {d.setpoint_nN:g}")
    p.add_argument("--rate-Hz", type=float, default=d.rate_Hz, help=f"sample rate (default {d.rate_Hz:g})")
    p.add_argument("--speed-um-per-s", type=float, default=d.speed_um_per_s,
                   help=f"approach and retract speed (default {d.speed_um_per_s:g})")
    p.add_argument("--layer-thickness-um", type=float, default=d.layer_thickness_um,
                   help=f"thin_layer: the layer's thickness (default {d.layer_thickness_um:g})")
    p.add_argument("--not-bonded", action="store_true", help="thin_layer: the layer lies on the substrate")
    p.set_defaults(func=cmd_sim_map)
    return p


def cmd_sim_map(args: argparse.Namespace) -> int:
    """Write the map the arguments describe and say what was written."""
    import time

    spec = MapSpec(grid=args.grid, size_um=args.size_um, radius_um=args.radius_um, E_range_Pa=args.E_range_Pa,
                   spring_constant_N_per_m=args.spring_constant, setpoint_nN=args.setpoint_nN,
                   rate_Hz=args.rate_Hz, speed_um_per_s=args.speed_um_per_s, noise_pN=args.noise_pN,
                   noise_cutoff_Hz=args.noise_cutoff_Hz, region=args.region,
                   layer_thickness_um=args.layer_thickness_um, layer_bonded=not args.not_bonded)
    if not str(args.out).endswith(".h5"):
        raise RigError(f"{args.out}: afmformats reads its HDF5 maps only under the suffix .h5")
    from rig.progress import Progress

    t0 = time.perf_counter()
    n = spec.grid[0] * spec.grid[1]
    # said only for a map that takes a while (a 256x256 one takes minutes); a page's small map,
    # whose output it shows, writes within a second or two
    shown = Progress(n, what="curves written", after_s=PROGRESS_AFTER_S)
    try:
        path = write_map(args.out, spec, seed=args.seed, progress=shown.add)
    finally:
        shown.close()
    truth = json.loads(truth_path(path).read_text())
    n = len(truth["curves"])
    region = truth["region"]
    where = f"; region {region['effect']}: {len(region['curves'])} curves" if region["effect"] else ""
    size = path.stat().st_size / 1e6
    print(f"wrote {path} ({n} curves, {size:.3g} MB, {time.perf_counter() - t0:.2g} s{where})")
    print(f"truth: {truth_path(path)}")
    print(f"fit one: rig analyze {path} --model hertz --indenter paraboloid:R={spec.radius_um:g}um "
          "--segment approach --curve 0")
    return 0


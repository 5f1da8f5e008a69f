"""AFM force curves, read through `afmformats` (the optional extra `rig[afm]`): JPK `.jpk-force`,
`.jpk-force-map`, `.jpk-qi-data` and `.jpk-qi-series`; Asylum `.ibw`; the NT-MDT Nova text
export; AFM Workshop `.csv` and its `.zip` force map; the Optics11 Chiaro text export; and
afmformats' own `.h5` and `.tab`.

A file is recognised by its suffix and its content, so the text and CSV files the project's
own readers take (Mach-1, JPK text export, Instron, CSV with units) are never taken for AFM
files. A file may hold many curves (a force map): each is numbered as the instrument numbers
it (afmformats' `enum`); `ReadOptions.curve` picks one, `list_curves` lists them and
`iter_records` gives every curve as a Record from one load of the file.

Heights fall as the tip goes in, so the travel into the sample is -(height - height at the
start); the tip-sample indentation subtracts the cantilever's deflection (force / spring
constant), which matters for soft cantilevers. The force keeps the file's sign and zero.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import re
import warnings
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.errors import RigError, SpecError
from rig.records.record import Record
from rig.records.units import LENGTH

ZIP_MAGIC = b"PK\x03\x04"
HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
CHIARO_MARK = "Device:\tChiaro"
WORKSHOP_MARK = "Force-Distance Curve"


@dataclass(frozen=True)
class ReadOptions:
    """What the user says about a file beyond its content.

    `curve`: the curve's number as the instrument numbers it (afmformats' `enum`); None gives
    the file's first curve. `spring_constant_N_per_m` and `sensitivity_m_per_V` override (or
    supply, when the file does not hold them) the cantilever's calibration; the sensitivity is
    in the unit of the file's deflection signal (m/V for volts; nm/nA, i.e. m/A, for the NT-MDT
    export's deflection in nA). `block` picks a data block of a Mach-1 file.
    """

    curve: int | None = None
    spring_constant_N_per_m: float | None = None
    sensitivity_m_per_V: float | None = None
    block: int | None = None


@dataclass(frozen=True)
class CurveInfo:
    """One curve of a file: its number, where it was taken, and its place on the map's grid."""

    enum: int
    x_m: float | None = None
    y_m: float | None = None
    grid_x: int | None = None
    grid_y: int | None = None
    grid_shape: tuple[int, int] | None = None  # (columns, rows) of the map's grid


@dataclass(frozen=True)
class AfmFormat:
    """One AFM file format: the record's source name, the instrument, how messages name such a file, and its
    suffixes."""

    source: str  # Record.source
    instrument: str  # Record.meta["instrument"]
    what: str  # how messages name such a file
    suffixes: tuple[str, ...]


JPK = AfmFormat("jpk", "JPK", "JPK force file",
                (".jpk-force", ".jpk-force-map", ".jpk-qi-data", ".jpk-qi-series"))
ASYLUM = AfmFormat("asylum", "Asylum", "Asylum .ibw file", (".ibw",))
NTMDT = AfmFormat("ntmdt", "NT-MDT", "NT-MDT Nova text export", (".txt",))
CHIARO = AfmFormat("chiaro", "Optics11 Chiaro", "Optics11 Chiaro text export", (".txt",))
WORKSHOP = AfmFormat("afm-workshop", "AFM Workshop", "AFM Workshop force curve", (".csv",))
WORKSHOP_MAP = AfmFormat("afm-workshop", "AFM Workshop", "AFM Workshop force map", (".zip",))
HDF5 = AfmFormat("afmformats", "afmformats", "afmformats HDF5 file", (".h5",))
TAB = AfmFormat("afmformats", "afmformats", "afmformats .tab file", (".tab",))
FORMATS = (JPK, ASYLUM, NTMDT, CHIARO, WORKSHOP, WORKSHOP_MAP, HDF5, TAB)

AFM_LOOKED_FOR = ("an AFM force file (JPK .jpk-force, .jpk-force-map, .jpk-qi-data, .jpk-qi-series; Asylum "
                  ".ibw; NT-MDT Nova .txt export; AFM Workshop .csv or .zip map; Optics11 Chiaro .txt; "
                  "afmformats .h5 or .tab)")

# afmformats' segment numbers by modality (its AFMForceDistance, AFMCreepCompliance and
# AFMStressRelaxation classes): a stress relaxation starts with a pause before the approach
SEGMENT_NAMES = {
    "force-distance": ("approach", "retract"),
    "creep-compliance": ("approach", "intermediate", "retract"),
    "stress-relaxation": ("intermediate", "approach", "intermediate", "retract"),
}

_NUM = r"[-+]?(?:\d+(?:[.,]\d*)?|[.,]\d+)(?:[eE][-+]?\d+)?"
_NTMDT_ROW = re.compile(rf"^\s*{_NUM}\t{_NUM}\t{_NUM}\s*$")


def in_time_order(t: np.ndarray, *columns: np.ndarray | None) -> tuple:
    """`t` and the columns sorted by time, a repeated time dropped (segments that restart or
    overlap); a None column stays None."""
    if np.all(t[1:] > t[:-1]):  # most files: already in order, nothing to sort or drop
        return (t.copy(), *(None if c is None else c.copy() for c in columns))
    order = np.argsort(t, kind="stable")
    keep = np.concatenate([[True], np.diff(t[order]) > 0])
    return (t[order][keep], *(None if c is None else c[order][keep] for c in columns))


DEFLECTION_SMOOTHING = 15  # samples (odd): the local cubic that takes the deflection's noise out of the tip


def tip_travel(height_m: np.ndarray, force_N: np.ndarray, spring_N_per_m: float | None,
               notes: list[str], segments: np.ndarray | None = None) -> np.ndarray:
    """The travel into the sample from a height that falls as the tip goes in; with the
    cantilever's spring constant, less its deflection (the tip lags the piezo by force / k).

    The deflection is taken through a local cubic over DEFLECTION_SMOOTHING samples
    (Savitzky-Golay) first, within each of the instrument's `segments` (else the approach up to
    the deepest point and what follows), so that no corner where the piezo turns or stops is
    rounded. Its noise over k would otherwise enter the indentation, and where the sample is
    about as stiff as the cantilever (dF/dd ~ k) the model's force at that noisy indentation
    carries the noise again: the residual in contact reached twice the noise on clean simulated
    curves, and `delay`, which averages neighbouring positions, was named the missing effect on
    a quarter of them. The force itself is left as measured."""
    travel = -(height_m - height_m[0])
    if spring_N_per_m:
        deflection = force_N - np.median(force_N[: max(len(force_N) // 50, 5)])
        if segments is None:  # the approach up to the deepest point, and what follows
            segments = (np.arange(len(travel)) > np.argmax(travel)).astype(int)
        travel = travel - smoothed_within(deflection, segments) / spring_N_per_m
        notes.append(f"indentation = travel - deflection (cantilever {spring_N_per_m:.3g} N/m)")
    return travel


def smoothed_within(y: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """`y` through a local cubic over DEFLECTION_SMOOTHING samples, run by run of equal
    `segments` (a run too short for the window is left as it is)."""
    out = np.array(y, dtype=float)
    edges = np.flatnonzero(np.diff(segments)) + 1
    for a, b in zip(np.r_[0, edges], np.r_[edges, len(y)], strict=True):
        if b - a >= 2 * DEFLECTION_SMOOTHING:
            out[a:b] = savgol_cubic(out[a:b], DEFLECTION_SMOOTHING)
    return out


def savgol_cubic(y: np.ndarray, w: int) -> np.ndarray:
    """A cubic least-squares fit over `w` samples (odd) at each sample: Savitzky-Golay, with the
    edges from the fit to the first and last window, as `scipy.signal.savgol_filter(y, w, 3,
    mode="interp")` gives it (written here: importing scipy.signal costs a one-curve `rig
    analyze` 0.7 s, and each batch worker as much)."""
    h = w // 2
    centre = _savgol_centre(w)
    out = np.empty(len(y))
    out[h:len(y) - h] = np.convolve(y, centre[::-1], mode="valid")
    left, right = _savgol_edges(w)
    out[:h] = left @ y[:w]
    out[len(y) - h:] = right @ y[-w:]
    return out


@functools.lru_cache(maxsize=4)
def _savgol_edges(w: int) -> tuple[np.ndarray, np.ndarray]:
    """The cubic fitted to the first (last) `w` samples, at the first (last) w // 2: a fixed
    linear map of the window's samples, computed once for every curve of a map."""
    h = w // 2
    k = np.arange(w, dtype=float)
    fit = np.linalg.pinv(np.vander(k, 4))  # the cubic's coefficients, highest power first
    left, right = np.vander(k[:h], 4) @ fit, np.vander(k[w - h:], 4) @ fit
    left.flags.writeable = right.flags.writeable = False
    return left, right


@functools.lru_cache(maxsize=4)
def _savgol_centre(w: int) -> np.ndarray:
    """The weights of a cubic over `w` samples' fitted value at the window's centre (the same
    for every curve of a map: computed once)."""
    h = w // 2
    j = np.arange(-h, h + 1, dtype=float)
    centre = np.linalg.pinv(np.vander(j, 4, increasing=True))[0]
    centre.flags.writeable = False
    return centre


def detect_afm(head: bytes, path: Path) -> AfmFormat | None:
    """The AFM format of a file from its suffix and first bytes, or None.

    The JPK, .ibw and .h5 suffixes are claimed whatever the content (a damaged file then gets
    a message naming what it should be); .txt, .csv, .zip and .tab only with the format's mark.
    """
    suffix = path.suffix.lower()
    if suffix in JPK.suffixes or (suffix.startswith(".jpk") and head.startswith(ZIP_MAGIC)):
        return JPK
    if suffix == ".ibw":
        return ASYLUM
    if suffix == ".h5":
        return HDF5
    if suffix == ".zip":
        return WORKSHOP_MAP if head.startswith(ZIP_MAGIC) and _zip_of_workshop_curves(path) else None
    if b"\x00" in head:
        return None
    text = head.decode("latin-1")
    if suffix == ".txt":
        if CHIARO_MARK in text:
            return CHIARO
        if _looks_like_ntmdt(text, complete=len(head) < 8192):
            return NTMDT
    if suffix == ".csv" and _first_line(text) == WORKSHOP_MARK:
        return WORKSHOP
    if suffix == ".tab" and "# BEGIN METADATA" in text:
        return TAB
    return None


def _first_line(text: str) -> str:
    return next((ln.strip() for ln in text.splitlines() if ln.strip()), "")


def _looks_like_ntmdt(text: str, complete: bool) -> bool:
    """Rows of three tab-separated numbers (decimal commas allowed), no header: height (nm),
    deflection on the approach and on the retract."""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not complete:
        lines = lines[:-1]  # the last line of the head may be cut
    return len(lines) >= 5 and all(_NTMDT_ROW.match(ln) for ln in lines)


def _zip_of_workshop_curves(path: Path) -> bool:
    """A zip whose members are AFM Workshop force-curve CSVs (a damaged zip is claimed too:
    the reader then says what is wrong with it)."""
    try:
        with zipfile.ZipFile(path) as arc:
            names = [n for n in arc.namelist() if not n.endswith("/")]
            if not names or not all(n.lower().endswith(".csv") for n in names):
                return False
            with arc.open(sorted(names)[0]) as fd:
                return _first_line(fd.read(200).decode("latin-1")) == WORKSHOP_MARK
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, ValueError, RuntimeError, NotImplementedError):
        return True


def format_of(path: str | Path) -> AfmFormat:
    """The AFM format of a file, or a SpecError saying it is none."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(8192)
    except OSError as exc:
        raise SpecError(f"cannot open: {exc.strerror or exc}", path=str(path)) from None
    fmt = detect_afm(head, path)
    if fmt is None:
        raise SpecError(f"not an AFM force file (looked for {AFM_LOOKED_FOR})", path=str(path))
    return fmt


# -- reading ------------------------------------------------------------------------------------

def read_afm(path: str | Path, options: ReadOptions | None = None, fmt: AfmFormat | None = None) -> Record:
    """One curve of an AFM file: `options.curve`, or the first one (with a note when there are more)."""
    path = Path(path)
    options = options or ReadOptions()
    fmt = fmt or format_of(path)
    data, caught = (_listed and _listed.pop(_key(path, fmt, options), None)) or _load(path, fmt, options)
    enums = [_enum(d) for d in data]
    if options.curve is None:
        i = 0
    elif options.curve in enums:
        i = enums.index(options.curve)
    else:
        which = "curve" if len(enums) == 1 else "curves"
        raise SpecError(f"no curve {options.curve} in the file: it holds {which} {describe_numbers(enums)}",
                        path=str(path))
    header = _header(path, fmt)
    rec = _record(path, fmt, data[i], len(data), header, caught)
    if len(data) > 1 and options.curve is None:
        rec.notes.insert(0, f"the file holds {len(data)} curves (numbered {describe_numbers(enums)}): this is "
                            f"curve {enums[i]}, the first; pick another with --curve N")
    return rec


def iter_records(path: str | Path, options: ReadOptions | None = None) -> Iterator[Record]:
    """Every curve of the file as a Record, in the file's order, from one load of the file
    (`options.curve` is not used). A curve is let go once it has been given."""
    path = Path(path)
    options = options or ReadOptions()
    fmt = format_of(path)
    data, caught = _load(path, fmt, options)
    header = _header(path, fmt)
    n = len(data)
    for i in range(n):
        d, data[i] = data[i], None
        yield _record(path, fmt, d, n, header, caught if i == 0 else [])


def each_record(path: str | Path, options: ReadOptions | None = None,
                curves: set[int] | None = None) -> Iterator[tuple[int, Record | RigError]]:
    """The curves numbered in `curves` (every curve if None), in the file's order, from one load
    of the file: (number, Record), or (number, the error that curve alone gave), so that one bad
    curve does not end a batch. A file that cannot be opened at all raises, as `read_afm` does."""
    path = Path(path)
    options = options or ReadOptions()
    fmt = format_of(path)
    if fmt is HDF5 and curves is not None:
        data, caught, n = _load_hdf5_curves(path, options, curves)
    else:
        data, caught = _load(path, fmt, options)
        n = len(data)
    header = _header(path, fmt)
    first = True
    for i in range(len(data)):
        d, data[i] = data[i], None
        enum = i
        try:
            with _translated(path, fmt):
                enum = _enum(d)
            if curves is not None and enum not in curves:
                continue
            rec = _record(path, fmt, d, n, header, caught if first else [])
        except RigError as exc:
            if curves is not None and enum not in curves:
                continue
            rec = exc
        first = False
        yield enum, rec


def _load_hdf5_curves(path: Path, options: ReadOptions, curves: set[int]) -> tuple[list, list[str], int]:
    """The curves numbered in `curves` of an afmformats HDF5 file, read as afmformats' own loader
    reads each (its H5DictReader and data class), without reading every other curve's metadata
    first: a 64x64 map's 4096 headers took afmformats 12 s per opening, and a batch opens the file
    once per chunk. Also the file's number of curves."""
    af = _afmformats(path)
    import h5py
    from afmformats.formats.fmt_hdf5 import H5DictReader

    where = str(path)
    if path.suffix not in af.formats.formats_by_suffix:
        raise SpecError(f"read as {HDF5.what}, which afmformats reads only under the suffix .h5: rename it",
                        path=where)
    _no_override(options, where)
    cls = af.formats.default_data_classes_by_modality["force-distance"]
    with _translated(path, HDF5) as caught, h5py.File(path, "r") as h5:
        keys = sorted((k for k in h5 if k.isdigit()), key=int)
        data = []
        for k in keys:
            if int(k) not in curves:
                continue
            # the metadata `_build` reads, not all of it: each attribute costs libhdf5 some 0.1 ms,
            # and a curve holds thirty
            group = h5[k]
            attrs = group.attrs
            held = set(attrs)
            # the grid's extent only where afmformats must work the grid index out from it; the
            # sampling rate only where there is no time column
            skip = set(_PLACE_KEYS[6:]) if {"grid index x", "grid index y"} <= held else set()
            if "time" in group:
                skip.add("rate approach")
            md = {key: attrs[key] for key in _HDF5_META if key in held and key not in skip}
            md.update(path=path, enum=int(k), format="afmformats (HDF5-based)")
            data.append(cls(data=_columns(h5, k, H5DictReader), metadata=md, diskcache=False))
    return data, [str(w.message) for w in caught], len(keys)


# what a curve's place is worked out from (afmformats fills the grid index from the rest)
_PLACE_KEYS = ("position x", "position y", "grid index x", "grid index y", "grid shape x", "grid shape y",
               "grid center x", "grid center y", "grid size x", "grid size y")


def _columns(h5, key: str, reader_class) -> dict[str, np.ndarray]:
    """The columns of curve `key` that `_build` reads, as afmformats' reader gives them (its dtype
    for each), read from the file already open (its reader opens the file again for every
    column) through libhdf5's own read, a third of the cost of h5py's indexing; a column
    afmformats does not document, or a dataset of another shape, goes through its reader, which
    says what is wrong with it."""
    import h5py
    from afmformats.formats.fmt_hdf5 import column_dtypes, known_columns

    group = h5[key]
    used = _used(sorted(group.keys()))
    if not all(c in known_columns and c in column_dtypes for c in used):
        reader = reader_class(h5, enum_key=key)
        return {c: reader[c] for c in used}
    out = {}
    for c in used:
        ds = h5py.h5d.open(group.id, c.encode())
        if len(ds.shape) != 1:
            reader = reader_class(h5, enum_key=key)
            return {c: reader[c] for c in used}
        arr = np.empty(ds.shape, ds.dtype)
        ds.read(h5py.h5s.ALL, h5py.h5s.ALL, arr)
        out[c] = np.asarray(arr, dtype=column_dtypes[c])
    return out


# the metadata of an afmformats HDF5 curve that `_build` and afmformats' data class read
_HDF5_META = ("software", "rate approach", "spring constant", "sensitivity", "instrument", "curve id",
              "point count", *_PLACE_KEYS)


def _used(columns: list[str]) -> list[str]:
    """The columns of an afmformats HDF5 curve that `_build` reads: the force, the segment, the
    time and the first height it looks for (the other heights are never read); all of them when
    the force is missing, for the message that lists them."""
    if "force" not in columns:
        return columns
    height = next((c for c in ("height (measured)", "height (piezo)", "tip position") if c in columns), None)
    return [c for c in columns if c in ("force", "segment", "time", height)]


def list_curves(path: str | Path, options: ReadOptions | None = None) -> list[CurveInfo]:
    """The curves a file holds: number, position on the sample and on the map's grid."""
    path = Path(path)
    options = options or ReadOptions()
    fmt = format_of(path)
    if fmt is HDF5:
        return _list_hdf5(path, options)
    data, caught = _load(path, fmt, options)
    _listed.clear()
    if len(data) == 1:
        # `rig analyze FILE` lists a file to learn whether it is a batch, then reads its one curve:
        # the read takes this load (a JPK curve's second opening cost 30 ms of CPU, afmformats' caches warm).
        # A file of many curves is not kept: a batch reads it curve by curve, letting each go
        _listed[_key(path, fmt, options)] = (data, caught)
    out = []
    with _translated(path, fmt):
        for d in data:
            md = d.metadata
            gx, gy = _meta(md, "grid index x"), _meta(md, "grid index y")
            sx, sy = _meta(md, "grid shape x"), _meta(md, "grid shape y")
            out.append(CurveInfo(_enum(d), _float(_meta(md, "position x")), _float(_meta(md, "position y")),
                                 None if gx is None else int(gx), None if gy is None else int(gy),
                                 None if sx is None or sy is None else (int(sx), int(sy))))
    return out


def curve_numbers(path: str | Path, options: ReadOptions | None = None) -> list[int] | None:
    """The numbers of an afmformats HDF5 file's curves, from its group names alone (no curve's
    metadata read: a 64x64 map's places took 3.7 s to list); None for a file of another format,
    whose curves `list_curves` lists. The same refusals as `list_curves`."""
    path = Path(path)
    if format_of(path) is not HDF5:
        return None
    _hdf5_checked(path, options or ReadOptions())
    import h5py

    with _translated(path, HDF5), h5py.File(path, "r") as h5:
        nums = sorted(int(k) for k in h5 if k.isdigit())
    if not nums:
        raise SpecError(f"the {HDF5.what} holds no force curve", path=str(path))
    return nums


def hdf5_places(path: str | Path, curves: set[int]) -> dict[int, CurveInfo]:
    """`list_curves`' places of the curves numbered in `curves` of an afmformats HDF5 file (for
    a curve whose record could not be built: the row still says where it was taken)."""
    return {i.enum: i for i in _list_hdf5(Path(path), ReadOptions(), curves)}


def count_curves(path: str | Path, options: ReadOptions | None = None) -> int:
    """How many curves `list_curves` lists (an afmformats HDF5 file's counted without reading
    them), with the same refusals."""
    path = Path(path)
    options = options or ReadOptions()
    if format_of(path) is not HDF5:
        return len(list_curves(path, options))
    _hdf5_checked(path, options)
    import h5py

    with _translated(path, HDF5), h5py.File(path, "r") as h5:
        n = sum(1 for k in h5 if k.isdigit())
    if not n:
        raise SpecError(f"the {HDF5.what} holds no force curve", path=str(path))
    return n


def _suited(path: Path, fmt: AfmFormat, options: ReadOptions):
    """afmformats, once the options, the suffix and the content suit its reader for `fmt`."""
    af = _afmformats(path)
    where = str(path)
    if options.block is not None:
        raise SpecError("--block picks a data block of a Mach-1 file; an AFM file's curves are picked with "
                        "--curve N", path=where)
    if path.suffix not in af.formats.formats_by_suffix:
        # afmformats matches suffixes exactly
        raise SpecError(f"read as {fmt.what}, which afmformats reads only under the suffix "
                        f"{' or '.join(fmt.suffixes)}: rename it", path=where)
    _check_content(path, fmt)
    return af


def _no_override(options: ReadOptions, where: str) -> None:
    """An HDF5 file holds its own calibration: refused as afmformats' own loader refuses it."""
    given = [f for f, v in (("--spring-constant", options.spring_constant_N_per_m),
                            ("--sensitivity", options.sensitivity_m_per_V)) if v is not None]
    if given:
        raise SpecError(f"the file ({HDF5.what}) holds its own cantilever calibration, which afmformats "
                        f"does not let {' and '.join(given)} override: leave {' and '.join(given)} out",
                        path=where)


def _hdf5_checked(path: Path, options: ReadOptions):
    """afmformats, once the options and the file are known to suit its HDF5 reader (what its
    loader refuses, refused as `_load` refuses it)."""
    af = _suited(path, HDF5, options)
    where = str(path)
    _no_override(options, where)
    return af


def _list_hdf5(path: Path, options: ReadOptions, curves: set[int] | None = None) -> list[CurveInfo]:
    """`list_curves` of an afmformats HDF5 file from the few attributes that place each curve,
    read as afmformats reads them (its MetaData, which fills in a missing grid index), without
    the rest of every curve's metadata: a 64x64 map's 4096 full headers took afmformats 9 s."""
    af = _hdf5_checked(path, options)
    import h5py

    where = str(path)
    out = []
    with _translated(path, HDF5), h5py.File(path, "r") as h5:
        for k in sorted((k for k in h5 if k.isdigit()), key=int):
            if curves is not None and int(k) not in curves:
                continue
            attrs = h5[k].attrs
            keys = _PLACE_KEYS[:6] if "grid index x" in attrs and "grid index y" in attrs else _PLACE_KEYS
            md = af.meta.MetaData({key: attrs[key] for key in keys if key in attrs})
            gx, gy = _meta(md, "grid index x"), _meta(md, "grid index y")
            sx, sy = _meta(md, "grid shape x"), _meta(md, "grid shape y")
            out.append(CurveInfo(int(k), _float(_meta(md, "position x")), _float(_meta(md, "position y")),
                                 None if gx is None else int(gx), None if gy is None else int(gy),
                                 None if sx is None or sy is None else (int(sx), int(sy))))
    if not out:
        raise SpecError(f"the {HDF5.what} holds no force curve", path=where)
    return out


def describe_numbers(nums: list[int], most: int = 12) -> str:
    """'109, 129, 416'; '0-16383' for a run; the first runs and a count when there are many."""
    runs: list[tuple[int, int]] = []
    for v in sorted(set(nums)):
        if runs and v == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], v)
        else:
            runs.append((v, v))
    parts = [str(a) if a == b else (f"{a}, {b}" if b == a + 1 else f"{a}-{b}") for a, b in runs]
    if len(parts) > most:
        return ", ".join(parts[:most]) + f", ... ({len(set(nums))} curves, {runs[0][0]} to {runs[-1][1]})"
    return ", ".join(parts)


def _afmformats(path: Path | None = None):
    try:
        import afmformats
    except ImportError:
        where = f"{path}: an AFM force file: " if path else ""
        raise RigError(f"{where}reading AFM force files needs the afmformats package "
                       "(pip install 'indentation-rig[afm]')") from None
    return afmformats


def _errors(af) -> tuple[type[BaseException], ...]:
    """Everything afmformats and the readers under it raise for a bad file (its own errors derive
    from BaseException), but not KeyboardInterrupt or SystemExit."""
    return (Exception, af.errors.AFMFileFormatError, af.errors.MissingMetaDataError,
            af.meta.MetaDataMissingError)


@contextlib.contextmanager
def _quiet():
    """afmformats logs a traceback for every file it fails on, and igor2 logs the raw bytes it
    could not shape: the failure becomes one line instead. Warnings are kept for the notes."""
    loggers = [logging.getLogger(name) for name in ("afmformats", "igor2")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield caught
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


@contextlib.contextmanager
def _translated(path: Path, fmt: AfmFormat):
    """Any failure while afmformats reads (data are read lazily, curve by curve) as one line;
    gives the list of warnings caught meanwhile."""
    af = _afmformats()
    with _quiet() as caught:
        try:
            yield caught
        except RigError:
            raise
        except af.errors.MissingMetaDataError as exc:
            keys = list(getattr(exc, "meta_keys", []))
            raise SpecError(_missing_message(keys, fmt), path=str(path)) from None
        except _errors(af) as exc:
            raise SpecError(f"not a readable {fmt.what}: {_why(exc)}", path=str(path)) from None


_listed: dict[tuple, tuple[list, list[str]]] = {}  # the last one-curve file `list_curves` loaded


def _key(path: Path, fmt: AfmFormat, options: ReadOptions) -> tuple:
    """What makes a load the same: the file as it is now and the calibration the user gave."""
    st = path.stat()
    return (str(path.resolve()), st.st_mtime_ns, st.st_size, fmt.what, options.spring_constant_N_per_m,
            options.sensitivity_m_per_V)


def _load(path: Path, fmt: AfmFormat, options: ReadOptions) -> tuple[list, list[str]]:
    """afmformats' curves of the file (data are read when asked for), and the warnings it gave."""
    af = _suited(path, fmt, options)
    where = str(path)
    override: dict[str, float] = {}
    if options.spring_constant_N_per_m is not None:
        override["spring constant"] = float(options.spring_constant_N_per_m)
    if options.sensitivity_m_per_V is not None:
        override["sensitivity"] = float(options.sensitivity_m_per_V)
    with _translated(path, fmt) as caught:
        try:
            data = _load_jpk(af, path, override) if fmt is JPK else af.load_data(path, meta_override=override)
        except NotImplementedError as exc:
            if not override or "Setting metadata" not in str(exc):
                raise
            # the Asylum and afmformats loaders refuse a calibration from the user
            given = " and ".join(f"--{k.replace(' ', '-')}" for k in override)
            raise SpecError(f"the file ({fmt.what}) holds its own cantilever calibration, which afmformats "
                            f"does not let {given} override: leave {given} out", path=where) from None
    if not data:
        raise SpecError(f"the {fmt.what} holds no force curve", path=where)
    notes = []
    for w in caught:
        if not issubclass(w.category, DeprecationWarning | PendingDeprecationWarning):
            msg = f"afmformats: {str(w.message).replace(str(path), path.name)}"
            if msg not in notes:
                notes.append(msg)
    return list(data), notes[:5]


def _load_jpk(af, path: Path, override: dict[str, float]) -> list:
    """What `afmformats.load_data` does for a JPK file, without its format detection: the suffix
    and the zip header already say JPK (one recipe per JPK suffix), and detecting parses the
    file's headers twice more (14 of the 20 ms a single curve takes to load, a sixteenth of a
    one-curve `rig analyze`)."""
    (recipe,) = af.formats.formats_by_suffix[path.suffix]
    _forget_archive(path)
    out = []
    for dd in recipe.loader(path, meta_override=override):
        dd["metadata"]["format"] = f"{recipe['maker']} ({recipe['descr']})"
        data_class = af.formats.default_data_classes_by_modality[dd["metadata"]["imaging mode"]]
        out.append(data_class(data=dd["data"], metadata=dd["metadata"]))
    return out


def _forget_archive(path: Path) -> None:
    """Close afmformats' open archive of `path`, if it keeps one. It keeps the last 32 JPK archives
    open by their path, so a file written again under the same name (a re-export, while `rig web`
    or a notebook runs on) was read through the old archive's index: "not a complete zip archive"."""
    try:
        from afmformats.formats.fmt_jpk.jpk_reader import ArchiveCache
    except ImportError:
        return
    for key in (path, str(path)):
        arc = ArchiveCache.open_archives.pop(key, None)
        if arc is not None:
            arc.close()


def _check_content(path: Path, fmt: AfmFormat) -> None:
    """The binary formats claimed by suffix alone: the first bytes must be theirs."""
    with open(path, "rb") as fh:
        head = fh.read(8)
    if not head:
        raise SpecError("file is empty", path=str(path))
    expect = {JPK: (ZIP_MAGIC, "a zip archive"), HDF5: (HDF5_MAGIC, "an HDF5 file"),
              WORKSHOP_MAP: (ZIP_MAGIC, "a zip archive")}.get(fmt)
    if expect and not head.startswith(expect[0]):
        raise SpecError(f"not a readable {fmt.what}: it is not {expect[1]} (damaged, or another kind of file)",
                        path=str(path))
    if fmt is ASYLUM and not (head[:2] in (b"\x01\x00", b"\x02\x00", b"\x03\x00", b"\x05\x00")
                              or head[:2] in (b"\x00\x01", b"\x00\x02", b"\x00\x03", b"\x00\x05")):
        raise SpecError(f"not a readable {fmt.what}: it does not start as an Igor binary wave (damaged, or "
                        "another kind of file)", path=str(path))


def _why(exc: BaseException) -> str:
    """afmformats' failure in a few words."""
    name = type(exc).__name__
    text = " ".join(str(exc).split())
    if name == "FileFormatNotSupportedError":
        return "afmformats does not recognise its content (damaged or truncated?)"
    if name == "BadZipFile":
        return "not a complete zip archive (damaged or truncated?)"
    if len(text) > 160:
        text = text[:157] + "..."
    return f"{name}: {text}" if text else name


def _missing_message(keys: list[str], fmt: AfmFormat) -> str:
    what = {"spring constant": "the cantilever's spring constant",
            "sensitivity": "the deflection sensitivity"}
    sens_unit = "nm/nA: this export's deflection is in nA" if fmt is NTMDT else "m/V"
    how = {"spring constant": "--spring-constant (N/m)", "sensitivity": f"--sensitivity ({sens_unit})"}
    keys = [k for k in ("spring constant", "sensitivity") if k in keys] or ["spring constant", "sensitivity"]
    if len(keys) == 1:
        return f"the file does not hold {what[keys[0]]}: give it with {how[keys[0]]}"
    return (f"the file does not hold {what[keys[0]]} or {what[keys[1]]}: give them with {how[keys[0]]} and "
            f"{how[keys[1]]}")


def _enum(d) -> int:
    return int(d.enum)


def _meta(md, key: str):
    """A metadata value, or None when the file does not give it."""
    af = _afmformats()
    try:
        return md.get(key)
    except _errors(af):  # a lazy value that cannot be worked out
        return None


def _float(value) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def _header(path: Path, fmt: AfmFormat) -> dict:
    """What the file's own header says beyond afmformats (the Chiaro's probe and fit)."""
    if fmt is CHIARO:
        return chiaro_header(path)
    return {}


def _record(path: Path, fmt: AfmFormat, d, n_curves: int, header: dict, caught: list[str]) -> Record:
    with _translated(path, fmt):
        return _build(path, fmt, d, n_curves, header, caught)


def _build(path: Path, fmt: AfmFormat, d, n_curves: int, header: dict, caught: list[str]) -> Record:
    where = str(path)
    md = d.metadata
    cols = set(d.columns)
    enum = _enum(d)
    modality = d.modality
    if "force" not in cols:
        raise SpecError(f"curve {enum} has no force column (afmformats found {', '.join(sorted(cols))})",
                        path=where)
    f = np.asarray(d["force"], dtype=float)
    n = len(f)
    instrument = fmt.instrument
    if fmt in (HDF5, TAB):  # afmformats' own files: the instrument that recorded the curve
        instrument = str(_meta(md, "software") or fmt.instrument)
    notes = [f"{instrument} {modality}, {n} samples"]
    # the travel of the probe: the measured height (the piezo's sensor), else the piezo's own
    # command; the Chiaro's "height (measured)" is its own indentation from its own contact
    # point, so its piezo is used
    order = ["height (piezo)", "tip position"] if fmt is CHIARO else \
        ["height (measured)", "height (piezo)", "tip position"]
    column = next((c for c in order if c in cols), None)
    if column is None:
        raise SpecError(f"curve {enum} has no height column (afmformats found {', '.join(sorted(cols))})",
                        path=where)
    h = np.asarray(d[column], dtype=float)
    seg = np.asarray(d["segment"], dtype=int) if "segment" in cols else None
    if "time" in cols:
        t = np.asarray(d["time"], dtype=float)
        time_from = "file"
        t, h, f, seg = in_time_order(t, h, f, seg)
    else:
        rate = _float(_meta(md, "rate approach"))
        if rate and rate > 0:
            t = np.arange(n) / rate
            time_from = "sampling rate"
            notes.append(f"the file has no time column: time from its sampling rate, {rate:g} Hz")
        else:
            t = np.arange(n, dtype=float)
            time_from = "sample number"
            notes.append("the file has no time and no sampling rate: t_s is the sample number (one per sample)")
    if len(t) < 2:
        raise SpecError(f"curve {enum} holds {len(t)} sample(s)", path=where)
    k = _float(_meta(md, "spring constant"))
    if column == "tip position":
        travel = tip_travel(h, f, None, notes)
        notes.append("position from the file's tip position (the cantilever's deflection already subtracted)")
    else:
        if fmt is CHIARO:
            notes.append("position from the piezo (the file's Indentation column is the instrument's own, "
                         "from its own contact point)")
        elif column != "height (measured)":
            notes.append(f"position from the file's {column}")
        travel = tip_travel(h, f, k, notes, seg)
        if not k:
            notes.append("the file gives no spring constant: the position is the piezo's travel, the "
                         "cantilever's deflection not subtracted (give --spring-constant to subtract it)")
    labels = _segment_labels(seg, modality, travel, notes)
    gx, gy = _meta(md, "grid index x"), _meta(md, "grid index y")
    sx, sy = _meta(md, "grid shape x"), _meta(md, "grid shape y")
    meta = {
        "instrument": instrument,
        "instrument_model": _meta(md, "instrument"),
        "format": _meta(md, "format"),
        "curve": enum,
        "curves_in_file": n_curves,
        "curve_id": _meta(md, "curve id"),
        "x_m": _float(_meta(md, "position x")),
        "y_m": _float(_meta(md, "position y")),
        "grid_index": None if gx is None or gy is None else (int(gx), int(gy)),
        "grid_shape": None if sx is None or sy is None else (int(sx), int(sy)),
        "spring_constant_N_per_m": k,
        "sensitivity": _float(_meta(md, "sensitivity")),
        "modality": modality,
        "position_column": column,
        "time_from": time_from,
        "indenter": header.get("indenter"),
        "instrument_result": header.get("instrument_result"),
    }
    if header.get("note"):
        notes.append(header["note"])
    notes.extend(caught)
    return Record(path.name, fmt.source, t, travel, f, segment=labels, meta=meta, length_unit="µm",
                  force_unit="nN", notes=notes)


def _segment_labels(seg: np.ndarray | None, modality: str, travel: np.ndarray, notes: list[str]) -> np.ndarray:
    """'approach', 'intermediate' or 'retract' per sample, from afmformats' segment numbers."""
    names = SEGMENT_NAMES.get(modality, ("approach", "retract"))
    n = len(travel)
    # one segment number throughout, told by its extremes (np.unique hashes every sample)
    if modality == "force-distance" and (seg is None or (len(seg) > 0 and seg.min() == seg.max())):
        # one segment for an approach and a retract (Asylum .ibw): split at the deepest point
        deep = int(np.argmax(travel))
        notes.append(f"the file does not mark the approach and the retract: split at the deepest point "
                     f"(sample {deep})")
        out = np.full(n, "retract", dtype="<U12")
        out[: deep + 1] = "approach"
        return out
    table = np.array([*names, ""], dtype="<U12")
    if seg is None:
        return np.full(n, "", dtype="<U12")
    idx = np.where((seg >= 0) & (seg < len(names)), seg, len(names))
    return table[idx]


# -- Optics11 Chiaro header ---------------------------------------------------------------------

_PA = {"pa": 1.0, "kpa": 1e3, "mpa": 1e6, "gpa": 1e9}
_FORCE_UNITS = {"n": 1.0, "mn": 1e-3, "un": 1e-6, "µn": 1e-6, "nn": 1e-9}


def chiaro_header(path: str | Path) -> dict:
    """The Chiaro's header (latin-1 text, µ as byte 0xB5): the probe (tip radius, spring constant)
    as `indenter` ("sphere:R=27.5um"), `tip_radius_m`, `spring_constant_N_per_m`, and the
    instrument's own fit as `instrument_result` ({"model", "E_Pa", "poisson", "E_eff_Pa",
    "max_force_N"}), each when the header gives it."""
    path = Path(path)
    lines = []
    try:
        with open(path, encoding="latin-1", newline="") as fh:
            for line in fh:
                if line.startswith("Time (s)"):  # the data follow
                    break
                lines.append(line)
    except OSError as exc:
        raise SpecError(f"cannot open: {exc.strerror or exc}", path=str(path)) from None
    fields: dict[str, str] = {}
    for line in "".join(lines).splitlines():
        s = line.strip()
        parts = [p.strip() for p in s.split("\t")]
        if len(parts) >= 2 and len(parts) % 2 == 0:
            fields.update(zip(parts[::2], parts[1::2], strict=True))
        elif ":" in s:
            key, _, val = s.partition(":")
            fields[key.strip()] = val.strip()
    out: dict = {}
    result: dict = {}
    for key, val in fields.items():
        value = _float(val.replace(",", "."))
        m = re.fullmatch(r"Tip radius \((?P<u>[^)]+)\)", key)
        if m and value and m["u"] in LENGTH:
            out["tip_radius_m"] = value * LENGTH[m["u"]]
        elif key == "k (N/m)" and value:
            out["spring_constant_N_per_m"] = value
        elif key == "Model" and val:
            result["model"] = val
        elif (m := re.fullmatch(r"E\[eff\] \((?P<u>\w+)\)", key)) and value is not None \
                and m["u"].lower() in _PA:
            result["E_eff_Pa"] = value * _PA[m["u"].lower()]
        elif (m := re.fullmatch(r"E\[v=(?P<nu>[0-9.]+)\] \((?P<u>\w+)\)", key)) and value is not None \
                and m["u"].lower() in _PA:
            result["E_Pa"] = value * _PA[m["u"].lower()]
            result["poisson"] = float(m["nu"])
        elif (m := re.fullmatch(r"P\[max\] \((?P<u>\S+)\)", key)) and value is not None \
                and m["u"].lower() in _FORCE_UNITS:
            result["max_force_N"] = value * _FORCE_UNITS[m["u"].lower()]
    if "tip_radius_m" in out:
        out["indenter"] = f"sphere:R={out['tip_radius_m'] * 1e6:g}um"
    if "E_Pa" in result or "E_eff_Pa" in result:
        out["instrument_result"] = result
    said = []
    if "indenter" in out:
        said.append(f"probe {out['indenter']}")
    if "E_Pa" in result:
        model = f" {result['model']}" if "model" in result else ""
        said.append(f"the instrument's own{model} fit: E = {result['E_Pa']:.4g} Pa at Poisson "
                    f"{result['poisson']:g}")
    if said:
        out["note"] = "Chiaro header: " + "; ".join(said)
    return out

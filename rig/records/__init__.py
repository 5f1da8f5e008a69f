"""Reading measured records from the files instruments write, recognised by their content:
the rig's own MCAP logs and CSV, AFM force files (JPK, Asylum, NT-MDT, AFM Workshop, Optics11
Chiaro, through afmformats: rig.records.afm), JPK text exports, Biomomentum Mach-1 `.txt`,
Instron Bluehill CSV, and CSV with units in the column names."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from rig.errors import RigError, SpecError
from rig.records.afm import (
    AFM_LOOKED_FOR,
    CurveInfo,
    ReadOptions,
    detect_afm,
    each_record,
    iter_records,
    list_curves,
    read_afm,
)
from rig.records.record import Record
from rig.specs.frames import Frame

MCAP_MAGIC = b"\x89MCAP"
LOOKED_FOR = ("an MCAP log, a CSV with t_s,position_mm,force_N (or units in the column names), a JPK "
              f"text export, a Mach-1 .txt, an Instron Bluehill CSV, or {AFM_LOOKED_FOR}")

__all__ = ["LOOKED_FOR", "CurveInfo", "ReadOptions", "Record", "each_record", "iter_records", "list_curves",
           "read_record", "recognised"]


def read_record(path: str | Path, options: ReadOptions | int | None = None, *,
                block: int | None = None) -> Record:
    """Open any supported file; one clear line when it is none of them.

    `options` says what the file does not (an AFM file's curve and cantilever calibration, a
    Mach-1 file's data block); a bare int in its place is a Mach-1 block, as `block=` is.
    """
    from rig.records.csvfile import looks_like_csv, read_csv_record
    from rig.records.instron import looks_like_instron, read_instron
    from rig.records.jpk import looks_like_jpk_text, read_jpk_text
    from rig.records.mach1 import looks_like_mach1, read_mach1

    options = _options(options, block)
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(8192)
    except IsADirectoryError:
        raise SpecError("is a directory, not a record", path=str(path)) from None
    except OSError as exc:
        raise SpecError(f"cannot open: {exc.strerror or exc}", path=str(path)) from None
    fmt = detect_afm(raw, path)
    if fmt is not None:
        return read_afm(path, options, fmt)
    _no_afm_options(options, path)
    if raw.startswith(MCAP_MAGIC):
        return _read_mcap(path)
    if b"\x00" in raw:
        raise SpecError(f"a binary file this tool cannot read (looked for {LOOKED_FOR})", path=str(path))
    head = raw.decode("utf-8", errors="replace")
    if not head.strip():
        raise SpecError("file is empty", path=str(path), line=1)
    if looks_like_mach1(head):
        return read_mach1(path, options.block)
    if looks_like_jpk_text(head):
        return read_jpk_text(path)
    if looks_like_instron(head):
        return read_instron(path)
    if looks_like_csv(head):
        return read_csv_record(path)
    if path.suffix.lower() == ".mcap":
        return _read_mcap(path)  # says what is wrong with the log
    raise SpecError(f"not a file this tool can read (looked for {LOOKED_FOR})", path=str(path))


def recognised(path: str | Path) -> bool:
    """Whether the file is one of the records `read_record` reads, by the same marks (first
    bytes, the AFM formats' own marks, a CSV's time, length and force columns), without reading
    it: a folder walked for a batch also holds pictures, notes and tables."""
    from rig.records.csvfile import looks_like_csv, pick_columns
    from rig.records.instron import looks_like_instron
    from rig.records.jpk import looks_like_jpk_text
    from rig.records.mach1 import looks_like_mach1

    path = Path(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(8192)
    except OSError:
        return False
    if raw.startswith(MCAP_MAGIC) or detect_afm(raw, path) is not None:
        return True
    if b"\x00" in raw:
        return False
    head = raw.decode("utf-8", errors="replace")
    if looks_like_mach1(head) or looks_like_jpk_text(head) or looks_like_instron(head):
        return True
    if not looks_like_csv(head):
        return False
    first = next((ln for ln in head.splitlines() if ln.strip()), "")
    try:
        pick_columns([h.strip() for h in first.split(",")], str(path))
    except SpecError:
        return False
    return True


def _options(options: ReadOptions | int | None, block: int | None) -> ReadOptions:
    if options is None:
        options = ReadOptions()
    elif not isinstance(options, ReadOptions):
        if isinstance(options, bool) or not isinstance(options, int | np.integer):
            raise TypeError(f"read_record: options must be a ReadOptions or a block number, not {options!r}")
        options = ReadOptions(block=int(options))
    if block is not None:
        if options.block is not None and options.block != block:
            raise TypeError(f"read_record: block {block} and options.block {options.block} disagree")
        options = replace(options, block=block)
    return options


def _no_afm_options(options: ReadOptions, path: Path) -> None:
    given = [flag for flag, value in (("--curve", options.curve),
                                      ("--spring-constant", options.spring_constant_N_per_m),
                                      ("--sensitivity", options.sensitivity_m_per_V)) if value is not None]
    if given:
        raise SpecError(f"{' and '.join(given)} apply to AFM force files; this is not one (looked for "
                        f"{AFM_LOOKED_FOR})", path=str(path))


def _read_mcap(path: Path) -> Record:
    from rig.recording.logs import read_log

    log = read_log(path)
    if log.n < 10:
        raise RigError(f"{path}: the log holds {log.n} samples: too few to analyse")
    s = log.samples
    kinds = np.array(log.step_kind)
    keep = ~np.isin(kinds, ["tare", "fault", "done"])
    tare = kinds == "tare"
    # from the surface throughout: an approach's travel out of contact is negative indentation
    x_mm = log.position_mm(Frame.SURFACE)
    return Record(path.name, "mcap", s["t_s"][keep], x_mm[keep] / 1000.0, s["force_N"][keep],
                  frame=Frame.SURFACE, steps=kinds[keep], baseline_force_N=s["force_N"][tare],
                  length_unit="mm", force_unit="N", meta={"indenter": _probe(log, path) or None,
                                                           **_size(log)})


def _size(log) -> dict:
    """The specimen's thickness (m) and contact area (m^2) the log's header keeps, if any."""
    from rig.specs.specimen import from_header

    dims = from_header(log.trial)
    return {k: v for k, v in (("thickness_m", dims.get("thickness_mm", 0) * 1e-3),
                              ("area_m2", dims.get("area_mm2", 0) * 1e-6)) if v}


def _probe(log, path: Path) -> str:
    """The rig's probe as the log's own config names it ('' when it does not, or is unreadable:
    replay warns about such a config; here it only means no geometry)."""
    from rig.specs.config import parse_config

    text = log.attachments.get("config.yaml")
    if not text:
        return ""
    try:
        return parse_config(text.decode(), f"{path}:config.yaml").probe
    except (RigError, UnicodeDecodeError):
        return ""

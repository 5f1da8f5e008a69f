"""Read trial logs (MCAP, also files cut short by a crash) and CSV files; export CSV.

Reading scans records in file order with `mcap.stream_reader.StreamReader`, so it does
not need the summary or footer a crashed writer never wrote: it stops at the first
truncated or undecodable record and keeps everything before it.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from rig.errors import RigError, SpecError
from rig.recording.messages import EVENT_TOPIC, HEALTH_TOPIC, SAMPLE, SAMPLE_TOPIC


@dataclass
class TrialLog:
    path: Path
    samples: dict[str, np.ndarray]  # column name -> values, one entry per tick
    step_kind: list[str]
    contact: np.ndarray
    events: list[dict]
    health: list[dict]
    metadata: dict[str, dict[str, str]]
    attachments: dict[str, bytes]
    schemas: dict[str, dict]  # topic -> JSON schema
    complete: bool  # footer present: the writer finished normally
    read_error: str = ""  # why reading stopped early, for a truncated file
    raw_messages: dict[str, list[dict]] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.samples.get("t_s", ()))

    @property
    def trial(self) -> dict[str, str]:
        return self.metadata.get("trial", {})

    @property
    def outcome(self) -> str:
        if "outcome" in self.metadata:
            return self.metadata["outcome"].get("outcome", "unknown")
        return "interrupted"


def read_log(path: str | Path, keep_raw: bool = False) -> TrialLog:
    """Read a trial log; raises RigError for a file that is not an MCAP log at all."""
    path = Path(path)
    try:
        fh = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise RigError(f"{path}: cannot open log: {exc.strerror or exc}") from None
    schemas_by_id: dict[int, dict] = {}
    channels: dict[int, str] = {}
    topic_schema: dict[str, dict] = {}
    rows: dict[str, list[dict]] = {SAMPLE_TOPIC: [], EVENT_TOPIC: [], HEALTH_TOPIC: []}
    metadata: dict[str, dict[str, str]] = {}
    attachments: dict[str, bytes] = {}
    complete = False
    error = ""
    seen_any = False
    with fh:
        try:
            for rec in StreamReader(fh, record_size_limit=1 << 30).records:
                seen_any = True
                if isinstance(rec, Message):
                    topic = channels.get(rec.channel_id)
                    if topic in rows:
                        rows[topic].append(json.loads(rec.data))
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                    if rec.schema_id in schemas_by_id:
                        topic_schema[rec.topic] = schemas_by_id[rec.schema_id]
                elif isinstance(rec, Schema):
                    schemas_by_id[rec.id] = json.loads(rec.data) if rec.data else {}
                elif isinstance(rec, Metadata):
                    metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Attachment):
                    attachments[rec.name] = bytes(rec.data)
                elif isinstance(rec, Footer):
                    complete = True
        # A truncated record, a short read or a corrupt chunk (zstd, CRC) ends the readable part.
        except Exception as exc:  # noqa: BLE001
            error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            if not seen_any:
                raise RigError(f"{path}: not a readable MCAP log ({error})") from None
    samples = rows[SAMPLE_TOPIC]
    cols = {name: np.array([s.get(name, np.nan) for s in samples], dtype=float)
            for name in SAMPLE.numeric}
    for name in SAMPLE.optional_numeric:  # present when a model ran in the loop
        if samples and name in samples[0]:
            cols[name] = np.array([s.get(name, np.nan) for s in samples], dtype=float)
    return TrialLog(
        path=path, samples=cols,
        step_kind=[s.get("step_kind", "") for s in samples],
        contact=np.array([bool(s.get("contact", False)) for s in samples]),
        events=rows[EVENT_TOPIC], health=rows[HEALTH_TOPIC], metadata=metadata,
        attachments=attachments, schemas=topic_schema, complete=complete, read_error=error,
        raw_messages=rows if keep_raw else {},
    )


def export_csv(log: TrialLog, out: str | Path) -> int:
    """Write the samples as CSV; the first columns are t_s, position_mm, force_N."""
    order = ["t_s", "position_mm", "force_N"] + [c for c in SAMPLE.numeric
                                                 if c not in ("t_s", "position_mm", "force_N")]
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*order, "contact", "step_kind"])
        cols = [log.samples[c] for c in order]
        ints = {"seq", "step"}
        for i in range(log.n):
            row = [(str(int(col[i])) if name in ints else repr(float(col[i])))
                   for name, col in zip(order, cols, strict=True)]
            w.writerow([*row, int(log.contact[i]), log.step_kind[i]])
    return log.n


def read_csv_trial(path: str | Path) -> dict[str, np.ndarray]:
    """Read a CSV with header t_s,position_mm,force_N (other columns ignored); clear errors."""
    path = str(path)
    try:
        fh = open(path, newline="")  # noqa: SIM115
    except OSError as exc:
        raise SpecError(f"cannot open CSV: {exc.strerror or exc}", path=path) from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise SpecError("file is empty", path=path, line=1) from None
        header = [h.strip() for h in header]
        missing = [c for c in ("t_s", "position_mm", "force_N") if c not in header]
        if missing:
            raise SpecError(f"missing column(s) {', '.join(missing)} (header must include "
                            "t_s,position_mm,force_N)", path=path, line=1)
        idx = [header.index(c) for c in ("t_s", "position_mm", "force_N")]
        data: list[list[float]] = []
        for line_no, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            try:
                values = [float(row[i]) for i in idx]
            except IndexError:
                raise SpecError(f"row has {len(row)} fields, header has {len(header)}",
                                path=path, line=line_no) from None
            except ValueError:
                bad = next(header[i] for i in idx if not _is_float(row[i]))
                raise SpecError(f"column {bad}: '{row[header.index(bad)]}' is not a number",
                                path=path, line=line_no) from None
            if not all(np.isfinite(values)):
                col = header[idx[[np.isfinite(v) for v in values].index(False)]]
                raise SpecError(f"column {col} is NaN or infinite", path=path, line=line_no)
            data.append(values)
    if len(data) < 2:
        raise SpecError("fewer than two data rows", path=path)
    arr = np.array(data)
    t = arr[:, 0]
    d = np.diff(t)
    if np.any(d <= 0):
        k = int(np.argmax(d <= 0))
        what = "duplicated" if d[k] == 0 else "decreasing (unsorted)"
        raise SpecError(f"t_s is {what} at row {k + 3} (t_s = {t[k + 1]:g} after {t[k]:g})",
                        path=path, line=k + 3)
    return {"t_s": t, "position_mm": arr[:, 1], "force_N": arr[:, 2]}


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True

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

from rig.errors import RigError
from rig.recording.messages import EVENT_TOPIC, HEALTH_TOPIC, SAMPLE, SAMPLE_TOPIC
from rig.specs.frames import Frame, FrameTrack


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
    frames: FrameTrack | None = None  # set by `read_log`

    @property
    def n(self) -> int:
        return len(self.samples.get("t_s", ()))

    @property
    def trial(self) -> dict[str, str]:
        return self.metadata.get("trial", {})

    def position_mm(self, frame: Frame) -> np.ndarray:
        """Every sample's feedback position measured in `frame` (the logged `position_mm` changes
        zero at an approach's contact)."""
        return self.frames.position_mm(frame)

    def position_cmd_mm(self, frame: Frame) -> np.ndarray:
        return self.frames.convert_working(self.samples["position_cmd_mm"], frame)

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
    kinds = [s.get("step_kind", "") for s in samples]
    return TrialLog(
        path=path, samples=cols, step_kind=kinds, frames=frame_track(cols, kinds, rows[EVENT_TOPIC]),
        contact=np.array([bool(s.get("contact", False)) for s in samples]),
        events=rows[EVENT_TOPIC], health=rows[HEALTH_TOPIC], metadata=metadata,
        attachments=attachments, schemas=topic_schema, complete=complete, read_error=error,
        raw_messages=rows if keep_raw else {},
    )


def frame_track(cols: dict[str, np.ndarray], kinds: list[str], events: list[dict]) -> FrameTrack:
    """The zeros in effect at every sample, from the trial_start and step_start events.

    The loop logs `position_mm` from the working zero as it stood at the start of the tick, and
    moves that zero (at an approach's contact) during the tick: the zero after tick i is the one
    the step_start event of sample i's step carries. The slider's own position is logged since
    `slider_mm`; before it, it is the logged position plus the zero after the previous tick.
    """
    n = len(cols.get("t_s", ()))
    start = next((float(e["data"]["start_mm"]) for e in events
                  if e.get("kind") == "trial_start" and "start_mm" in (e.get("data") or {})), 0.0)
    zeros: dict[int, float] = {}
    for e in events:
        data = e.get("data") or {}
        if e.get("kind") == "step_start" and "step" in data and "zero_mm" in data:
            zeros[int(data["step"])] = float(data["zero_mm"])
    step = cols.get("step", np.full(n, -1.0))
    working = np.empty(n)
    zero = start
    for i in range(n):
        if not np.isnan(step[i]):
            zero = zeros.get(int(step[i]), zero)
        working[i] = zero
    slider = cols.get("slider_mm")
    if slider is None or np.isnan(slider).any():
        before = np.concatenate([[start], working[:-1]]) if n else working
        slider = cols["position_mm"] + before if n else np.zeros(0)
    # an approach (and the tare before it) belongs to the surface it goes on to find
    surface = working.copy()
    for i in range(n - 2, -1, -1):
        if kinds[i] in ("approach", "tare"):
            surface[i] = surface[i + 1]
    return FrameTrack(np.asarray(slider, dtype=float), working, surface, start)


def export_csv(log: TrialLog, out: str | Path) -> int:
    """Write the samples as CSV; the first columns are t_s, position_mm, force_N. Positions are
    measured from the surface throughout (the analysis reads them so), not from the zero the
    loop used at the time."""
    order = ["t_s", "position_mm", "force_N"] + [c for c in SAMPLE.numeric
                                                 if c not in ("t_s", "position_mm", "force_N")]
    surface = {"position_mm": log.position_mm(Frame.SURFACE),
               "position_cmd_mm": log.position_cmd_mm(Frame.SURFACE)}
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*order, "contact", "step_kind"])
        cols = [surface.get(c, log.samples[c]) for c in order]
        ints = {"seq", "step"}
        for i in range(log.n):
            row = [(str(int(col[i])) if name in ints else repr(float(col[i])))
                   for name, col in zip(order, cols, strict=True)]
            w.writerow([*row, int(log.contact[i]), log.step_kind[i]])
    return log.n

"""Read trial logs (MCAP, also files cut short by a crash) and CSV files; export CSV.

Reading scans records in file order with `mcap.stream_reader.StreamReader`, so it does
not need the summary or footer a crashed writer never wrote: it stops at the first
truncated or undecodable record and keeps everything before it.

Speed (`rig bench`, replay): a chunk is decompressed once and split into its records by
`mcap_chunks.split_chunk`, and the payloads of one topic in one chunk are decoded by a single
`json.loads` of a JSON array. Whenever that cannot give exactly what decoding message by
message gives (a record that does not fit its chunk, a payload that is not one JSON object,
anything raised), the chunk is read again by the library, message by message, as it always was:
what is read, and where reading stops, never depends on the fast path.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Attachment, Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from rig.errors import RigError
from rig.recording.mcap_chunks import LogStreamReader, chunk_bytes, split_chunk
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


class _Scan:
    """What the records read so far say; `rows` holds the decoded messages of the rig's topics."""

    def __init__(self) -> None:
        self.schemas_by_id: dict[int, dict] = {}
        self.channels: dict[int, str] = {}
        self.topic_schema: dict[str, dict] = {}
        self.rows: dict[str, list[dict]] = {SAMPLE_TOPIC: [], EVENT_TOPIC: [], HEALTH_TOPIC: []}
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self.complete = False
        self.seen_any = False  # a record was read: the file is an MCAP log, however damaged

    def record(self, rec: Any) -> None:
        """One record, as the reader has always taken it (a message decoded on its own)."""
        self.seen_any = True
        if isinstance(rec, Message):
            topic = self.channels.get(rec.channel_id)
            if topic in self.rows:
                self.rows[topic].append(json.loads(rec.data))
        elif isinstance(rec, Channel):
            self.channels[rec.id] = rec.topic
            if rec.schema_id in self.schemas_by_id:
                self.topic_schema[rec.topic] = self.schemas_by_id[rec.schema_id]
        elif isinstance(rec, Schema):
            self.schemas_by_id[rec.id] = json.loads(rec.data) if rec.data else {}
        elif isinstance(rec, Metadata):
            self.metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Attachment):
            self.attachments[rec.name] = bytes(rec.data)
        elif isinstance(rec, Footer):
            self.complete = True

    def chunk(self, chunk: Chunk) -> None:
        if not self._chunk_at_once(chunk):
            # The library's own reading of the chunk: its errors, and a message that does not
            # decode ending the log after the messages before it, exactly as before.
            for rec in breakup_chunk(chunk):
                self.record(rec)

    def _chunk_at_once(self, chunk: Chunk) -> bool:
        """The chunk's records taken together; False (nothing changed) where that might differ
        in any way from taking them one by one."""
        try:
            split = split_chunk(chunk_bytes(chunk))
            if split is None:
                return False
            schemas_by_id, channels = dict(self.schemas_by_id), dict(self.channels)
            topic_schema = dict(self.topic_schema)
            payloads: dict[str, list[bytes]] = {topic: [] for topic in self.rows}
            for rec in split.records:  # in order: a channel maps the messages after it
                if isinstance(rec, dict):
                    topics = [channels.get(channel_id) for channel_id in rec]
                    if len(set(topics)) < len(topics):
                        return False  # two channels of one topic: their messages interleave
                    for topic, run in zip(topics, rec.values(), strict=True):
                        if topic in payloads:
                            payloads[topic] += run
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                    if rec.schema_id in schemas_by_id:
                        topic_schema[rec.topic] = schemas_by_id[rec.schema_id]
                elif isinstance(rec, Schema):
                    schemas_by_id[rec.id] = json.loads(rec.data) if rec.data else {}
            decoded = {topic: decode_objects(p) for topic, p in payloads.items() if p}
        except Exception:  # noqa: BLE001 - anything unusual is left to the library's own reading
            return False
        if any(d is None for d in decoded.values()):
            return False
        for topic, d in decoded.items():
            self.rows[topic].extend(d)
        self.schemas_by_id, self.channels, self.topic_schema = schemas_by_id, channels, topic_schema
        self.seen_any = self.seen_any or split.count > 0
        return True


def decode_objects(payloads: list[bytes]) -> list[dict] | None:
    """`[json.loads(p) for p in payloads]` in one call, when each payload is one JSON object;
    None when the batch does not come back as one object per payload (then decode one by one).

    A payload that is not one JSON object on its own breaks the array, or changes its length or
    the type of an element, unless other malformed payloads of the same topic and chunk make up
    for it exactly: `{"a":"}` and `{"}` read together as one object, `{},{}` as two. Truncation
    and damage to a file do not write such sets; only a writer that means to could."""
    values = json.loads(b"[" + b",".join(payloads) + b"]")
    if len(values) != len(payloads) or set(map(type, values)) != {dict}:
        return None
    return values


def read_log(path: str | Path, keep_raw: bool = False) -> TrialLog:
    """Read a trial log; raises RigError for a file that is not an MCAP log at all."""
    path = Path(path)
    try:
        fh = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise RigError(f"{path}: cannot open log: {exc.strerror or exc}") from None
    scan = _Scan()
    error = ""
    with fh:
        try:
            for rec in LogStreamReader(fh, record_size_limit=1 << 30).records:
                if isinstance(rec, Chunk):
                    scan.chunk(rec)
                else:
                    scan.record(rec)
        # A truncated record, a short read or a corrupt chunk (zstd, CRC) ends the readable part.
        except Exception as exc:  # noqa: BLE001
            error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            if not scan.seen_any:
                raise RigError(f"{path}: not a readable MCAP log ({error})") from None
    rows = scan.rows
    try:
        cols, kinds, contact = sample_columns(rows[SAMPLE_TOPIC])
        frames = frame_track(cols, kinds, rows[EVENT_TOPIC])
    # valid JSON that is not what the rig writes (a sample that is not an object, a field that is
    # not a number): said as such, with the message, rather than as a traceback
    except (AttributeError, TypeError, ValueError, KeyError, OverflowError) as exc:
        raise RigError(f"{path}: {_unreadable(rows, exc)}") from None
    return TrialLog(
        path=path, samples=cols, step_kind=kinds, frames=frames,
        contact=contact, events=rows[EVENT_TOPIC], health=rows[HEALTH_TOPIC], metadata=scan.metadata,
        attachments=scan.attachments, schemas=scan.topic_schema, complete=scan.complete, read_error=error,
        raw_messages=rows if keep_raw else {},
    )


def sample_columns(samples: list[dict]) -> tuple[dict[str, np.ndarray], list[str], np.ndarray]:
    """The numeric columns, the step kinds and the contact flags of the sample messages.

    All columns are converted by one `np.array` call over the rows' values; numpy converts each
    value as it does column by column. Rows that lack a field, or hold a value that is not one
    number, are read column by column with the defaults (NaN, "", False)."""
    names = list(SAMPLE.numeric)
    # the optional ones are present when a model ran in the loop
    names += [name for name in SAMPLE.optional_numeric if samples and name in samples[0]]
    try:
        table = np.array(list(map(itemgetter(*names), samples)), dtype=float)
        kinds = list(map(itemgetter("step_kind"), samples))
        contact = np.array(list(map(itemgetter("contact"), samples)))
        fast = table.shape == (len(samples), len(names)) and contact.dtype == bool
    except Exception:  # noqa: BLE001 - a missing field or an odd value: read below, one value at a time
        fast = False
    if fast:
        return {name: np.array(table[:, j]) for j, name in enumerate(names)}, kinds, contact
    cols = {name: np.array([s.get(name, np.nan) for s in samples], dtype=float) for name in names}
    kinds = [s.get("step_kind", "") for s in samples]
    contact = np.array([bool(s.get("contact", False)) for s in samples])
    return cols, kinds, contact


def _unreadable(rows: dict[str, list], exc: Exception) -> str:
    """Which message of a log cannot be read as the rig's, and why."""
    for topic, messages in rows.items():
        for i, message in enumerate(messages):
            if not isinstance(message, dict):
                return f"message {i + 1} on {topic} is not a JSON object: {json.dumps(message)[:80]}"
    for i, sample in enumerate(rows[SAMPLE_TOPIC]):
        for name in (*SAMPLE.numeric, *SAMPLE.optional_numeric):
            try:
                np.array([sample.get(name, np.nan)], dtype=float)
            except (TypeError, ValueError):
                return f"message {i + 1} on {SAMPLE_TOPIC}: {name} is not a number: {sample[name]!r:.80}"
    return f"its messages cannot be read as the rig's ({type(exc).__name__}: {exc})"


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
    working = _working_zeros(step, zeros, start)
    slider = cols.get("slider_mm")
    if slider is None or np.isnan(slider).any():
        before = np.concatenate([[start], working[:-1]]) if n else working
        slider = cols["position_mm"] + before if n else np.zeros(0)
    # an approach (and the tare before it) belongs to the surface it goes on to find: each of its
    # samples takes the zero of the next sample that is neither (the last sample keeps its own)
    belongs = np.array([k in ("approach", "tare") for k in kinds[:-1]] + [False]) if n else np.zeros(0, bool)
    index = np.arange(n)
    source = np.minimum.accumulate(np.where(belongs, n, index)[::-1])[::-1]
    surface = working[source]
    return FrameTrack(np.asarray(slider, dtype=float), working, surface, start)


def _working_zeros(step: np.ndarray, zeros: dict[int, float], start: float) -> np.ndarray:
    """The working zero after every tick: a sample whose step has a known zero_mm takes it, any
    other (no step, or a step without a step_start event) keeps the zero before it."""
    step = np.asarray(step, dtype=float)
    n = len(step)
    stepped = ~np.isnan(step)
    if not (np.abs(step[stepped]) < 2.0 ** 62).all():  # not an int64: the loop converts any number
        working, zero = np.empty(n), start
        for i in range(n):
            if stepped[i]:
                zero = zeros.get(int(step[i]), zero)
            working[i] = zero
        return working
    number = np.where(stepped, step, 0.0).astype(np.int64)  # truncates toward zero, as int() does
    found = np.zeros(n, dtype=bool)
    value = np.zeros(n)
    for k in np.unique(number[stepped]).tolist():
        if k in zeros:
            here = stepped & (number == k)
            found |= here
            value[here] = zeros[k]
    last = np.maximum.accumulate(np.where(found, np.arange(n), -1)) if n else np.zeros(0, np.int64)
    return np.where(last >= 0, value[last], start)


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

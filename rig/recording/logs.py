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

Faster still (3-5x): a log the recorder finished carries its sample columns in binary, as an
attachment (`columns.py`; json.loads alone caps decoding near 300k samples/s). When the summary
lists it, the file is walked whole in memory (`_whole_records`, strict: any record out of place
and it gives up), events and health are decoded as above, and the sample messages are only
stepped over and counted. The columns are taken if they are consistent with the file: read to its
footer without a fault, every chunk's CRC right (the messages are the bytes that were written),
as many /rig/sample messages as the attachment has samples and as the summary's statistics count,
and the first and last of them decoding to the attachment's first and last rows, bit for bit.
Otherwise (a log cut short, one from before the columns, one altered by some tool, anything
unexpected) the file is read again as above, decoding every message; so `read_log` returns the
same either way, and where that reading stops or what it says of a damaged file is as before.
"""

from __future__ import annotations

import csv
import json
import mmap
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from operator import itemgetter
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    Footer,
    Message,
    Metadata,
    Schema,
    Statistics,
)
from mcap.stream_reader import breakup_chunk

from rig.errors import RigError
from rig.recording.columns import ATTACHMENT_NAME, Columns, read_columns
from rig.recording.mcap_chunks import LogStreamReader, chunk_bytes, split_chunk
from rig.recording.messages import EVENT_TOPIC, HEALTH_TOPIC, SAMPLE, SAMPLE_TOPIC
from rig.specs.frames import Frame, FrameTrack

_FOOTER = struct.Struct("<BQQQI")  # opcode, length 20, summary start, summary offset start, CRC
_RECORD = struct.Struct("<BQ")
_LENGTH = struct.Struct("<Q")
MAGIC = b"\x89MCAP0\r\n"


@dataclass
class TrialLog:
    """An MCAP trial log as read back (`read_log`): the samples as columns, the events and health
    records, the trial's metadata and attachments (its config and protocol as run, the sample
    columns), and whether the writer finished (``complete``; ``read_error`` says why a truncated
    file stopped)."""

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
    from_columns: bool = False  # the samples came from the attached columns, not decoded from messages

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

    def __init__(self, defer_samples: bool = False) -> None:
        # With `defer_samples` (a log that says it has its columns attached) the sample messages
        # are only counted, their first and last payloads kept; `verified` while every chunk was
        # split at once and its CRC is right
        self.defer_samples = defer_samples
        self._zstd = zstandard.ZstdDecompressor()
        self.samples = 0
        self.first_sample: bytes | None = None
        self.last_sample: bytes | None = None
        self.verified = True
        self.statistics: Statistics | None = None
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
            if topic == SAMPLE_TOPIC and self.defer_samples:
                self.verified = False  # a message outside a chunk, or a chunk read one by one
            elif topic in self.rows:
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
        elif isinstance(rec, Statistics):
            self.statistics = rec
        elif isinstance(rec, Footer):
            self.complete = True

    def chunk(self, chunk: Chunk) -> None:
        if not self._chunk_at_once(chunk):
            self.verified = False
            # The library's own reading of the chunk: its errors, and a message that does not
            # decode ending the log after the messages before it, exactly as before.
            for rec in breakup_chunk(chunk):
                self.record(rec)

    def _chunk_at_once(self, chunk: Chunk) -> bool:
        """The chunk's records taken together; False (nothing changed) where that might differ
        in any way from taking them one by one."""
        try:
            data = chunk_bytes(chunk, self._zstd)
            count_only = frozenset()
            if self.defer_samples:
                count_only = frozenset(i for i, topic in self.channels.items() if topic == SAMPLE_TOPIC)
            split = split_chunk(data, count_only)
            if split is None:
                return False
            if self.defer_samples and self.verified:
                # 0 is "no CRC written": then nothing says these are the bytes the columns came from
                self.verified = chunk.uncompressed_crc != 0 and zlib.crc32(data) == chunk.uncompressed_crc
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
            deferred = payloads.pop(SAMPLE_TOPIC) if self.defer_samples else []
            if deferred and split.counted:
                return False  # samples on a channel known before and on one defined here
            decoded = {topic: decode_objects(p) for topic, p in payloads.items() if p}
        except Exception:  # noqa: BLE001 - anything unusual is left to the library's own reading
            self._zstd = zstandard.ZstdDecompressor()  # no state of a failed chunk carried on
            return False
        if any(d is None for d in decoded.values()):
            return False
        if deferred:
            self._deferred(len(deferred), deferred[0], deferred[-1])
        elif split.counted:
            self._deferred(split.counted, split.first, split.last)
        for topic, d in decoded.items():
            self.rows[topic].extend(d)
        self.schemas_by_id, self.channels, self.topic_schema = schemas_by_id, channels, topic_schema
        self.seen_any = self.seen_any or split.count > 0
        return True

    def _deferred(self, count: int, first: bytes | None, last: bytes | None) -> None:
        if self.first_sample is None:
            self.first_sample = first
        self.last_sample = last
        self.samples += count


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
    """Read a trial log; raises RigError for a file that is not an MCAP log at all.

    Unless `keep_raw` (every message decoded and returned), a log's attached sample columns are
    used when they are consistent with it (see the module's docstring)."""
    path = Path(path)
    if not keep_raw:
        log = _read_attached(path)
        if log is not None:
            return log
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


def _read_attached(path: Path) -> TrialLog | None:
    """The log, its samples from the attached columns; None unless the file is whole, ends in its
    footer, and the columns are consistent with it. Then nothing here has said anything: the
    caller reads the file as always (and says what is wrong with it, if anything)."""
    try:
        with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
            if not _says_columns_attached(data):
                return None
            scan = _Scan(defer_samples=True)
            for rec in _whole_records(data):
                if isinstance(rec, Chunk):
                    scan.chunk(rec)
                else:
                    scan.record(rec)
        columns = _attached_columns(scan)
        if columns is None:
            return None
        rows = scan.rows
        frames = frame_track(columns.samples, columns.step_kind, rows[EVENT_TOPIC])
    except Exception:  # noqa: BLE001 - anything at all: the messages are read instead
        return None
    return TrialLog(
        path=path, samples=columns.samples, step_kind=columns.step_kind, frames=frames,
        contact=columns.contact, events=rows[EVENT_TOPIC], health=rows[HEALTH_TOPIC], metadata=scan.metadata,
        attachments=scan.attachments, schemas=scan.topic_schema, complete=scan.complete, read_error="",
        from_columns=True,
    )


# Records the reader's state depends on; all others (header, indexes, summary offsets, data end)
# are passed over, as by the library's scan once parsed.
_PARSED = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.MESSAGE: Message, Opcode.METADATA: Metadata,
           Opcode.ATTACHMENT: Attachment, Opcode.STATISTICS: Statistics}
_CHUNK_HEAD = struct.Struct("<QQQII")  # start and end time, uncompressed size and CRC, compression's length


def _whole_records(data: mmap.mmap) -> Iterator[Any]:
    """The records of a whole MCAP file in memory, as the library's scan yields them (chunks as
    `Chunk`), for a file that is all there and well formed; anything else raises ValueError.
    The library reads a file through a stream, field by field; here the file is walked with
    struct, and only the few records that matter are parsed (by the library's record classes)."""
    end = len(data)
    if data[:8] != MAGIC or data[end - 8:] != MAGIC:
        raise ValueError("no magic")
    pos, end = 8, end - 8
    while pos < end:
        opcode, length = _RECORD.unpack_from(data, pos)
        body, pos = pos + 9, pos + 9 + length
        if pos > end:
            raise ValueError("a record overruns the file")
        if opcode == Opcode.CHUNK:
            start, stop, size, crc, n = _CHUNK_HEAD.unpack_from(data, body)
            at = body + _CHUNK_HEAD.size
            compression = data[at:at + n].decode()
            (records,) = _LENGTH.unpack_from(data, at + n)
            if at + n + 8 + records != pos:
                raise ValueError("a chunk's fields do not fill it")
            yield Chunk(compression=compression, data=data[at + n + 8:pos], message_start_time=start,
                        message_end_time=stop, uncompressed_crc=crc, uncompressed_size=size)
        elif opcode in _PARSED:
            stream = ReadDataStream(BytesIO(data[body:pos]))
            rec = _PARSED[opcode].read(stream)
            if stream.count != length:
                raise ValueError("a record's fields do not fill it")
            yield rec
        elif opcode == Opcode.FOOTER:
            if pos != end:
                raise ValueError("records after the footer")
            yield Footer.read(ReadDataStream(BytesIO(data[body:pos])))


def _says_columns_attached(data: mmap.mmap) -> bool:
    """Whether the log's summary lists the sample columns' attachment: the footer, then the
    summary's attachment indexes. Only which way to read depends on this (any doubt: decode)."""
    footer_at = len(data) - _FOOTER.size - 8
    if footer_at < 8:
        return False
    opcode, length, summary_start, _offsets, _crc = _FOOTER.unpack_from(data, footer_at)
    if opcode != Opcode.FOOTER or length != 20 or not 8 <= summary_start < footer_at:
        return False
    summary = data[summary_start:footer_at]
    pos = 0
    while pos + 9 <= len(summary):
        opcode, length = _RECORD.unpack_from(summary, pos)
        body, pos = pos + 9, pos + 9 + length
        if opcode == Opcode.ATTACHMENT_INDEX and pos <= len(summary):
            index = AttachmentIndex.read(ReadDataStream(BytesIO(summary[body:pos])))
            if index.name == ATTACHMENT_NAME:
                return True
    return False


def _attached_columns(scan: _Scan) -> Columns | None:
    """The attached sample columns, when they are consistent with the file; else None."""
    data = scan.attachments.get(ATTACHMENT_NAME)
    if data is None or not (scan.complete and scan.verified and scan.statistics and scan.samples):
        return None
    n = scan.samples
    counted = sum(count for channel_id, count in scan.statistics.channel_message_counts.items()
                  if scan.channels.get(channel_id) == SAMPLE_TOPIC)
    if counted != n:
        return None
    columns = read_columns(data)
    if columns is None or columns.n != n:
        return None
    try:
        ends = [json.loads(scan.first_sample), json.loads(scan.last_sample)]
        cols, kinds, contact = sample_columns(ends)
    except Exception:  # noqa: BLE001 - the messages are read one by one, and what is wrong said there
        return None
    dense = [name for name in columns.samples if name not in SAMPLE.sparse_numeric]
    if [name for name in cols if name not in SAMPLE.sparse_numeric] != dense \
            or kinds != [columns.step_kind[0], columns.step_kind[-1]]:
        return None
    for name in SAMPLE.sparse_numeric:  # present in the ends or not, they must agree there
        if name in columns.samples:
            cols[name] = np.array([e.get(name, np.nan) for e in ends], dtype=float)
    if not np.array_equal(contact, columns.contact[[0, -1]]):
        return None
    for name, ends_col in cols.items():
        if not np.array_equal(ends_col.view(np.uint64), columns.samples[name][[0, -1]].view(np.uint64)):
            return None
    if [ends[0]["seq"], ends[1]["seq"]] != [columns.header.get("first_seq"), columns.header.get("last_seq")]:
        return None
    return columns


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
        cols = {name: np.array(table[:, j]) for j, name in enumerate(names)}
    else:
        cols = {name: np.array([s.get(name, np.nan) for s in samples], dtype=float) for name in names}
        kinds = [s.get("step_kind", "") for s in samples]
        contact = np.array([bool(s.get("contact", False)) for s in samples])
    # a force step's setpoint and error, on its own ticks only
    for name in SAMPLE.sparse_numeric:
        if any(name in s for s in samples):
            cols[name] = np.array([s.get(name, np.nan) for s in samples], dtype=float)
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
    belongs = np.fromiter(map(("approach", "tare").__contains__, kinds), bool, n)  # no list of n bools
    belongs[-1:] = False
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

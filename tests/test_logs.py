"""MCAP logs: readable by the mcap library, messages valid against their own schemas,
readable after a crash, exported to CSV."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Chunk, Footer, Message, MessageIndex, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from rig.errors import RigError
from rig.models.catalogue import build_model
from rig.models.saved import SavedModel
from rig.recording.columns import ATTACHMENT_NAME, MEDIA_TYPE, ColumnBuilder
from rig.recording.logs import TrialLog, export_csv, read_log
from rig.recording.mcap_chunks import LogStreamReader, chunk_bytes, split_chunk
from rig.recording.messages import EVENT_TOPIC, HEALTH_TOPIC, SAMPLE, SAMPLE_TOPIC
from rig.records.csvfile import read_csv_trial
from rig.specs.config import RigConfig
from rig.specs.frames import FrameTrack
from rig.views.replay import summarize
from tests.conftest import PROTOCOLS, run_sim


@pytest.fixture(scope="module")
def demo_log(tmp_path_factory):
    return run_sim(PROTOCOLS / "demo.yaml", tmp_path=tmp_path_factory.mktemp("demo")).log_path


def test_mcap_reader_opens_log(demo_log):
    with open(demo_log, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {SAMPLE_TOPIC, EVENT_TOPIC, HEALTH_TOPIC}
        for ch in topics.values():
            assert ch.message_encoding == "json"
            assert summary.schemas[ch.schema_id].encoding == "jsonschema"
        counts = summary.statistics.channel_message_counts
        samples = counts[topics[SAMPLE_TOPIC].id]
        assert samples > 1000
        assert counts[topics[HEALTH_TOPIC].id] >= 10  # about 1 Hz over an 11 s trial
        names = [m.name for m in reader.iter_metadata()]
        assert names[0] == "trial" and "outcome" in names
        attachments = {a.name: a.data for a in reader.iter_attachments()}
        assert attachments["protocol.yaml"] == (PROTOCOLS / "demo.yaml").read_bytes()
        assert b"rate_Hz" in attachments["config.yaml"]


def test_every_message_validates_against_its_schema(demo_log):
    with open(demo_log, "rb") as fh:
        reader = make_reader(fh)
        validators = {}
        n = 0
        for schema, channel, message in reader.iter_messages():
            if channel.topic not in validators:
                validators[channel.topic] = jsonschema.Draft202012Validator(json.loads(schema.data))
            validators[channel.topic].validate(json.loads(message.data))
            n += 1
    assert n > 1000


def test_schema_rejects_a_bad_message(demo_log):
    """The schemas are real constraints, not decoration."""
    log = read_log(demo_log)
    validator = jsonschema.Draft202012Validator(log.schemas[SAMPLE_TOPIC])
    with pytest.raises(jsonschema.ValidationError):
        validator.validate({"seq": -1, "t_s": "now"})


def test_trial_metadata(demo_log):
    log = read_log(demo_log)
    trial = log.trial
    for key in ("specimen", "operator", "protocol_name", "start_time", "software_version",
                "config_digest"):
        assert key in trial
    assert trial["protocol_name"].startswith("demo")
    assert log.complete and log.outcome == "completed"
    kinds = [e["kind"] for e in log.events]
    assert kinds[0] == "trial_start" and kinds[-1] == "trial_end"
    assert kinds.count("step_start") == 3 and "tare" in kinds


def test_csv_export_round_trip(demo_log, tmp_path):
    log = read_log(demo_log)
    out = tmp_path / "demo.csv"
    assert export_csv(log, out) == log.n
    with open(out) as fh:
        header = next(csv.reader(fh))
    assert header[:3] == ["t_s", "position_mm", "force_N"]
    back = read_csv_trial(out)
    assert np.array_equal(back["force_N"], log.samples["force_N"])
    assert np.array_equal(back["t_s"], log.samples["t_s"])


def test_truncated_log_reads_up_to_the_cut(demo_log, tmp_path):
    data = demo_log.read_bytes()
    full = read_log(demo_log).n
    cut = tmp_path / "cut.mcap"
    with open(demo_log, "rb") as fh:  # two thirds into the messages: the columns come after them
        (columns,) = [a for a in make_reader(fh).get_summary().attachment_indexes if a.name == ATTACHMENT_NAME]
    cut.write_bytes(data[: columns.offset * 2 // 3])
    log = read_log(cut)
    assert not log.complete and log.outcome == "interrupted"
    assert 0 < log.n < full
    assert np.array_equal(log.samples["seq"], np.arange(log.n))  # a clean prefix
    assert summarize(log)["samples"] == log.n


def test_not_a_log_is_a_clear_error(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"this is not mcap at all")
    with pytest.raises(RigError, match="not a readable MCAP log"):
        read_log(bad)
    with pytest.raises(RigError, match="cannot open"):
        read_log(tmp_path / "missing.mcap")


@pytest.mark.parametrize("text,fragment", [
    ("t_s,position_mm\n0,1\n", "missing column(s) force_N"),
    ("t_s,position_mm,force_N\n0,1,2\n0.01,x,2\n", "bad.csv:3: column position_mm: 'x' is not"),
    ("t_s,position_mm,force_N\n0,1,2\n0.01,1,nan\n", "NaN"),
    ("t_s,position_mm,force_N\n0,1,2\n0.02,1,2\n0.01,1,2\n", "unsorted"),
    ("t_s,position_mm,force_N\n0,1,2\n0,1,2\n", "duplicated"),
    ("", "empty"),
])
def test_bad_csv(tmp_path, text, fragment):
    from rig.errors import SpecError

    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(SpecError) as info:
        read_csv_trial(p)
    assert fragment in str(info.value)


# ------------------------------------------------ the reader against decoding message by message

def _read_log_per_message(path, keep_raw=False) -> TrialLog:
    """The reader as it was before chunks were decoded at once (rig 0.1, 2026-11): every record
    through `StreamReader`, every message through its own `json.loads`, columns and zeros one
    sample at a time. The reference the fast reader must match in every field."""
    path = Path(path)
    try:
        fh = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise RigError(f"{path}: cannot open log: {exc.strerror or exc}") from None
    schemas_by_id, channels, topic_schema = {}, {}, {}
    rows = {SAMPLE_TOPIC: [], EVENT_TOPIC: [], HEALTH_TOPIC: []}
    metadata, attachments = {}, {}
    complete, error, seen_any = False, "", False
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
        except Exception as exc:  # noqa: BLE001
            error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            if not seen_any:
                raise RigError(f"{path}: not a readable MCAP log ({error})") from None
    samples = rows[SAMPLE_TOPIC]
    cols = {name: np.array([s.get(name, np.nan) for s in samples], dtype=float) for name in SAMPLE.numeric}
    for name in SAMPLE.optional_numeric:
        if samples and name in samples[0]:
            cols[name] = np.array([s.get(name, np.nan) for s in samples], dtype=float)
    kinds = [s.get("step_kind", "") for s in samples]
    frames = _frame_track_per_sample(cols, kinds, rows[EVENT_TOPIC])
    return TrialLog(
        path=path, samples=cols, step_kind=kinds, frames=frames,
        contact=np.array([bool(s.get("contact", False)) for s in samples]),
        events=rows[EVENT_TOPIC], health=rows[HEALTH_TOPIC], metadata=metadata,
        attachments=attachments, schemas=topic_schema, complete=complete, read_error=error,
        raw_messages=rows if keep_raw else {},
    )


def _frame_track_per_sample(cols, kinds, events) -> FrameTrack:
    n = len(cols.get("t_s", ()))
    start = next((float(e["data"]["start_mm"]) for e in events
                  if e.get("kind") == "trial_start" and "start_mm" in (e.get("data") or {})), 0.0)
    zeros = {}
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
    surface = working.copy()
    for i in range(n - 2, -1, -1):
        if kinds[i] in ("approach", "tare"):
            surface[i] = surface[i + 1]
    return FrameTrack(np.asarray(slider, dtype=float), working, surface, start)


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal value for value, NaN payload and sign of zero included."""
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype == float:
        return np.array_equal(a.view(np.uint64), b.view(np.uint64))
    return np.array_equal(a, b)


def _assert_same_log(new: TrialLog, ref: TrialLog) -> None:
    """Every field of two readings of a log the same, bit for bit (raw_messages apart)."""
    assert list(new.samples) == list(ref.samples)
    for name in ref.samples:
        assert _same_bits(new.samples[name], ref.samples[name]), name
        assert new.samples[name].flags.writeable, name  # callers may change them in place
    assert new.step_kind == ref.step_kind
    assert _same_bits(new.contact, ref.contact)
    for name in ("events", "health", "metadata", "attachments", "schemas", "complete", "read_error"):
        assert getattr(new, name) == getattr(ref, name), name
    assert list(new.metadata) == list(ref.metadata) and list(new.attachments) == list(ref.attachments)
    for name in ("slider_mm", "working_zero_mm", "surface_mm"):
        assert _same_bits(getattr(new.frames, name), getattr(ref.frames, name)), name
    assert new.frames.start_mm == ref.frames.start_mm


def uses_columns(path) -> bool:
    """Whether `read_log` takes this log's samples from its attached columns."""
    return read_log(path).from_columns


def assert_reads_as_per_message(path, columns: bool | None = None) -> TrialLog:
    """`read_log` gives, field for field, what decoding message by message gives: with `keep_raw`
    (every message decoded) and without (from the attached columns where a log has them; whether
    it does is checked when `columns` says)."""
    new, ref = read_log(path, keep_raw=True), _read_log_per_message(path, keep_raw=True)
    _assert_same_log(new, ref)
    assert new.raw_messages == ref.raw_messages  # every message, in order, on every topic
    assert list(new.raw_messages) == list(ref.raw_messages)
    assert new.events is new.raw_messages[EVENT_TOPIC] and new.health is new.raw_messages[HEALTH_TOPIC]
    plain = read_log(path)
    assert plain.raw_messages == {} and not new.from_columns
    _assert_same_log(plain, ref)
    if columns is not None:
        assert uses_columns(path) == columns
    return new


def _small_chunks(compression: str) -> RigConfig:
    """Chunks closed about every millisecond of the writer's time: many chunks and indexes even in
    virtual time, as a real-clock trial (one chunk a second) has."""
    config = RigConfig()
    config.recorder.compression = compression
    config.recorder.flush_s = 0.001
    return config


@pytest.fixture(scope="module")
def sim_logs(tmp_path_factory, demo_log, paper_075_log) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("readers")
    logs = {"demo-zstd": demo_log, "paper-zstd": paper_075_log.log_path}
    for compression in ("zstd", "lz4", "none"):
        logs[f"demo-small-chunks-{compression}"] = run_sim(
            PROTOCOLS / "demo.yaml", _small_chunks(compression), tmp_path=tmp,
            name=f"demo-{compression}.mcap").log_path
    logs["approach-lz4"] = run_sim(PROTOCOLS / "approach-relax.yaml", _small_chunks("lz4"), tmp_path=tmp,
                                   name="approach.mcap").log_path
    # a model in the loop: the optional force_model_N and model_error_N in every sample
    model = tmp / "model.json"
    model.write_text(SavedModel(build_model("proposed"), {
        "k1_N_per_m3": 5.6e4, "k2_N_per_m2": 550.0, "k3_N_per_m": 14.0, "tau2_N_s_per_m2": 2.3e5,
        "tau1_s": 8.0}).text())
    logs["model-zstd"] = run_sim(PROTOCOLS / "paper-3mm_s.yaml", tmp_path=tmp, name="model.mcap",
                                 model_path=str(model)).log_path
    # a fault: a specimen three times as stiff goes over the protocol's force limit
    stiff = _small_chunks("none")
    for name in ("k1_N_per_m3", "k2_N_per_m2", "k3_N_per_m", "tau2_N_s_per_m2"):
        setattr(stiff.sim.tissue, name, getattr(stiff.sim.tissue, name) * 3)
    logs["fault-none"] = run_sim(PROTOCOLS / "paper-3mm_s.yaml", stiff, tmp_path=tmp,
                                 name="fault.mcap").log_path
    return logs


SIM_LOGS = ["demo-zstd", "paper-zstd", "demo-small-chunks-zstd", "demo-small-chunks-lz4",
            "demo-small-chunks-none", "approach-lz4", "model-zstd", "fault-none"]


@pytest.mark.parametrize("name", SIM_LOGS)
def test_reads_as_decoding_message_by_message(sim_logs, name):
    """Every log the rig finishes has its columns attached, and reads through them exactly as
    by decoding its messages."""
    log = assert_reads_as_per_message(sim_logs[name], columns=True)
    assert log.complete and log.n > 700 and not log.read_error
    assert np.array_equal(log.samples["seq"], np.arange(log.n))  # none dropped, none reordered
    if name.startswith("approach"):
        assert "approach" in log.step_kind and not np.array_equal(log.frames.surface_mm,
                                                                   log.frames.working_zero_mm)
    optional = {"force_model_N", "model_error_N"} & set(log.samples)
    assert optional == ({"force_model_N", "model_error_N"} if name.startswith("model") else set())
    assert (log.outcome == "fault") == name.startswith("fault")


def test_the_simulators_logs_never_need_the_slow_path(sim_logs, monkeypatch):
    """Every chunk the rig writes is split and decoded at once (the library's per-message
    reading of a chunk is only for what the fast path cannot be sure of)."""
    import rig.recording.logs as logs

    def no_slow_path(chunk, *args, **kwargs):
        raise AssertionError("a chunk of the rig's own log was read message by message")

    monkeypatch.setattr(logs, "breakup_chunk", no_slow_path)
    for path in sim_logs.values():
        assert read_log(path).complete


def _count_slow_chunks(monkeypatch) -> list[int]:
    import rig.recording.logs as logs

    calls = [0]

    def counted(chunk, *args, **kwargs):
        calls[0] += 1
        return breakup_chunk(chunk, *args, **kwargs)

    monkeypatch.setattr(logs, "breakup_chunk", counted)
    return calls


def _chunks(path) -> list:
    with open(path, "rb") as fh:
        return [r for r in StreamReader(fh, emit_chunks=True).records if isinstance(r, Chunk)]


def test_chunks_split_as_the_library_splits_them(sim_logs):
    """Every chunk of every log: the same messages per channel, in order, and the same schema and
    channel records as `breakup_chunk`."""
    for path in sim_logs.values():
        chunks = _chunks(path)
        assert chunks
        for chunk in chunks:
            split = split_chunk(chunk_bytes(chunk))
            library = breakup_chunk(chunk)
            assert split is not None and split.count == len(library)
            ours = {}
            for rec in split.records:
                for channel_id, payloads in (rec.items() if isinstance(rec, dict) else ()):
                    ours.setdefault(channel_id, []).extend(payloads)
            theirs = {}
            for rec in library:
                if isinstance(rec, Message):
                    theirs.setdefault(rec.channel_id, []).append(rec.data)
            assert ours == theirs
            assert [r for r in split.records if not isinstance(r, dict)] == \
                [r for r in library if not isinstance(r, Message)]


def test_message_indexes_are_read_past_not_decoded(sim_logs):
    """The scan yields what the library's scan yields, but no message index entries."""
    path = sim_logs["demo-small-chunks-zstd"]
    with open(path, "rb") as fh:
        theirs = list(StreamReader(fh, emit_chunks=True, record_size_limit=1 << 30).records)
    with open(path, "rb") as fh:
        ours = list(LogStreamReader(fh, record_size_limit=1 << 30).records)
    assert [type(r) for r in ours] == [type(r) for r in theirs]
    indexes = [(a, b) for a, b in zip(ours, theirs, strict=True) if isinstance(b, MessageIndex)]
    assert len(indexes) > 10
    assert all(a.channel_id == b.channel_id and a.records == [] and b.records for a, b in indexes)
    assert [a for a in ours if not isinstance(a, MessageIndex)] == \
        [b for b in theirs if not isinstance(b, MessageIndex)]


def _cut_points(path) -> list[int]:
    """Where a crash may cut a log: spread over the file, and at and just past the start of every
    chunk, message index and summary record (inside their opcode, length and first fields)."""
    size = path.stat().st_size
    points = set(range(8, size, max(size // 30, 1)))
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    chunks = summary.chunk_indexes[:8]
    starts = [c.chunk_start_offset for c in chunks] + [c.chunk_start_offset + c.chunk_length for c in chunks]
    starts += [offset for c in chunks for offset in c.message_index_offsets.values()]
    starts += [summary.chunk_indexes[-1].chunk_start_offset + summary.chunk_indexes[-1].chunk_length]
    for start in starts:
        points.update(start + d for d in (0, 1, 5, 9, 11, 17, 40, 200))
    return sorted(p for p in points if 0 < p < size)


@pytest.mark.parametrize("name", ["demo-small-chunks-zstd", "demo-small-chunks-none"])
def test_a_log_cut_anywhere_reads_as_decoding_message_by_message(sim_logs, tmp_path, name):
    """A log cut short anywhere: the same samples (a clean prefix), the same error, or the same
    clear RigError for a cut before the first record."""
    data = sim_logs[name].read_bytes()
    cut = tmp_path / "cut.mcap"
    prefixes = errors = 0
    for point in _cut_points(sim_logs[name]):
        cut.write_bytes(data[:point])
        try:
            ref = _read_log_per_message(cut)
        except RigError as exc:
            with pytest.raises(RigError) as info:
                read_log(cut)
            assert str(info.value) == str(exc)
            errors += 1
            continue
        log = assert_reads_as_per_message(cut, columns=False)  # a log cut short: its messages decoded
        assert log.n == ref.n and np.array_equal(log.samples["seq"], np.arange(log.n))
        # or in the closing magic, or just before it (the footer whole)
        assert log.read_error and (not log.complete or point >= len(data) - 8)
        prefixes += 1
    assert prefixes > 100 and errors >= 1


def test_a_damaged_payload_ends_the_log_where_it_always_did(sim_logs, tmp_path, monkeypatch):
    """A message that does not decode (a flipped byte in an uncompressed chunk) stops reading at
    that message, after the messages before it in the same chunk, as decoding one by one did."""
    data = sim_logs["demo-small-chunks-none"].read_bytes()
    at = data.index(b'{"seq":500,')
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(data[:at + 7] + b"?" + data[at + 8:])  # {"seq":?00,
    # the columns are there, and consistent in count and ends, but the chunk's CRC is not right
    assert ATTACHMENT_NAME.encode() in damaged.read_bytes()
    log = assert_reads_as_per_message(damaged, columns=False)
    assert log.n == 500 and log.read_error.startswith("JSONDecodeError")
    slow = _count_slow_chunks(monkeypatch)
    read_log(damaged)
    assert slow[0] == 1  # that chunk alone, read again message by message


def _hand_made_log(path, messages: list[tuple[int, bytes]], topics: tuple[str, ...] = (SAMPLE_TOPIC,),
                   chunk_size: int = 1 << 20) -> Path:
    """A log written by the mcap library alone: channel i+1 on topics[i], the given payloads."""
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=chunk_size)
        w.start()
        sid = w.register_schema("rig.Sample", "jsonschema", b"{}")
        for topic in topics:
            w.register_channel(topic, "json", sid)
        for i, (channel, payload) in enumerate(messages):
            w.add_message(channel, log_time=i, data=payload, publish_time=i, sequence=i)
        w.finish()
    return path


def _sample(seq: int, **changes) -> bytes:
    row = {"seq": seq, "t_s": seq / 100, "position_mm": 1.0, "position_cmd_mm": 1.0, "force_N": 0.1 * seq,
           "stiffness_N_per_m": 80.0, "force_pred_N": 0.5, "error_N": 0.0, "forgetting": 1.0,
           "contact": True, "step": 0, "step_kind": "ramp", "late_ms": 0.0}
    row.update(changes)
    return json.dumps({k: v for k, v in row.items() if v is not ...}).encode()


@pytest.mark.parametrize("case", ["odd-values", "missing-fields", "not-an-object", "not-a-number",
                                  "two-channels-one-topic", "utf8-bom", "one-message-per-chunk", "empty"])
def test_unusual_payloads_read_as_decoding_message_by_message(tmp_path, case, monkeypatch):
    """Logs the rig never writes, which must still read exactly as before (through the slow path
    where the fast one cannot be sure)."""
    topics = (SAMPLE_TOPIC,)
    rows = [(1, _sample(i)) for i in range(300)]
    if case == "odd-values":  # numbers as strings, null, ints, bools, NaN; read as numpy converts them
        rows[10] = (1, _sample(10, force_N="1.5", t_s=None, late_ms=True, error_N=float("nan"), step=3))
        rows[11] = (1, _sample(11, contact=1, step_kind=7))
    elif case == "missing-fields":
        rows[20] = (1, _sample(20, contact=..., step_kind=..., force_N=...))
    elif case == "not-an-object":
        rows[30] = (1, b"[1, 2]")
    elif case == "not-a-number":
        rows[30] = (1, _sample(30, force_N={"N": 1}))
    elif case == "two-channels-one-topic":
        topics = (SAMPLE_TOPIC, SAMPLE_TOPIC)
        rows = [(1 + i % 2, _sample(i)) for i in range(300)]
    elif case == "utf8-bom":
        rows[40] = (1, b"\xef\xbb\xbf" + _sample(40))
    elif case == "empty":
        rows = []
    path = _hand_made_log(tmp_path / f"{case}.mcap", rows, topics,
                          chunk_size=1 if case == "one-message-per-chunk" else 1 << 20)
    if case in ("not-an-object", "not-a-number"):  # the old reader's traceback, now said as such
        with pytest.raises((AttributeError, TypeError)):
            _read_log_per_message(path)
        with pytest.raises(RigError) as info:
            read_log(path)
        assert str(info.value) == {
            "not-an-object": f"{path}: message 31 on /rig/sample is not a JSON object: [1, 2]",
            "not-a-number": f"{path}: message 31 on /rig/sample: force_N is not a number: {{'N': 1}}"}[case]
        return
    slow = _count_slow_chunks(monkeypatch)
    log = assert_reads_as_per_message(path)
    assert log.n == len(rows) and log.complete
    # payloads that are not one JSON object each, or one topic on two channels: read one by one
    assert (slow[0] > 0) == (case in ("utf8-bom", "two-channels-one-topic"))


# ------------------------------------------------------------- the sample columns, attached

def test_the_columns_are_a_plain_attachment(demo_log):
    """Any MCAP reader opens the log as before: the same channels and messages, and one more
    attachment, a zstd-compressed npz whose header and arrays match the messages."""
    import io

    import zstandard

    with open(demo_log, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        (sample_channel,) = [c.id for c in summary.channels.values() if c.topic == SAMPLE_TOPIC]
        seqs = [json.loads(m.data)["seq"] for _, c, m in reader.iter_messages() if c.topic == SAMPLE_TOPIC]
        (index,) = [a for a in summary.attachment_indexes if a.name == ATTACHMENT_NAME]
        assert index.media_type == MEDIA_TYPE == "application/zstd"
        (attachment,) = [a for a in reader.iter_attachments() if a.name == ATTACHMENT_NAME]
    npz = np.load(io.BytesIO(zstandard.ZstdDecompressor().decompress(attachment.data)), allow_pickle=False)
    header = json.loads(str(npz["header"]))
    assert header["samples"] == len(seqs) == summary.statistics.channel_message_counts[sample_channel]
    assert (header["first_seq"], header["last_seq"]) == (seqs[0], seqs[-1])
    log = _read_log_per_message(demo_log)
    for name in header["columns"]:
        assert _same_bits(npz[name], log.samples[name]), name
    assert np.array_equal(npz["contact"], log.contact)
    assert [header["step_kinds"][k] for k in npz["step_kind"]] == log.step_kind


def _rewrite(src: Path, dst: Path, *, columns: bytes | str | None = "keep", samples=None,
             crcs: bool = True) -> Path:
    """`src` written again by the mcap library: the same schemas, channels, metadata and
    attachments in order, the sample payloads through `samples(list) -> list` if given, and the
    columns' attachment kept, left out (None) or replaced."""
    from mcap.writer import Writer

    with open(src, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        messages = list(reader.iter_messages())
        metadata = [(m.name, m.metadata) for m in reader.iter_metadata()]
        attachments = list(reader.iter_attachments())
    sample_messages = [m for _, c, m in messages if c.topic == SAMPLE_TOPIC]
    payloads = [m.data for m in sample_messages]
    if samples is not None:
        payloads = samples(payloads)
    with open(dst, "wb") as fh:
        w = Writer(fh, enable_crcs=crcs)
        w.start()
        ids = {sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        channels = {cid: w.register_channel(c.topic, c.message_encoding, ids[c.schema_id])
                    for cid, c in summary.channels.items()}
        for name, data in metadata[:1]:
            w.add_metadata(name, data)
        k = 0
        for _, channel, m in messages:
            if channel.topic == SAMPLE_TOPIC:
                if k >= len(payloads):
                    continue
                data, k = payloads[k], k + 1
            else:
                data = m.data
            w.add_message(channels[m.channel_id], log_time=m.log_time, data=data, publish_time=m.publish_time,
                          sequence=m.sequence)
        for name, data in metadata[1:]:
            w.add_metadata(name, data)
        for a in attachments:
            data = a.data
            if a.name == ATTACHMENT_NAME:
                if columns is None:
                    continue
                data = data if columns == "keep" else columns
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, data)
        w.finish()
    return dst


def _columns_of(path) -> bytes:
    with open(path, "rb") as fh:
        return next(a.data for a in make_reader(fh).iter_attachments() if a.name == ATTACHMENT_NAME)


def _edit_columns(data: bytes, edit) -> bytes:
    """The attachment with its npz's arrays changed by `edit(dict)`."""
    import io

    import zstandard

    with np.load(io.BytesIO(zstandard.ZstdDecompressor().decompress(data))) as npz:
        arrays = {name: npz[name] for name in npz.files}
    edit(arrays)
    out = io.BytesIO()
    np.savez(out, **arrays)
    return zstandard.ZstdCompressor().compress(out.getvalue())


def _with_header(arrays: dict, **changes) -> None:
    header = json.loads(str(arrays["header"])) | changes
    arrays["header"] = np.array(json.dumps(header))


def _last_seq_changed(payloads: list[bytes]) -> list[bytes]:
    last = json.loads(payloads[-1])
    return [*payloads[:-1], json.dumps(last | {"seq": last["seq"] + 1}).encode()]


@pytest.mark.parametrize("case", ["kept", "left-out", "another-logs", "samples-dropped", "last-seq-changed",
                                  "a-value-changed", "header-says-other-ends", "damaged", "not-zstd",
                                  "no-chunk-crcs"])
def test_columns_are_used_only_when_consistent_with_the_log(sim_logs, tmp_path, case):
    """A log rewritten by the mcap library alone, with its columns kept (used), or not matching
    its messages in some way (not used: the messages are decoded). Either way the same log."""
    demo, other = sim_logs["demo-zstd"], sim_logs["paper-zstd"]
    columns, samples = "keep", None
    if case == "left-out":  # as a log from before the columns
        columns = None
    elif case == "another-logs":
        columns = _columns_of(other)
    elif case == "samples-dropped":  # as a tool that cut the messages' time range might
        samples = lambda p: p[:-100]  # noqa: E731
    elif case == "last-seq-changed":
        samples = _last_seq_changed
    elif case == "a-value-changed":  # the last row's force, one bit: the ends are compared bit for bit
        columns = _edit_columns(_columns_of(demo), lambda a: a["force_N"].view(np.uint64).__setitem__(-1, a[
            "force_N"].view(np.uint64)[-1] ^ 1))
    elif case == "header-says-other-ends":
        columns = _edit_columns(_columns_of(demo), lambda a: _with_header(a, last_seq=10 ** 9))
    elif case == "damaged":  # a byte of the compressed attachment flipped
        data = bytearray(_columns_of(demo))
        data[len(data) // 2] ^= 0x40
        columns = bytes(data)
    elif case == "not-zstd":
        import zstandard

        columns = zstandard.ZstdDecompressor().decompress(_columns_of(demo))
    path = _rewrite(demo, tmp_path / f"{case}.mcap", columns=columns, samples=samples,
                    crcs=case != "no-chunk-crcs")  # then nothing says the messages are as written
    log = assert_reads_as_per_message(path, columns=case == "kept")
    assert log.complete and not log.read_error


def _sample_dict(seq: int, **changes) -> dict:
    return json.loads(_sample(seq, **changes))


def test_odd_values_round_trip_through_the_columns(tmp_path):
    """Values the rig may log (NaN, infinities, -0.0, integers, 17 digits) come back through the
    columns bit for bit as through the messages."""
    from rig.recording.recorder import Recorder

    rec = Recorder(tmp_path / "odd.mcap", compression="none")
    odd = [float("nan"), float("inf"), -float("inf"), -0.0, 0.1 + 0.2, 1e308, 5e-324, 2 ** 53 + 1, -7]
    for i in range(300):
        rec.put(SAMPLE_TOPIC, i, _sample_dict(i, force_N=odd[i % len(odd)], error_N=odd[(i + 3) % len(odd)],
                                              step=i // 100, step_kind=["tare", "ramp", "hold"][i // 100],
                                              contact=i % 2 == 0))
    assert rec.close({"outcome": "completed"})
    assert not rec.columns_skipped
    log = assert_reads_as_per_message(rec.path, columns=True)
    assert np.isnan(log.samples["force_N"][0]) and np.signbit(log.samples["force_N"][3])


@pytest.mark.parametrize("case", ["a-string", "a-missing-field", "build-fails"])
def test_a_log_without_its_columns_is_finished_all_the_same(tmp_path, monkeypatch, case):
    """Samples the columns cannot hold exactly as the reader would (a number logged as a string, a
    field missing), or building them failing at the end: the log is finished without them, says
    why on the recorder, and reads from its messages."""
    from rig.recording.recorder import Recorder

    if case == "build-fails":
        def fail(self):
            raise MemoryError("no memory for the columns")

        monkeypatch.setattr(ColumnBuilder, "build", fail)
    rec = Recorder(tmp_path / f"{case}.mcap")
    for i in range(300):
        changes = {}
        if i == 150 and case == "a-string":
            changes = {"force_N": "1.5"}
        elif i == 150 and case == "a-missing-field":
            changes = {"late_ms": ...}
        rec.put(SAMPLE_TOPIC, i, _sample_dict(i, **changes))
    assert rec.close({"outcome": "completed"}) and rec.failure is None
    assert rec.columns_skipped == {"a-string": "sample 150: a field is not a plain number",
                                   "a-missing-field": "sample 150: KeyError: 'late_ms'",
                                   "build-fails": "MemoryError: no memory for the columns"}[case]
    log = assert_reads_as_per_message(rec.path, columns=False)
    assert log.complete and log.n == 300 and log.outcome == "completed"
    assert ATTACHMENT_NAME not in log.attachments


def test_too_many_samples_for_the_columns(tmp_path):
    from rig.recording.recorder import Recorder

    rec = Recorder(tmp_path / "long.mcap", columns_limit=100)
    for i in range(300):
        rec.put(SAMPLE_TOPIC, i, _sample_dict(i))
    assert rec.close({"outcome": "completed"})
    assert rec.columns_skipped == "over 100 samples"
    assert_reads_as_per_message(rec.path, columns=False)


def test_an_io_error_writing_the_columns_is_the_recordings_failure(tmp_path, monkeypatch):
    """Writing the columns fails as any write may (disk full): the recording has failed, and says
    so, and the log holds every message and the outcome, read as a log cut short."""
    from mcap.writer import Writer

    from rig.recording.recorder import Recorder

    def full(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Writer, "add_attachment", full)
    rec = Recorder(tmp_path / "full.mcap")
    for i in range(300):
        rec.put(SAMPLE_TOPIC, i, _sample_dict(i))
    assert not rec.close({"outcome": "completed"})
    assert rec.failure == "recording failed: No space left on device (errno 28)"
    log = assert_reads_as_per_message(rec.path, columns=False)
    assert log.n == 300 and not log.complete and log.outcome == "completed"

"""Logs left unfinished by a crash: find them, make them readable in full, list all trials.

A crashed writer leaves an MCAP file without summary or footer. `recover` copies every
record that can still be read into a new, finished file with an `outcome` record
marked `interrupted`, checks the copy, and only then replaces the original.

A log without a footer may also be one a live process is writing right now (a trial of
another daemon or of `rig run` in the same folder): its recorder holds an flock on it, and
such a file is never touched here.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from rig.errors import RigError
from rig.recording.logs import read_log
from rig.recording.messages import SCHEMAS
from rig.recording.recorder import is_being_written


@dataclass
class TrialEntry:
    path: Path
    start_time: str
    specimen: str
    protocol: str
    duration_s: float | None
    outcome: str
    recovered: bool
    requested_by: str = ""

    def as_dict(self) -> dict:
        return {"path": str(self.path), "start_time": self.start_time, "specimen": self.specimen,
                "protocol": self.protocol, "duration_s": self.duration_s, "outcome": self.outcome,
                "recovered": self.recovered, "requested_by": self.requested_by}


def is_finished(path: Path) -> bool:
    """True when the file ends with the MCAP footer and magic (the writer finished it)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            if size < 8 + 29:
                return False
            fh.seek(size - 8)
            return fh.read(8) == b"\x89MCAP0\r\n"
    except OSError:
        return False


def find_unfinished(out_dir: str | Path, *, in_use: list[Path] | None = None) -> list[Path]:
    """Logs left unfinished by a writer that is gone. Those a live process is still writing
    are left out (and appended to `in_use` when given, so the caller can say so)."""
    out = Path(out_dir)
    if not out.is_dir():
        return []
    found = []
    for p in sorted(out.glob("*.mcap")):
        if is_finished(p):
            continue
        if is_being_written(p):
            if in_use is not None:
                in_use.append(p)
            continue
        found.append(p)
    return found


class LogInUse(RigError):
    """The log is being written by a live process: recovery leaves it alone."""


def recover(path: str | Path) -> Path:
    """Rewrite an unfinished log as a finished one; the original stays until the copy verifies.
    `LogInUse` if a live process is writing it (its lock is held); the file is not touched."""
    path = Path(path)
    with _recovering(path):
        return _recover(path)


@contextlib.contextmanager
def _recovering(path: Path):
    """The log's lock for the whole rewrite: a live writer, or a second recovery, keeps it out."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError as exc:
        raise RigError(f"{path}: cannot open: {exc.strerror}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise LogInUse(f"{path} is being written by a live process: left as it is") from None
        yield
    finally:
        os.close(fd)


def _recover(path: Path) -> Path:
    log = read_log(path, keep_raw=True)
    tmp = path.with_suffix(".mcap.recovering")
    with open(tmp, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile="", library="indentation-rig/recovery")
        for name, data in log.metadata.items():
            if name != "outcome":
                w.add_metadata(name, data)
        for name, data in log.attachments.items():
            w.add_attachment(0, 0, name, "application/yaml", data)
        channels = {}
        for topic, schema in SCHEMAS.items():
            stored = log.schemas.get(topic, schema)
            sid = w.register_schema(stored.get("title", schema["title"]), "jsonschema",
                                    json.dumps(stored).encode())
            channels[topic] = w.register_channel(topic, "json", sid)
        start_ns = _start_ns(log.trial.get("start_time", ""))
        n = 0
        for topic, rows in log.raw_messages.items():
            for row in rows:
                stamp = start_ns + int(float(row.get("t_s", 0.0)) * 1e9)
                w.add_message(channels[topic], log_time=stamp, publish_time=stamp, sequence=n,
                              data=json.dumps(row, separators=(",", ":")).encode())
                n += 1
        duration = float(log.samples["t_s"][-1]) if log.n else 0.0
        w.add_metadata("outcome", {
            "outcome": "interrupted", "samples": str(log.n), "duration_s": f"{duration:.3f}",
            "recovered": "true", "recovered_at": datetime.now(UTC).isoformat(),
            "read_error": log.read_error or "no footer"})
        w.finish()
        fh.flush()
        os.fsync(fh.fileno())
    check = read_log(tmp)
    if not check.complete or check.n != log.n:
        tmp.unlink(missing_ok=True)
        raise RigError(f"{path}: recovered copy did not verify ({check.n} of {log.n} samples); "
                       "original left as it was")
    os.replace(tmp, path)
    return path


def _start_ns(text: str) -> int:
    try:
        return int(datetime.fromisoformat(text).timestamp() * 1e9)
    except ValueError:
        return 0


def list_trials(out_dir: str | Path) -> list[TrialEntry]:
    """Every log in `out_dir`, newest first, from metadata (finished files are not scanned)."""
    out = Path(out_dir)
    entries = []
    for path in out.glob("*.mcap") if out.is_dir() else []:
        meta = _metadata(path)
        trial, outcome = meta.get("trial", {}), meta.get("outcome")
        duration = float(outcome["duration_s"]) if outcome and outcome.get("duration_s") else None
        entries.append(TrialEntry(
            path=path, start_time=trial.get("start_time", ""), specimen=trial.get("specimen", ""),
            protocol=trial.get("protocol_name", ""), duration_s=duration,
            outcome=outcome.get("outcome", "?") if outcome else
            "running" if is_being_written(path) else "interrupted",
            recovered=bool(outcome and outcome.get("recovered") == "true"),
            requested_by=trial.get("requested_by", "")))
    entries.sort(key=lambda e: (e.start_time, str(e.path)), reverse=True)
    return entries


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    if is_finished(path):
        try:
            with open(path, "rb") as fh:
                return {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}
        except Exception:  # noqa: BLE001 - fall back to a full scan of a damaged file
            pass
    try:
        return read_log(path).metadata
    except RigError:
        return {}

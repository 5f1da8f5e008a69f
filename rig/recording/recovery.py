"""Logs left unfinished by a crash: find them, make them readable in full, list all trials;
and campaigns left without an end: end their journals.

A log folder holds the trials' logs and, one level down, a folder per campaign
(`characterize-SPECIMEN/`: its trials' logs and its journal). Listing, finding and recovering
look at both; a folder that is a symlink is not followed (recovery rewrites what it finds, and
the folders it rewrites are the log folder's own).

A crashed writer leaves an MCAP file without summary or footer. `recover` copies every
record that can still be read into a new, finished file with an `outcome` record
marked `interrupted`, checks the copy, and only then replaces the original.

A log without a footer may also be one a live process is writing right now (a trial of
another daemon or of `rig run` in the same folder): its recorder holds an flock on it, and
such a file is never touched here.

A campaign's journal (JSON lines, `rig.service.characterize`) ends with an `end` event. One
without it was left by a process that died mid-campaign: `end_journal` appends an `end` whose
status is `interrupted`, saying how far the campaign got. A journal is left alone while a live
process holds a lock on it or writes a log in its folder (a campaign still under way).
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
    """A log as `rig logs` lists it: its path, start time, specimen, protocol, duration and how it ended."""

    path: Path
    start_time: str
    specimen: str
    protocol: str
    duration_s: float | None
    outcome: str
    recovered: bool
    requested_by: str = ""
    campaign: str = ""  # the campaign's folder (characterize-SPECIMEN) for a campaign's trial

    def as_dict(self) -> dict:
        return {"path": str(self.path), "start_time": self.start_time, "specimen": self.specimen,
                "protocol": self.protocol, "duration_s": self.duration_s, "outcome": self.outcome,
                "recovered": self.recovered, "requested_by": self.requested_by, "campaign": self.campaign}


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


CAMPAIGN_FOLDERS = "characterize-*"  # a campaign's logs and journal, inside the log folder
JOURNALS = "characterize-*.jsonl"


def log_folders(out_dir: str | Path) -> list[Path]:
    """The log folder and its campaigns' folders (real directories only, not symlinks)."""
    out = Path(out_dir)
    if not out.is_dir():
        return []
    return [out, *sorted(p for p in out.glob(CAMPAIGN_FOLDERS) if p.is_dir() and not p.is_symlink())]


def log_files(out_dir: str | Path) -> list[Path]:
    """Every trial log in the log folder and its campaigns' folders."""
    return [p for folder in log_folders(out_dir) for p in sorted(folder.glob("*.mcap"))]


def find_unfinished(out_dir: str | Path, *, in_use: list[Path] | None = None) -> list[Path]:
    """Logs left unfinished by a writer that is gone, in the log folder and its campaigns'
    folders. Those a live process is still writing are left out (and appended to `in_use`
    when given, so the caller can say so)."""
    found = []
    for p in log_files(out_dir):
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
    """Every log in `out_dir` and its campaigns' folders, newest first, from metadata (finished
    files are not scanned)."""
    out = Path(out_dir)
    entries = []
    for path in log_files(out):
        meta = _metadata(path)
        trial, outcome = meta.get("trial", {}), meta.get("outcome")
        duration = float(outcome["duration_s"]) if outcome and outcome.get("duration_s") else None
        entries.append(TrialEntry(
            path=path, start_time=trial.get("start_time", ""), specimen=trial.get("specimen", ""),
            protocol=trial.get("protocol_name", ""), duration_s=duration,
            outcome=outcome.get("outcome", "?") if outcome else
            "running" if is_being_written(path) else "interrupted",
            recovered=bool(outcome and outcome.get("recovered") == "true"),
            requested_by=trial.get("requested_by", ""),
            campaign=path.parent.name if path.parent != out else ""))
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


# ---------------------------------------------------------------- campaigns' journals
@dataclass
class EndedCampaign:
    """A campaign journal found without an end, and the end written for it."""

    journal: Path
    specimen: str
    started_t: float | None  # time.time() of its start event
    trials: int  # trials begun
    reason: str


def find_open_journals(out_dir: str | Path, *, in_use: list[Path] | None = None) -> list[Path]:
    """Campaign journals in the log folder's campaign folders whose last event is not `end`.
    A journal that a live process holds locked, or whose folder holds a log being written (the
    campaign is under way in another process), is left out (and appended to `in_use`)."""
    found = []
    for folder in log_folders(out_dir)[1:]:
        for path in sorted(folder.glob(JOURNALS)):
            if path.is_symlink() or not path.is_file() or _journal_ended(path):
                continue
            if is_being_written(path) or any(is_being_written(p) for p in folder.glob("*.mcap")):
                if in_use is not None:
                    in_use.append(path)
                continue
            found.append(path)
    return found


def _events(path: Path) -> list[dict]:
    """The journal's events; a line cut short by the crash (or otherwise unreadable) is skipped."""
    events = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            with contextlib.suppress(ValueError):
                event = json.loads(line)
                if isinstance(event, dict):
                    events.append(event)
    return events


def _journal_ended(path: Path) -> bool:
    events = _events(path)
    return bool(events) and events[-1].get("event") == "end"


def end_journal(path: str | Path) -> EndedCampaign:
    """Append an `end` event with status `interrupted` to a journal left without one, saying how
    far the campaign got (the trials begun, and whether one was under way). The journal's own
    lock is held while it is written, so two recoveries cannot both end it."""
    path = Path(path)
    with _recovering(path):
        events = _events(path)
        if events and events[-1].get("event") == "end":
            raise RigError(f"{path}: the campaign's journal already has an end")
        start = next((e for e in events if e.get("event") == "start"), {})
        begun = {e.get("n"): e for e in events if e.get("event") == "trial"}
        ran = {e.get("n"): e for e in events if e.get("event") == "ran"}
        running = [n for n in begun if n not in ran]
        if running:
            where = f"during trial {running[-1]} (its log, if it was opened, is recovered as interrupted)"
        elif begun:
            where = f"after trial {max(ran, key=lambda n: n or 0)}, between trials"
        else:
            where = "before its first trial"
        reason = (f"interrupted: the process running the campaign stopped without ending it (killed, a "
                  f"crash or a power loss) {where}; {len(begun)} trial{'s' if len(begun) != 1 else ''} begun")
        specimen = str(start.get("specimen", ""))
        trials = [{"n": n, "protocol": e.get("protocol"), "why": e.get("why"),
                   "outcome": ran[n].get("outcome") if n in ran else "interrupted",
                   "log": ran[n].get("log") if n in ran else None} for n, e in begun.items()]
        now = datetime.now(UTC)
        end = {"t": now.timestamp(), "event": "end", "status": "interrupted", "reason": reason,
               "recovered": True, "recovered_at": now.isoformat(),
               "summary": {"specimen": specimen, "status": "interrupted", "reason": reason,
                           "journal": str(path), "trials": trials}}
        with open(path, "rb+") as fh:
            fh.seek(0, os.SEEK_END)
            if fh.tell():  # a line the crash cut short stays a line of its own
                fh.seek(-1, os.SEEK_END)
                cut = fh.read(1) != b"\n"
            else:
                cut = False
            fh.write((("\n" if cut else "") + json.dumps(end) + "\n").encode())
            fh.flush()
            os.fsync(fh.fileno())
    started = start.get("t")
    return EndedCampaign(path, specimen, float(started) if isinstance(started, int | float) else None,
                         len(begun), reason)

"""MCAP recording: JSON channels with jsonschema schemas, written by a thread of its own.

The loop only puts small dicts on a queue; encoding, compression and disk I/O happen
on the writer thread. Every `flush_s` the writer finishes the open chunk, flushes and
fsyncs, so a crash loses at most about one second. Metadata and attachments are
written at once, outside chunks, so even a log cut short names its trial.

When the log is finished, the sample columns are attached in binary as well (`columns.py`), so
replay need not decode every message's JSON; a log without them (cut short, older, or one whose
columns could not be built) reads the same from its messages.

A recording that fails (disk full, an I/O error, a writer that falls `max_queue`
messages behind) is never silent: `failure` says what happened, the loop reads it every
tick and ends the trial as a fault, and what was flushed before stays readable.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mcap.writer import CompressionType, Writer

from rig import __version__
from rig.recording.columns import ATTACHMENT_NAME, MEDIA_TYPE, ColumnBuilder
from rig.recording.messages import SAMPLE_TOPIC, SCHEMAS

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
_STOP = object()


@dataclass
class TrialInfo:
    """What the log's header records about a trial beyond its protocol and config: the specimen, the
    operator, the clock, free notes and any further key-value pairs."""

    specimen: str = ""
    operator: str = ""
    clock: str = "real"
    notes: str = ""
    extra: dict[str, str] = field(default_factory=dict)


def open_new_log(path: str | Path, attempts: int = 1000) -> tuple[BinaryIO, Path]:
    """A new log file at `path`, or at `<stem>_2`, `<stem>_3`... if that name is taken, and the
    name used. Opened exclusively (O_EXCL): two runs starting in the same second never share
    a file. Held with an flock until closed, so recovery leaves a log being written alone.
    """
    path = Path(path)
    for n in range(1, attempts + 1):
        candidate = path if n == 1 else path.with_name(f"{path.stem}_{n}{path.suffix}")
        try:
            fh = open(candidate, "xb")  # noqa: SIM115 - the recorder's writer thread closes it
        except FileExistsError:
            continue
        # A file system without flock: the log is still ours alone (O_EXCL).
        with contextlib.suppress(OSError):
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        return fh, candidate
    raise FileExistsError(f"{path}: no free name among {attempts} tried")


def is_being_written(path: str | Path) -> bool:
    """True while a live recorder holds `path` (its flock); a crashed writer's lock is gone."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)
    return False


class Recorder:
    """Owns one MCAP file. `put` is the only call the loop makes per tick.

    `path` is the name wanted; `self.path` the name used (see `open_new_log`)."""

    def __init__(self, path: str | Path, *, flush_s: float = 1.0, compression: str = "zstd",
                 max_queue: int = 20000, columns_limit: int = 2_000_000) -> None:
        self.path = Path(path)
        self.flush_s = flush_s
        self.max_queue = max_queue
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self.overflowed = False
        self.flushed_messages = 0  # messages known to be on disk (fsynced)
        self._file, self.path = open_new_log(self.path)
        self._writer = Writer(self._file, chunk_size=256 * 1024, compression=_COMPRESSION[compression])
        self._writer.start(profile="", library=f"indentation-rig/{__version__}")
        self._channels: dict[str, int] = {}
        for topic, schema in SCHEMAS.items():
            sid = self._writer.register_schema(schema["title"], "jsonschema",
                                               json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic, "json", sid)
        self.messages = 0
        self.flushes = 0
        self.error: BaseException | None = None
        self._closed = False
        self.unfinished = ""  # why close() returned before the log was finished
        self._busy = False
        self._columns = ColumnBuilder(columns_limit)
        # why the log was finished without its sample columns ("" when they are attached): not a
        # failure of the recording, whose messages are all there; the reader decodes them instead
        self.columns_skipped = ""
        self.thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self.thread.start()

    # ---------------------------------------------------------------- loop side
    def put(self, topic: str, log_time_ns: int, message: dict[str, Any]) -> None:
        if self.error is not None or self._q.qsize() >= self.max_queue:
            # The writer is dead or cannot keep up: holding more would only eat memory.
            self.overflowed = self.overflowed or self.error is None
            return
        self._q.put((topic, log_time_ns, message))

    def depth(self) -> int:
        return self._q.qsize()

    @property
    def failure(self) -> str | None:
        """What went wrong with this recording, or None while it is healthy."""
        if self.error is not None:
            return f"recording failed: {_describe(self.error)}"
        if self.overflowed:
            return (f"recording cannot keep up: over {self.max_queue} messages waiting for the writer "
                    "(disk too slow or blocked)")
        return None

    def wait_idle(self, timeout_s: float = 2.0) -> bool:
        """Block until the writer has taken everything queued so far (not for the loop)."""
        deadline = time.monotonic() + timeout_s
        while (not self._q.empty() or self._busy) and self.error is None:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.001)
        return True

    # --------------------------------------------------- written immediately
    def write_metadata(self, name: str, data: dict[str, str]) -> None:
        self._q.put(("__metadata__", name, {k: str(v) for k, v in data.items()}))

    def attach(self, name: str, media_type: str, data: bytes, log_time_ns: int) -> None:
        self._q.put(("__attachment__", (name, media_type, log_time_ns), data))

    def close(self, outcome: dict[str, str] | None = None, timeout_s: float = 30.0) -> bool:
        """Write the outcome, finish the file (summary, footer) and fsync. Safe to call twice.

        False when the log is not finished: the writer failed, or is still writing after
        `timeout_s` (then `unfinished` says so and the log stays locked until it is done)."""
        if not self._closed:
            self._closed = True
            if outcome is not None:
                self.write_metadata("outcome", outcome)
            self._q.put(_STOP)
            self.thread.join(timeout_s if self.error is None else 1.0)
            if self.thread.is_alive():
                self.unfinished = (f"the log was not finished within {timeout_s:g} s (the disk is slow or "
                                   f"blocked; {self.depth()} messages still queued): {self.path} may end "
                                   "without its outcome")
        return self.error is None and not self.unfinished

    # --------------------------------------------------------------- writer
    def _run(self) -> None:
        last_flush = time.monotonic()
        dirty = False
        try:
            while True:
                try:
                    item = self._q.get(timeout=min(self.flush_s, 0.2))
                except queue.Empty:
                    item = None
                if item is _STOP:
                    break
                if item is not None:
                    self._busy = True
                    dirty |= self._write(item)
                    self._busy = False
                if dirty and time.monotonic() - last_flush >= self.flush_s:
                    self._sync()
                    dirty = False
                    last_flush = time.monotonic()
            while True:  # drain anything queued after the stop marker
                try:
                    item = self._q.get_nowait()
                except queue.Empty:
                    break
                if item is not _STOP:
                    self._write(item)
            self._attach_columns()
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self.flushed_messages = self.messages
        except BaseException as exc:  # noqa: BLE001 - disk full, I/O error: keep what is on disk, report it
            self.error = exc
        finally:
            with contextlib.suppress(OSError):  # closing flushes; the disk may still be full
                self._file.close()

    def _write(self, item: tuple) -> bool:
        topic, stamp, payload = item
        if topic == "__metadata__":
            self._writer.add_metadata(stamp, payload)
            self._sync()
            return False
        if topic == "__attachment__":
            name, media_type, log_time_ns = stamp
            self._writer.add_attachment(log_time_ns, log_time_ns, name, media_type, payload)
            self._sync()
            return False
        data = json.dumps(payload, separators=(",", ":")).encode()
        self._writer.add_message(self._channels[topic], log_time=stamp, publish_time=stamp,
                                 data=data, sequence=self.messages & 0xFFFFFFFF)
        self.messages += 1
        if topic == SAMPLE_TOPIC:
            self._columns.add(data)
        return True

    def _attach_columns(self) -> None:
        """The sample columns as an attachment, after the last message and before the summary.

        Building them only reads memory: if that fails, nothing has been written and the log is
        finished without them. Writing them can fail only as any write can (disk full, an I/O
        error): that is the recording's failure, reported as such, with every message and the
        outcome already on disk."""
        try:
            data = self._columns.build()
        except Exception as exc:  # noqa: BLE001 - MemoryError included: the log matters, not the shortcut
            data = None
            self._columns.broken = f"{type(exc).__name__}: {exc}"
        if data is None:
            self.columns_skipped = self._columns.broken
            return
        self._columns = ColumnBuilder(0)  # the memory they held is not needed any more
        # the open chunk first, so the attachment follows every message it holds
        self._writer.flush()
        now = time.time_ns()
        self._writer.add_attachment(now, now, ATTACHMENT_NAME, MEDIA_TYPE, data)

    def _sync(self) -> None:
        self._writer.flush()
        self._file.flush()
        os.fsync(self._file.fileno())
        self.flushes += 1
        self.flushed_messages = self.messages


def _describe(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror} (errno {exc.errno})"
    return f"{type(exc).__name__}: {exc}"

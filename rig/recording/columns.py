"""The sample columns in binary, attached to a finished log: replay without decoding JSON.

Decoding a /rig/sample message costs about 3 us in CPython's json.loads, which caps reading a
log near 300k samples/s. So the recorder, which writes those messages, also keeps the columns
the reader would build from them and, when it finishes the log, writes them as one MCAP
attachment (`ATTACHMENT_NAME`: a numpy `.npz` of one float64 array per numeric column as
`read_log` returns it, `contact` as bool, `step_kind` as codes into the header's list, and a
`header` (JSON) with the sample count and the first and last seq; compressed whole by zstd with
its checksum, as MCAP attachments are stored as given: about 26 bytes a sample instead of 99,
for 0.3 ms more per 6000 samples read, where zip's own deflate costs 1.1 ms). The messages stay
as they were: any MCAP reader sees the same log, plus one attachment.

The columns are built from the very bytes written (each sample's JSON decoded again on the
writer thread), converted exactly as `logs.sample_columns` converts them, so they are the
reader's columns bit for bit. A log whose samples the reader would not take on its fast path
(a missing field, a value that is not a plain number) gets no attachment: its reader decodes
the messages, as for a log from before this attachment existed or one cut short by a crash.
"""

from __future__ import annotations

import functools
import io
import json
import zipfile
from operator import itemgetter
from typing import Any

import numpy as np
import zstandard

from rig.recording.messages import SAMPLE

_MISSING = object()

ATTACHMENT_NAME = "rig/sample-columns.npz.zst"
MEDIA_TYPE = "application/zstd"  # of an .npz (application/x-npz): `zstd -d`, then np.load
FORMAT = "rig.sample-columns"
VERSION = 1
HEADER = "header"  # the npz member holding the JSON header
CONTACT, STEP_KIND = "contact", "step_kind"
# Rows converted to an array at a time: a list of tuples costs ~10x the array's memory, and the
# conversion holds the GIL beside the 100 Hz loop (4096 rows: ~1 ms; 256: ~0.07 ms).
_BLOCK = 256


class ColumnBuilder:
    """The sample columns of a log being written, fed one encoded message at a time.

    `broken` says why no attachment will be written (then `add` does nothing more)."""

    def __init__(self, limit: int = 2_000_000) -> None:
        self.limit = limit  # samples kept at most: 128 bytes each in memory until the log is finished
        self.names: list[str] | None = None
        self.n = 0
        self.broken = ""
        self._blocks: list[np.ndarray] = []
        self._rows: list[tuple] = []
        self._contact: list[bool] = []
        self._kinds: list[int] = []
        self._kind_codes: dict[str, int] = {}
        self._get: Any = None
        # a force step's setpoint and error, on its own ticks only: NaN on the others, as the reader
        self._sparse: dict[str, list[float]] = {name: [] for name in SAMPLE.sparse_numeric}
        self._sparse_seen: set[str] = set()

    def add(self, data: bytes) -> None:
        if self.broken:
            return
        try:
            self._add(json.loads(data))
        except Exception as exc:  # noqa: BLE001 - the log is written all the same; only the shortcut is lost
            self._break(f"sample {self.n}: {type(exc).__name__}: {exc}")

    def _add(self, row: dict) -> None:
        if self.n >= self.limit:
            self._break(f"over {self.limit} samples")
            return
        if self.names is None:
            # the reader's columns: every required number, and the optional ones the first sample has
            self.names = [*SAMPLE.numeric, *(n for n in SAMPLE.optional_numeric if n in row)]
            self._get = itemgetter(*self.names)
        values = self._get(row)
        # Only plain numbers: the reader converts them with the same np.array call, so both give
        # the same bits. Anything else (a string, None, a list) the reader takes its own way.
        if not all(type(v) is float or type(v) is int for v in values):
            self._break(f"sample {self.n}: a field is not a plain number")
            return
        contact, kind = row[CONTACT], row[STEP_KIND]
        if type(contact) is not bool or type(kind) is not str:
            self._break(f"sample {self.n}: contact or step_kind of an unexpected type")
            return
        for name, col in self._sparse.items():
            v = row.get(name, _MISSING)
            if v is _MISSING:
                col.append(np.nan)
            elif type(v) is float or type(v) is int:
                col.append(float(v))
                self._sparse_seen.add(name)
            else:
                self._break(f"sample {self.n}: {name} is not a plain number")
                return
        self._rows.append(values)
        self._contact.append(contact)
        code = self._kind_codes.get(kind)
        if code is None:
            code = self._kind_codes[kind] = len(self._kind_codes)
        self._kinds.append(code)
        self.n += 1
        if len(self._rows) >= _BLOCK:
            self._flush_rows()

    def _flush_rows(self) -> None:
        if self._rows:
            block = np.array(self._rows, dtype=float)
            if block.shape != (len(self._rows), len(self.names or ())):
                raise ValueError(f"rows of shape {block.shape}")
            self._blocks.append(block)
            self._rows = []

    def _break(self, why: str) -> None:
        self.broken = why
        self._blocks, self._rows, self._contact, self._kinds = [], [], [], []
        self._sparse = {name: [] for name in SAMPLE.sparse_numeric}

    def build(self) -> bytes | None:
        """The attachment's bytes, or None when there is none to write (see `broken`)."""
        if self.broken or not self.n:
            self.broken = self.broken or "no samples"
            return None
        self._flush_rows()
        table = np.concatenate(self._blocks)
        names = self.names or []
        arrays = {name: np.ascontiguousarray(table[:, j]) for j, name in enumerate(names)}
        for name in SAMPLE.sparse_numeric:
            if name in self._sparse_seen:
                arrays[name] = np.array(self._sparse[name], dtype=float)
                names = [*names, name]
        seq = arrays["seq"]
        header = {"format": FORMAT, "version": VERSION, "samples": self.n, "columns": names,
                  "first_seq": _seq_value(seq[0]), "last_seq": _seq_value(seq[-1]),
                  "step_kinds": list(self._kind_codes)}
        arrays[CONTACT] = np.array(self._contact, dtype=bool)
        arrays[STEP_KIND] = np.array(self._kinds, dtype=np.min_scalar_type(max(len(self._kind_codes) - 1, 0)))
        arrays[HEADER] = np.array(json.dumps(header))
        out = io.BytesIO()
        np.savez(out, **arrays)
        return zstandard.ZstdCompressor(level=3, write_checksum=True).compress(out.getvalue())


def _seq_value(value: float) -> int | float:
    return int(value) if float(value).is_integer() else float(value)


class Columns:
    """An attachment read back: the reader's columns, step kinds and contact flags."""

    def __init__(self, header: dict, samples: dict[str, np.ndarray], step_kind: list[str],
                 contact: np.ndarray) -> None:
        self.header = header
        self.samples = samples
        self.step_kind = step_kind
        self.contact = contact

    @property
    def n(self) -> int:
        return int(self.header["samples"])


def read_columns(data: bytes) -> Columns | None:
    """The columns of an attachment, or None when it is not one this reader knows all of. zstd
    checks its checksum, zipfile each member's CRC-32: a damaged attachment is not taken."""
    try:
        arrays = _load_npz(zstandard.ZstdDecompressor().decompress(data))
        header = json.loads(str(arrays[HEADER][()]))
        if header.get("format") != FORMAT or header.get("version") != VERSION:
            return None
        n, names, kinds = int(header["samples"]), list(header["columns"]), list(header["step_kinds"])
        samples = {name: arrays[name] for name in names}
        contact, codes = arrays[CONTACT], arrays[STEP_KIND]
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, EOFError, zstandard.ZstdError):
        return None
    if not all(a.dtype == np.float64 and a.shape == (n,) for a in samples.values()):
        return None
    if contact.dtype != bool or contact.shape != (n,) or codes.shape != (n,) or codes.dtype.kind != "u":
        return None
    if (n and int(codes.max()) >= len(kinds)) or not all(type(k) is str for k in kinds):
        return None
    table = np.array(kinds, dtype=object)
    return Columns(header, samples, table[codes].tolist(), contact)


def _load_npz(data: bytes) -> dict[str, np.ndarray]:
    """`np.load` of an npz, every member read at once. np.load parses every member's header with
    ast.literal_eval (about 60 us each, half the time of reading the attachment); here a header
    seen before is not parsed again."""
    out = {}
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for info in zf.infolist():
            raw = zf.read(info)  # checks the member's CRC-32
            array = _npy(raw)
            if array is None:  # not a form this shortcut knows: numpy's own reading
                with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                    return {name: npz[name] for name in npz.files}
            out[info.filename.removesuffix(".npy")] = array
    return out


def _npy(raw: bytes) -> np.ndarray | None:
    """A .npy file's array (format 1.0, no objects), or None."""
    if raw[:8] != b"\x93NUMPY\x01\x00":
        return None
    end = 10 + int.from_bytes(raw[8:10], "little")
    dtype, shape = _npy_header(raw[:end])
    if dtype is None or dtype.hasobject:
        return None
    count = int(np.prod(shape)) if shape else 1
    if end + count * dtype.itemsize != len(raw):
        return None
    return np.frombuffer(raw, dtype, count, end).reshape(shape).copy()


@functools.lru_cache(maxsize=64)
def _npy_header(head: bytes) -> tuple[np.dtype | None, tuple[int, ...]]:
    shape, fortran, dtype = np.lib.format.read_array_header_1_0(io.BytesIO(head[8:]))
    if fortran and len(shape) > 1:
        return None, ()
    return dtype, shape

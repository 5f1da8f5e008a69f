"""Reading MCAP logs in file order, fast: message indexes read past, chunks split in one pass.

`LogStreamReader` is the library's `StreamReader(emit_chunks=True)`, except for message index
records: the library decodes them into a tuple per indexed message, two stream reads each, which
cost as much as all the rest of the scan, and a reader in file order never uses them. They are
yielded without their entries. Where one is not all there (a file cut inside it), the library's
own parser reads the bytes there are, so reading stops with the error it always gave; one whose
entries overrun its own length (a damaged file: the library would read on into the records after
it) ends reading there.

`mcap.stream_reader.breakup_chunk` builds a `Message` through five stream reads for every
message, which costs more than decoding its JSON. Here the chunk, decompressed by the library
(`chunk_bytes`), is walked once with `struct.unpack_from`, and a message becomes only its channel
id and a slice of its payload. Schema and channel records, a few per log, are still parsed by
the library's own record classes.

Only what is certain is split: a record that does not fit its chunk, a message shorter than
its fixed fields, or a schema or channel record whose fields do not fill it exactly makes
`split_chunk` return None, and the caller hands the whole chunk to the library, which reads
such damage in its own way. The format (MCAP spec, "Records"): every record is an opcode
(uint8) and a length (uint64) followed by that many bytes; a message's are channel id
(uint16), sequence (uint32), log time and publish time (uint64 each), then its data.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from io import BytesIO
from typing import BinaryIO

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, McapRecord, MessageIndex, Schema
from mcap.stream_reader import StreamReader, get_chunk_data_stream

_HEAD = struct.Struct("<BQH")  # opcode, record length, and a message's channel id
_MESSAGE_FIXED = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time
_CHANNEL_ID = struct.Struct("<H")
_LENGTH = struct.Struct("<Q")
_INDEX_LENGTH = struct.Struct("<I")  # a message index: channel id (uint16), then this, its entries' bytes


class LogStreamReader(StreamReader):
    """`StreamReader(emit_chunks=True)` that yields message indexes without their entries."""

    def __init__(self, stream: BinaryIO, record_size_limit: int) -> None:
        super().__init__(stream, emit_chunks=True, record_size_limit=record_size_limit)

    # `_read_record` and `_stream` are the library's own (mcap 1.x); tests/test_logs.py checks
    # that this override is used and that every log reads as it does through the library alone.
    def _read_record(self, opcode: int, length: int) -> McapRecord | None:
        if opcode != Opcode.MESSAGE_INDEX:
            return super()._read_record(opcode, length)
        body = self._stream.read(length)
        if len(body) < length or not _index_fits(body):
            # the library's error for a record cut short; for one that overruns itself, an error here
            return MessageIndex.read(ReadDataStream(BytesIO(body)))
        return MessageIndex(_CHANNEL_ID.unpack_from(body)[0], [])  # a record was read, its entries not


def _index_fits(body: bytes) -> bool:
    """The library's parser of this message index stays inside it (entries of 16 bytes)."""
    if len(body) < 6:
        return False
    entries = _INDEX_LENGTH.unpack_from(body, 2)[0]
    return 6 + -(-entries // 16) * 16 <= len(body)


@dataclass
class SplitChunk:
    """A chunk's records in order: each item is a schema or channel record, or a run of messages
    between them as {channel id: [payload, ...]} (payloads in the order written)."""

    records: list[Schema | Channel | dict[int, list[bytes]]] = field(default_factory=list)
    count: int = 0  # records the library would yield for this chunk
    # messages of the channels `split_chunk` was asked only to count: how many, the first and last
    counted: int = 0
    first: bytes | None = None
    last: bytes | None = None


def chunk_bytes(chunk: Chunk, zstd: zstandard.ZstdDecompressor | None = None) -> bytes:
    """The chunk's records, decompressed once (by the library: zstd, lz4 or none).

    With `zstd`, a zstd chunk is decompressed by that decompressor, as the library does but
    without making a new one for every chunk (a third of the time it takes on a 1 s chunk)."""
    if zstd is not None and chunk.compression == "zstd":
        return zstd.decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    stream, size = get_chunk_data_stream(chunk)
    return stream.read(size)


def split_chunk(data: bytes, count_only: frozenset[int] = frozenset()) -> SplitChunk | None:
    """The records of a decompressed chunk, or None where the library must read it instead.

    Messages on the channels in `count_only` are counted (`counted`, `first`, `last`), not
    listed: slicing out every payload costs more than all the rest of the walk. Those channels
    are as the reader knew them before the chunk; a chunk that defines a channel or schema is
    split in full, so that no message is counted under a channel it redefines."""
    if len(count_only) == 1:
        return _split_counting(data, next(iter(count_only)))
    out = SplitChunk()
    counted = 0
    first_at = last_at = -1
    run: dict[int, list[bytes]] = {}
    end_of_data = len(data)
    pos = 0
    unpack = _HEAD.unpack_from
    message = Opcode.MESSAGE.value
    while pos < end_of_data:
        if pos + _HEAD.size > end_of_data:
            return None
        opcode, length, channel_id = unpack(data, pos)
        body = pos + 9
        pos = body + length
        if pos > end_of_data:
            return None
        if opcode == message:
            if length < _MESSAGE_FIXED:
                return None
            if channel_id in count_only:
                if first_at < 0:
                    first_at = body
                last_at = body
                counted += 1
                continue
            payloads = run.get(channel_id)
            if payloads is None:
                payloads = run[channel_id] = []
            payloads.append(data[body + _MESSAGE_FIXED:pos])
            out.count += 1
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            if count_only:
                return split_chunk(data)
            stream = ReadDataStream(BytesIO(data[body:pos]))
            rec = (Schema if opcode == Opcode.SCHEMA else Channel).read(stream)
            if stream.count != length:
                return None
            if run:
                out.records.append(run)
                run = {}
            out.records.append(rec)
            out.count += 1
        # any other record inside a chunk is skipped, as the library skips it
    return _closed(out, run, data, counted, first_at, last_at)


def _split_counting(data: bytes, channel: int) -> SplitChunk | None:
    """`split_chunk(data, {channel})`: the same walk, in a loop that does no more for a message
    on `channel` (nearly every record of the rig's chunks) than step over it; the other records'
    places are noted and read after, in order."""
    end_of_data = len(data)
    pos = counted = 0
    first_at = last_at = -1
    others = []
    unpack = _HEAD.unpack_from
    message = Opcode.MESSAGE.value
    try:
        while pos < end_of_data:
            opcode, length, channel_id = unpack(data, pos)
            if opcode == message and channel_id == channel and length >= _MESSAGE_FIXED:
                if first_at < 0:
                    first_at = pos + 9
                last_at = pos + 9
                counted += 1
            else:
                others.append(pos)
            pos += 9 + length
    except struct.error:  # fewer than a record's opcode, length and channel id left
        return None
    if pos != end_of_data:  # the last record overruns the chunk
        return None
    out = SplitChunk()
    run: dict[int, list[bytes]] = {}
    for pos in others:
        opcode, length, channel_id = unpack(data, pos)
        body = pos + 9
        if opcode == message:
            if length < _MESSAGE_FIXED:
                return None
            payloads = run.get(channel_id)
            if payloads is None:
                payloads = run[channel_id] = []
            payloads.append(data[body + _MESSAGE_FIXED:body + length])
            out.count += 1
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            return split_chunk(data)  # see split_chunk: nothing counted under a channel defined here
    return _closed(out, run, data, counted, first_at, last_at)


def _closed(out: SplitChunk, run: dict[int, list[bytes]], data: bytes, counted: int, first_at: int,
            last_at: int) -> SplitChunk:
    """`out` with its last run of payloads and what was counted: how many, the first and the last."""
    if run:
        out.records.append(run)
    if counted:
        out.counted, out.count = counted, out.count + counted
        out.first = _payload(data, first_at)
        out.last = _payload(data, last_at)
    return out


def _payload(data: bytes, body: int) -> bytes:
    length = _LENGTH.unpack_from(data, body - 8)[0]
    return data[body + _MESSAGE_FIXED:body + length]

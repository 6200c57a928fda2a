"""MCAP written a chunk at a time, where a chunk may be built in another process.

The recorder's writer thread builds chunks of covey's raw messages; the Foxglove worker
(recording/foxglove_worker.py) builds and compresses the chunks of the standard channels in a child
process and hands them over whole. `McapFile` writes both kinds into one file and keeps the one
summary (schemas, channels, statistics, chunk and metadata indexes) that Foxglove seeks with.
mcap.writer.Writer cannot take a chunk built elsewhere, and its per-message record building was
the larger part of the writer thread's cost; so the two per-message records (Message and
MessageIndex, https://mcap.dev/spec) are struct-packed here, and every other record is written by
the mcap library's own record classes. Tests read the files back with the mcap library's
streaming and indexed readers.

Every record is `opcode u8, length u64, body`; all integers little-endian.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import BinaryIO

import zstandard
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
MAX_ID = 0xFFFF
"""Schema and channel ids are u16 in MCAP."""
# Message body: channel_id u16, sequence u32, log_time u64, publish_time u64, then the data.
_MESSAGE = struct.Struct("<BQHIQQ")
_MESSAGE_BODY = 2 + 4 + 8 + 8
# Chunk body: start u64, end u64, uncompressed_size u64, uncompressed_crc u32, compression str
# (u32 length + utf-8), records u64 length + bytes.
_CHUNK_HEAD = struct.Struct("<BQQQQI")
_U32, _U64 = struct.Struct("<I"), struct.Struct("<Q")
_RECORD = struct.Struct("<BQ")
_MESSAGE_FIELDS = struct.Struct("<HIQQ")


@dataclass(frozen=True)
class BuiltChunk:
    """A finished Chunk record and the MessageIndex records that follow it in the file."""

    records: bytes = field(repr=False)
    """The Chunk record, then one MessageIndex record per channel in it."""
    chunk_length: int
    """Bytes of the Chunk record alone (opcode and length included)."""
    index_offsets: dict[int, int]
    """Channel id -> offset of its MessageIndex record within `records`."""
    start_ns: int
    end_ns: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    message_counts: dict[int, int]
    """Messages in the chunk, by channel id."""
    schemas: tuple[Schema, ...] = ()
    """Schemas first written in this chunk (the file's summary repeats them)."""
    channels: tuple[Channel, ...] = ()
    """Channels first written in this chunk."""
    plain: bytes = field(default=b"", repr=False)
    """The chunk's records uncompressed, when build() was asked for them (the Foxglove worker
    reads covey's messages from them); not written to the file."""

    @property
    def messages(self) -> int:
        return sum(self.message_counts.values())


class ChunkBuilder:
    """Collects records for one chunk at a time; `build()` compresses them and starts the next.

    Schemas and channels are written into the chunk where they are first added, so each chunk
    can be read on its own (a streaming reader meets a channel before its messages)."""

    def __init__(self, compression: str = "zstd") -> None:
        if compression not in ("zstd", ""):
            raise ValueError(f"compression {compression!r}: covey writes 'zstd' or '' (none)")
        self.compression = compression
        self._zstd = zstandard.ZstdCompressor() if compression == "zstd" else None
        self._reset()

    def _reset(self) -> None:
        self._parts: list[bytes] = []
        self.size = 0
        """Uncompressed bytes so far."""
        self._index: dict[int, list[int]] = {}  # channel id -> [log_time, offset, ...]
        self.messages = 0
        """Messages so far."""
        self._start_ns = 0
        self._end_ns = 0
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []

    def _record(self, rec: Schema | Channel) -> None:
        rb = RecordBuilder()
        rec.write(rb)
        data = rb.end()
        self._parts.append(data)
        self.size += len(data)

    def add_schema(self, schema: Schema) -> None:
        self._record(schema)
        self._schemas.append(schema)

    def add_channel(self, channel: Channel) -> None:
        self._record(channel)
        self._channels.append(channel)

    def add(
        self, channel_id: int, log_time_ns: int, data: bytes, publish_time_ns: int, seq: int = 0
    ) -> None:
        """One Message record. The channel must have been added to this file before."""
        index = self._index.get(channel_id)
        if index is None:
            index = self._index[channel_id] = []
        if self.messages == 0:
            self._start_ns = self._end_ns = log_time_ns
        elif log_time_ns < self._start_ns:
            self._start_ns = log_time_ns
        elif log_time_ns > self._end_ns:
            self._end_ns = log_time_ns
        self.messages += 1
        index.append(log_time_ns)
        index.append(self.size)
        self._parts.append(
            _MESSAGE.pack(
                Opcode.MESSAGE,
                _MESSAGE_BODY + len(data),
                channel_id,
                seq,
                log_time_ns,
                publish_time_ns,
            )
        )
        self._parts.append(data)
        self.size += 9 + _MESSAGE_BODY + len(data)

    def build(self, keep_plain: bool = False) -> BuiltChunk | None:
        """The chunk so far, compressed, or None when it holds no message (schemas and channels
        added meanwhile stay for the next chunk, as mcap's own writer keeps them)."""
        if self.messages == 0:
            return None
        data = b"".join(self._parts)
        body = self._zstd.compress(data) if self._zstd is not None else data
        comp = self.compression.encode()
        chunk_len = 8 + 8 + 8 + 4 + 4 + len(comp) + 8 + len(body)
        parts = [
            _CHUNK_HEAD.pack(
                Opcode.CHUNK,
                chunk_len,
                self._start_ns,
                self._end_ns,
                len(data),
                zlib.crc32(data),
            ),
            _U32.pack(len(comp)),
            comp,
            _U64.pack(len(body)),
            body,
        ]
        chunk_length = 9 + chunk_len
        offset, offsets, counts = chunk_length, {}, {}
        for cid, flat in self._index.items():
            # MessageIndex: channel_id u16, then (log_time u64, offset u64) pairs, u32-prefixed
            n = len(flat)
            rec = struct.pack(f"<BQHI{n}Q", Opcode.MESSAGE_INDEX, 2 + 4 + 8 * n, cid, 8 * n, *flat)
            parts.append(rec)
            offsets[cid] = offset
            counts[cid] = n // 2
            offset += len(rec)
        built = BuiltChunk(
            records=b"".join(parts),
            chunk_length=chunk_length,
            index_offsets=offsets,
            start_ns=self._start_ns,
            end_ns=self._end_ns,
            compression=self.compression,
            compressed_size=len(body),
            uncompressed_size=len(data),
            message_counts=counts,
            schemas=tuple(self._schemas),
            channels=tuple(self._channels),
            plain=data if keep_plain else b"",
        )
        self._reset()
        return built


class PlainReader:
    """covey's side of a chunk handed over uncompressed (BuiltChunk.plain): its messages as
    (topic, log_time_ns, data), in the order written. Remembers the channels met so far, so
    feed it every chunk of a stream in order."""

    def __init__(self) -> None:
        self.topics: dict[int, str] = {}

    def messages(self, plain: bytes) -> Iterator[tuple[str, int, bytes]]:
        pos, end = 0, len(plain)
        while pos < end:
            opcode, length = _RECORD.unpack_from(plain, pos)
            body = pos + 9
            pos = body + length
            if opcode == Opcode.MESSAGE:
                cid, _seq, log_time_ns, _pub = _MESSAGE_FIELDS.unpack_from(plain, body)
                yield self.topics[cid], log_time_ns, plain[body + _MESSAGE_BODY : pos]
            elif opcode == Opcode.CHANNEL:
                ch = Channel.read(ReadDataStream(io.BytesIO(plain[body:pos])))
                self.topics[ch.id] = ch.topic


class McapFile:
    """One MCAP file: header, metadata and chunks (from any ChunkBuilder), then at `finish()`
    the summary and footer. Not thread-safe: one thread writes it."""

    def __init__(self, out: BinaryIO, profile: str = "", library: str = "") -> None:
        self._out = out
        self._pos = 0
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = {}
        self._start_ns: int | None = None
        self._end_ns = 0
        self._write(MAGIC)
        self._write_record(Header(profile, library))

    def _write(self, data: bytes) -> None:
        self._out.write(data)
        self._pos += len(data)

    def _write_record(self, rec) -> int:
        rb = RecordBuilder()
        rec.write(rb)
        data = rb.end()
        self._write(data)
        return len(data)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._pos
        length = self._write_record(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def write_chunk(self, built: BuiltChunk) -> None:
        for s in built.schemas:
            if self._schemas.setdefault(s.id, s) != s:
                raise ValueError(f"schema id {s.id} is already {self._schemas[s.id].name}")
        for c in built.channels:
            if self._channels.setdefault(c.id, c) != c:
                raise ValueError(f"channel id {c.id} is already {self._channels[c.id].topic}")
        start = self._pos
        self._write(built.records)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=built.start_ns,
                message_end_time=built.end_ns,
                chunk_start_offset=start,
                chunk_length=built.chunk_length,
                message_index_offsets={
                    cid: start + off for cid, off in built.index_offsets.items()
                },
                message_index_length=len(built.records) - built.chunk_length,
                compression=built.compression,
                compressed_size=built.compressed_size,
                uncompressed_size=built.uncompressed_size,
            )
        )
        for cid, n in built.message_counts.items():
            self._counts[cid] = self._counts.get(cid, 0) + n
        if self._start_ns is None or built.start_ns < self._start_ns:
            self._start_ns = built.start_ns
        self._end_ns = max(self._end_ns, built.end_ns)

    def flush(self) -> None:
        self._out.flush()

    def finish(self) -> None:
        """DataEnd, the summary (its groups located by SummaryOffset records), Footer, magic.
        Does not close the stream."""
        self._write_record(DataEnd(0))
        summary_start = self._pos
        rb = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records) -> None:
            start = rb.count
            for rec in records:
                rec.write(rb)
            if rb.count > start:
                offsets.append(SummaryOffset(opcode, summary_start + start, rb.count - start))

        stats = Statistics(
            attachment_count=0,
            channel_count=len(self._channels),
            channel_message_counts=dict(sorted(self._counts.items())),
            chunk_count=len(self._chunk_indexes),
            message_count=sum(self._counts.values()),
            message_end_time=self._end_ns,
            message_start_time=self._start_ns or 0,
            metadata_count=len(self._metadata_indexes),
            schema_count=len(self._schemas),
        )
        group(Opcode.SCHEMA, sorted(self._schemas.values(), key=lambda s: s.id))
        group(Opcode.CHANNEL, sorted(self._channels.values(), key=lambda c: c.id))
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        offset_start = summary_start + rb.count
        for off in offsets:
            off.write(rb)
        summary = rb.end()
        # The footer's CRC covers the summary and the footer's fields before the CRC itself.
        crc = zlib.crc32(
            struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start, offset_start),
            zlib.crc32(summary),
        )
        self._write(summary)
        self._write_record(Footer(summary_start, offset_start, crc))
        self._write(MAGIC)
        self._out.flush()

"""recording/mcap_chunks.py: files it writes read back with the mcap library's own readers (the
indexed one Foxglove's seeking resembles, and the streaming one with CRCs checked), and its
hand-packed Message and MessageIndex records agree with the library's."""

from __future__ import annotations

import io
import random

import pytest
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, ChunkIndex, Message, MessageIndex, Schema
from mcap.stream_reader import StreamReader

from recording.mcap_chunks import ChunkBuilder, McapFile, PlainReader


def _two_streams(n: int = 300, seed: int = 3) -> tuple[bytes, list[tuple[str, int, bytes]]]:
    """A file written as the recorder writes one: covey's chunks and a second builder's chunks
    (ids from 0xC000, as the Foxglove worker's) interleaved, log times a little out of order."""
    rng = random.Random(seed)
    buf = io.BytesIO()
    f = McapFile(buf, "covey", "test")
    f.add_metadata("covey", {"fleet": "t"})
    raw, fox = ChunkBuilder(), ChunkBuilder()
    raw.add_schema(Schema(1, b"layout", "covey-struct", "covey.VehicleState"))
    fox.add_schema(Schema(0xC000, b"{}", "jsonschema", "j"))
    sent = []
    topics = {}
    for k in range(n):
        t = 1_000_000 + 1000 * k + rng.randint(-1500, 1500)
        vid = rng.randint(1, 4)
        for builder, base, topic in ((raw, 1, f"v/{vid}/state"), (fox, 0xC000, f"/v/{vid}")):
            cid = topics.get(topic)
            if cid is None:
                cid = topics[topic] = base + sum(1 for x in topics if x[0] == topic[0])
                builder.add_channel(Channel(cid, topic, "e", {}, base))
            data = rng.randbytes(rng.randint(0, 90))
            builder.add(cid, t, data, t + 1, seq=k)
            sent.append((topic, t, data))
        if rng.random() < 0.05:
            f.write_chunk(raw.build())
        if rng.random() < 0.03:
            f.write_chunk(fox.build())
    for builder in (raw, fox):
        f.write_chunk(builder.build())
    f.finish()
    return buf.getvalue(), sent


def test_the_mcap_library_reads_everything_back_indexed_and_streamed():
    blob, sent = _two_streams()
    reader = make_reader(io.BytesIO(blob))
    got = [(ch.topic, m.log_time, m.data) for _s, ch, m in reader.iter_messages()]
    assert sorted(got) == sorted(sent)
    assert [t for _, t, _ in got] == sorted(t for _, t, _ in got)  # the index orders by time
    summary = reader.get_summary()
    assert summary.statistics.message_count == len(sent)
    assert sum(summary.statistics.channel_message_counts.values()) == len(sent)
    assert set(summary.channels) == {cid for cid in summary.statistics.channel_message_counts}
    assert {s.id for s in summary.schemas.values()} == {1, 0xC000}
    assert summary.statistics.message_start_time == min(t for _, t, _ in sent)
    assert summary.statistics.message_end_time == max(t for _, t, _ in sent)
    assert [m.name for m in reader.iter_metadata()] == ["covey"]
    streamed = [
        r
        for r in StreamReader(io.BytesIO(blob), validate_crcs=True).records
        if isinstance(r, Message)
    ]
    assert len(streamed) == len(sent)


def test_message_indexes_point_at_their_messages():
    blob, _ = _two_streams(n=200, seed=5)
    summary = make_reader(io.BytesIO(blob)).get_summary()
    assert len(summary.chunk_indexes) >= 4
    for ci in summary.chunk_indexes:
        assert isinstance(ci, ChunkIndex)
        stream = ReadDataStream(io.BytesIO(blob[ci.chunk_start_offset + 9 :]))
        chunk = Chunk.read(stream)
        plain = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size
        )
        assert len(plain) == chunk.uncompressed_size
        assert (chunk.message_start_time, chunk.message_end_time) == (
            ci.message_start_time,
            ci.message_end_time,
        )
        for cid, offset in ci.message_index_offsets.items():
            assert blob[offset] == 0x07
            index = MessageIndex.read(ReadDataStream(io.BytesIO(blob[offset + 9 :])))
            assert index.channel_id == cid
            for log_time, at in index.records:
                assert plain[at] == 0x05
                msg = Message.read(
                    ReadDataStream(io.BytesIO(plain[at + 9 :])),
                    int.from_bytes(plain[at + 1 : at + 9], "little"),
                )
                assert (msg.channel_id, msg.log_time) == (cid, log_time)


def test_plain_reader_gives_back_what_was_added():
    b = ChunkBuilder()
    b.add_schema(Schema(1, b"", "", "s"))
    b.add_channel(Channel(1, "a", "e", {}, 1))
    b.add(1, 5, b"one", 5)
    b.add_channel(Channel(2, "b", "e", {"k": "v"}, 1))
    b.add(2, 4, b"", 4)
    first = b.build(keep_plain=True)
    b.add(1, 9, b"three", 9)
    second = b.build(keep_plain=True)
    reader = PlainReader()
    assert list(reader.messages(first.plain)) == [("a", 5, b"one"), ("b", 4, b"")]
    assert list(reader.messages(second.plain)) == [("a", 9, b"three")]  # channel from before
    assert (first.start_ns, first.end_ns, first.messages) == (4, 5, 2)
    assert b.build() is None  # nothing since


def test_bad_ids_and_compression_are_refused():
    with pytest.raises(ValueError, match="zstd"):
        ChunkBuilder("lz4")
    f = McapFile(io.BytesIO())
    a, b = ChunkBuilder(), ChunkBuilder()
    a.add_channel(Channel(1, "a", "e", {}, 0))
    b.add_channel(Channel(1, "b", "e", {}, 0))
    a.add(1, 1, b"", 1)
    b.add(1, 1, b"", 1)
    f.write_chunk(a.build())
    with pytest.raises(ValueError, match="channel id 1 is already a"):
        f.write_chunk(b.build())

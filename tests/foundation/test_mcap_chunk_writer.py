"""ChunkedMcapWriter and McapJsonWriter's fast paths: real files, read back with the mcap library.

The lean writer must write what the ``mcap`` library's ``Writer`` writes (same records, same
indexes, same summary), be read back by the library's seeking and streaming readers, and leave
a recoverable file when the process stops between chunks.
"""

from __future__ import annotations

import io
import json
import math
import random
import re
from pathlib import Path

import lz4.frame
import pytest
import zstandard
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import (
    COMPRESSIONS,
    ChunkedMcapWriter,
    McapJsonWriter,
    iter_messages,
    json_safe,
    recover,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.records import Chunk, ChunkIndex, MessageIndex
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

_LIBRARY_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


class _Bytes:
    """A file that keeps what is written (``ChunkedMcapWriter`` needs only ``write``)."""

    def __init__(self) -> None:
        self.buffer = io.BytesIO()
        self.writes = 0

    def write(self, data: bytes) -> int:
        self.writes += 1
        return self.buffer.write(data)


def _script(n_messages: int, n_topics: int, seed: int) -> list[tuple[int, bytes, int, int]]:
    """(topic index, data, log time, publish time) of a run: times out of order now and then."""
    rng = random.Random(seed)
    rows = []
    for i in range(n_messages):
        topic = rng.randrange(n_topics)
        log = 1_800_000_000_000_000_000 + 1_000 * i + rng.choice((0, 0, 0, -5_000, 3))
        data = json.dumps({"k": i, "v": rng.random()}).encode() * rng.choice((1, 1, 3))
        rows.append((topic, data, log, log + rng.choice((0, 7))))
    return rows


def _both(
    rows: list[tuple[int, bytes, int, int]],
    n_topics: int,
    *,
    chunk_size: int,
    compression: str,
    register_late: bool = False,
) -> tuple[bytes, bytes, int]:
    """The same run written by ChunkedMcapWriter and by the library's Writer."""
    ours_file = _Bytes()
    ours = ChunkedMcapWriter(
        ours_file, chunk_size=chunk_size, compression=compression, library="test", zstd_level=3
    )
    theirs_file = io.BytesIO()
    theirs = Writer(
        theirs_file, chunk_size=chunk_size, compression=_LIBRARY_COMPRESSION[compression]
    )
    theirs.start(library="test")
    channels: dict[int, tuple[int, int]] = {}

    def register(topic: int) -> None:
        ids = []
        for writer in (ours, theirs):
            schema = writer.register_schema(f"/t{topic}", "jsonschema", b'{"type":"object"}')
            ids.append(writer.register_channel(f"/t{topic}", "json", schema))
        channels[topic] = (ids[0], ids[1])

    if not register_late:
        for topic in range(n_topics):
            register(topic)
    for sequence, (topic, data, log, publish) in enumerate(rows):
        if topic not in channels:
            register(topic)
        ours.add_message(channels[topic][0], data, log, publish)
        theirs.add_message(channels[topic][1], log, data, publish, sequence)
    ours.finish()
    theirs.finish()
    return ours_file.buffer.getvalue(), theirs_file.getvalue(), ours_file.writes


@pytest.mark.parametrize("compression", COMPRESSIONS)
@pytest.mark.parametrize("chunk_size", [1, 700, 32 * 1024, 10**9])
def test_files_are_the_library_writers_files(compression: str, chunk_size: int) -> None:
    rows = _script(1500, 37, seed=chunk_size)
    ours, theirs, _ = _both(rows, 37, chunk_size=chunk_size, compression=compression)
    assert ours == theirs


def test_channels_registered_between_messages_and_empty_files() -> None:
    rows = _script(800, 12, seed=3)
    ours, theirs, _ = _both(rows, 12, chunk_size=900, compression="zstd", register_late=True)
    assert ours == theirs
    for n_topics in (0, 3):  # no messages at all: schemas and channels only in the summary
        ours, theirs, _ = _both([], n_topics, chunk_size=900, compression="lz4")
        assert ours == theirs
        with io.BytesIO(ours) as stream:
            summary = make_reader(stream).get_summary()
        assert summary.statistics.message_count == 0 and len(summary.channels) == n_topics


def _records(body: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of the records in a chunk's uncompressed bytes."""
    records, offset = [], 0
    while offset < len(body):
        length = 9 + int.from_bytes(body[offset + 1 : offset + 9], "little")
        records.append((offset, body[offset], length))
        offset += length
    assert offset == len(body)
    return records


def _uncompressed(chunk: Chunk) -> bytes:
    if chunk.compression == "zstd":
        return zstandard.decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    if chunk.compression == "lz4":
        return lz4.frame.decompress(chunk.data)
    assert chunk.compression == ""
    return chunk.data


def _u(data: bytes, at: int, size: int) -> int:
    return int.from_bytes(data[at : at + size], "little")


def _read_message_index(data: bytes, offset: int) -> MessageIndex:
    """The message index record at ``offset`` of the file, parsed by hand."""
    assert data[offset] == 0x07
    channel_id, size = _u(data, offset + 9, 2), _u(data, offset + 11, 4)
    assert _u(data, offset + 1, 8) == 6 + size
    entries = [
        (_u(data, at, 8), _u(data, at + 8, 8)) for at in range(offset + 15, offset + 15 + size, 16)
    ]
    return MessageIndex(channel_id=channel_id, records=entries)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_seeking_reader_indexes_and_chunk_boundaries(compression: str) -> None:
    n_topics, chunk_size = 53, 2000
    rows = _script(4000, n_topics, seed=11)
    data, _, writes = _both(rows, n_topics, chunk_size=chunk_size, compression=compression)
    with io.BytesIO(data) as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        statistics = summary.statistics
        assert statistics.message_count == len(rows)
        assert statistics.chunk_count == len(summary.chunk_indexes) > 50
        assert writes == 1 + statistics.chunk_count + 2  # header, chunks, data end, summary
        counts: dict[int, int] = {}
        for topic, *_ in rows:
            counts[topic + 1] = counts.get(topic + 1, 0) + 1
        assert dict(statistics.channel_message_counts) == counts
        assert statistics.message_start_time == min(row[2] for row in rows)
        assert statistics.message_end_time == max(row[2] for row in rows)
        # every message comes back, with its channel and publish time
        read = [
            (channel.topic, message.log_time, message.publish_time, message.data)
            for _, channel, message in reader.iter_messages(log_time_order=False)
        ]
        assert read == [(f"/t{t}", log, pub, d) for t, d, log, pub in rows]
        middle = sorted(row[2] for row in rows)[len(rows) // 2]
        late = list(reader.iter_messages(topics=["/t5"], starting_at=middle))
        assert [m.log_time for _, _, m in late] == sorted(
            log for t, _, log, _ in rows if t == 5 and log >= middle
        )
    chunk_indexes = {index.chunk_start_offset: index for index in summary.chunk_indexes}
    checked = 0
    for start in sorted(chunk_indexes):
        index = chunk_indexes[start]
        chunk = next(
            iter(
                StreamReader(
                    io.BytesIO(data[start : start + index.chunk_length]),
                    skip_magic=True,
                    emit_chunks=True,
                    validate_crcs=True,
                ).records
            )
        )
        assert isinstance(chunk, Chunk)
        assert (chunk.message_start_time, chunk.message_end_time) == (
            index.message_start_time,
            index.message_end_time,
        )
        assert index.compressed_size == len(chunk.data)
        body = _uncompressed(chunk)
        assert len(body) == chunk.uncompressed_size == index.uncompressed_size
        records = _records(body)
        # a chunk ends with the message that takes it past chunk_size (the last one: anywhere)
        ends = [offset + length for offset, opcode, length in records if opcode == 0x05]
        assert all(end <= chunk_size for end in ends[:-1])
        if start != max(chunk_indexes):
            assert ends[-1] == len(body) > chunk_size
        # its message indexes follow it and point at exactly its messages
        assert min(index.message_index_offsets.values()) == start + index.chunk_length
        messages = {offset for offset, opcode, _ in records if opcode == 0x05}
        indexed = set()
        for channel_id, offset in index.message_index_offsets.items():
            message_index = _read_message_index(data, offset)
            assert message_index.channel_id == channel_id
            for log_time, at in message_index.records:
                assert body[at] == 0x05  # a Message record
                assert _u(body, at + 9, 2) == channel_id
                assert _u(body, at + 15, 8) == log_time
                indexed.add(at)
                checked += 1
        assert indexed == messages
    assert checked == len(rows)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_cut_anywhere_recovers_the_complete_chunks(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "full.mcap"
    with McapJsonWriter(path, chunk_size=800, compression=compression) as writer:
        writer.add_topic("/a/y", fields=("x", "y"))
        writer.add_topic("/a/u")
        for k in range(300):
            writer.write_floats_many(
                [
                    ("/a/y", k, 0.1 * k, (float(k), -0.5), 1000 + k),
                    ("/a/u", k, 0.1 * k, (0.25,), 1000 + k),
                ]
            )
    full = list(iter_messages(path))
    assert len(full) == 600
    with path.open("rb") as stream:
        chunk_indexes = make_reader(stream).get_summary().chunk_indexes
    data = path.read_bytes()
    ends = sorted(c.chunk_start_offset + c.chunk_length for c in chunk_indexes)
    for cut_at in (ends[0] - 1, ends[0] + 3, ends[len(ends) // 2] + 40, ends[-1] - 10):
        cut = tmp_path / f"cut{cut_at}.mcap"
        cut.write_bytes(data[:cut_at])
        complete = [c for c in chunk_indexes if c.chunk_start_offset + c.chunk_length <= cut_at]
        expected = sum(len(c.message_index_offsets) and _messages_in(data, c) for c in complete)
        readable = list(iter_messages(cut))
        assert readable == full[: len(readable)] and len(readable) == expected
        fixed = tmp_path / f"fixed{cut_at}.mcap"
        assert recover(cut, fixed) == expected
        with fixed.open("rb") as stream:
            assert make_reader(stream).get_summary().statistics.message_count == expected
        assert list(iter_messages(fixed)) == readable


def _messages_in(data: bytes, chunk_index: ChunkIndex) -> int:
    count = 0
    for offset in chunk_index.message_index_offsets.values():
        reader = StreamReader(io.BytesIO(data[offset:]), skip_magic=True)
        count += len(next(iter(reader.records)).records)
    return count


floats = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=60, deadline=None)
@given(
    k=st.integers(0, 2**62),
    t=floats,
    rows=st.lists(st.lists(floats, min_size=2, max_size=2), min_size=1, max_size=4),
    plain=st.lists(floats, max_size=5),
)
def test_fast_paths_write_what_json_dumps_gives(
    tmp_path_factory: pytest.TempPathFactory,
    k: int,
    t: float,
    rows: list[list[float]],
    plain: list[float],
) -> None:
    path = tmp_path_factory.mktemp("fast") / "fast.mcap"
    with McapJsonWriter(path, compression="none") as writer:
        writer.add_topic("/a/y", fields=("x", "n%d"))  # a field name with "n" and "%"
        writer.write_floats("/a/y", k=k, t=t, values=rows[0], log_time_ns=1)
        writer.write_floats_many(
            [("/a/y", k, t, values, 2) for values in rows] + [("/a/p", k, -t, plain, 3)],
            register=True,
        )
    expected = []
    for values in [rows[0], *rows]:
        message = {"k": k, "t": t, "values": values, "x": values[0], "n%d": values[1]}
        expected.append(message)
    expected.append({"k": k, "t": -t, "values": plain})
    with path.open("rb") as stream:
        raw = [m.data for _, _, m in make_reader(stream).iter_messages(log_time_order=False)]
    assert raw == [
        json.dumps(json_safe(m), allow_nan=False, separators=(",", ":")).encode() for m in expected
    ]


def test_times_are_formatted_exactly(tmp_path: Path) -> None:
    path = tmp_path / "t.mcap"
    times = [0.0, -0.0, 0.0, 0.1, 0.1, -0.0, math.nan, math.inf, 1e16, 1e-5, 2, True]
    with McapJsonWriter(path, compression="none") as writer:
        writer.write_floats_many(
            [("/a", i, t, (0.5,), i) for i, t in enumerate(times)], register=True
        )
    with path.open("rb") as stream:
        raw = [m.data for _, _, m in make_reader(stream).iter_messages(log_time_order=False)]
    texts = [re.match(rb'{"k":\d+,"t":([^,]*),"values":\[0\.5\]}$', data) for data in raw]
    assert all(texts), raw
    assert [match.group(1).decode() for match in texts if match] == [
        "0.0", "-0.0", "0.0", "0.1", "0.1", "-0.0", "null", "null", "1e+16", "1e-05", "2.0",
        "1.0",
    ]  # fmt: skip


def test_write_floats_many_order_and_refusals(tmp_path: Path) -> None:
    path = tmp_path / "many.mcap"
    with McapJsonWriter(path) as writer:
        writer.add_topic("/a/y", fields=("x", "y"))
        writer.write_json("/a/status", {"state": "running"}, 5)
        assert writer.write_floats_many([("/a/y", 1, 0.1, (1.0, 2.0), 10)]) == 1
        with pytest.raises(RecordingError, match="not registered"):
            writer.write_floats_many([("/a/u", 1, 0.1, (1.0,), 11)])
        with pytest.raises(RecordingError, match=r"expected 2 values"):
            writer.write_floats_many(
                [("/a/y", 2, 0.2, (3.0, 4.0), 12), ("/a/y", 3, 0.3, (5.0,), 13)]
            )
        with pytest.raises(RecordingError, match="must be floats"):
            writer.write_floats_many([("/a/y", 4, 0.4, (1, 2), 14)])
        with pytest.raises(RecordingError, match="log_time_ns"):
            writer.write_floats_many([("/a/y", 4, 0.4, (1.0, 2.0), -1)])
        writer.write_json("/a/status", {"state": "safe"}, 20)
        assert writer.messages_written == 4
    ks = [(topic, m.get("k", m.get("state"))) for topic, _, m in iter_messages(path)]
    assert ks == [("/a/status", "running"), ("/a/y", 1), ("/a/y", 2), ("/a/status", "safe")]
    with pytest.raises(RecordingError, match="closed"):
        writer.write_floats_many([("/a/y", 5, 0.5, (1.0, 2.0), 30)])

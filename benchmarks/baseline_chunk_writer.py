"""The hand-written MCAP chunk writer hilswarm recorded with before foxglove-sdk (baseline only).

Kept for ``benchmarks/record_stream.py``, which prints the per-message cost of the recorder's
writer (foxglove-sdk) beside this baseline in the same run. Nothing in the package uses it.
"""

# ruff: noqa
from __future__ import annotations

import struct
import sys
import zlib
from array import array
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Channel as McapChannel
from mcap.records import ChunkIndex, DataEnd, Footer, Header, Statistics, SummaryOffset
from mcap.records import Schema as McapSchema
from mcap.writer import MCAP0_MAGIC

from hilswarm.agents.errors import RecordingError

COMPRESSIONS = ("zstd", "lz4", "none")


class _DirectFile:
    """A write-only file whose every write goes straight to the OS (no user-space buffer)."""

    def __init__(self, path: Path) -> None:
        self._raw = open(path, "wb", buffering=0)  # noqa: SIM115
        self.name = str(path)

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            written = self._raw.write(view)
            if written is None:
                raise OSError(f"non-blocking write to {self.name} did not proceed")
            view = view[written:]
        return len(data)

    def close(self) -> None:
        self._raw.close()


#: MCAP record opcodes written by :class:`ChunkedMcapWriter` itself.
_OP_MESSAGE = int(Opcode.MESSAGE)
_OP_CHUNK = int(Opcode.CHUNK)
_OP_MESSAGE_INDEX = int(Opcode.MESSAGE_INDEX)
#: Message record head: opcode, record length, channel id, sequence, log and publish time.
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED = _MESSAGE_HEAD.size - 9  # the record length beside the data [bytes]
_MESSAGE_HEAD_SIZE = _MESSAGE_HEAD.size
_pack_message_head = _MESSAGE_HEAD.pack
#: Chunk record head up to its compression name: opcode, length, start/end time, size, crc.
_CHUNK_HEAD = struct.Struct("<BQQQQI")
_U64 = struct.Struct("<Q")
#: Message index record head: opcode, record length, channel id, byte length of the entries.
_INDEX_HEAD = struct.Struct("<BQHI")
_INDEX_HEAD_SIZE = _INDEX_HEAD.size
#: Layouts of whole message index records of up to this many numbers (two per entry).
_INDEX_RECORD_MAX = 64
_INDEX_RECORDS: dict[int, struct.Struct] = {}
_LITTLE_ENDIAN = sys.byteorder == "little"


def _index_record(channel_id: int, entries: list[int]) -> bytes:
    """A message index record: ``entries`` holds log time [ns] and offset of each message."""
    n = len(entries)
    if n > _INDEX_RECORD_MAX:
        table = array("Q", entries)
        if not _LITTLE_ENDIAN:  # pragma: no cover - MCAP is little-endian
            table.byteswap()
        return _INDEX_HEAD.pack(_OP_MESSAGE_INDEX, 6 + 8 * n, channel_id, 8 * n) + table.tobytes()
    layout = _INDEX_RECORDS.get(n)
    if layout is None:
        layout = _INDEX_RECORDS[n] = struct.Struct(f"<BQHI{n}Q")
    return layout.pack(_OP_MESSAGE_INDEX, 6 + 8 * n, channel_id, 8 * n, *entries)


#: zstd level of recordings: on their small JSON chunks level 1 compresses as well as the
#: ``mcap`` library's level 3 in half the time (``benchmarks/record_stream.py``,
#: ``docs/recording.md``). The level is not part of the file: any reader decompresses it.
ZSTD_LEVEL = 1


def _compressor(compression: str, zstd_level: int) -> tuple[str, Any]:
    """The chunk compression's name in the file and its ``bytes -> bytes`` function."""
    if compression == "zstd":
        return "zstd", zstandard.ZstdCompressor(level=zstd_level).compress
    if compression == "lz4":
        return "lz4", lz4.frame.compress
    return "", None


def check_chunk_options(chunk_size: Any, compression: Any) -> None:
    """Raise :class:`RecordingError` unless ``chunk_size`` [bytes] and ``compression`` are valid."""
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise RecordingError(f"chunk_size must be a positive int [bytes], got {chunk_size!r}")
    if compression not in COMPRESSIONS:
        raise RecordingError(
            f"compression must be one of {sorted(COMPRESSIONS)}, got {compression!r}"
        )


class ChunkedMcapWriter:
    """A lean MCAP writer: chunked, indexed, with summary, for many small messages.

    Writes what the ``mcap`` library's ``Writer`` writes with its defaults (every index,
    statistics, repeated schemas and channels, summary offsets, chunk CRCs, no data-section
    CRC), record for record, so its files are the library's files (byte for byte with
    ``zstd_level=3``); but a message costs one ``struct.pack`` and a few list appends instead
    of a ``Message`` object and a dozen ``BytesIO`` writes. Schemas and channels go into the
    chunk in progress, like the library puts them; each finished chunk is written to the OS in
    one ``write`` together with its message indexes, so a killed process leaves every finished
    chunk readable.

    Args:
        file: where the bytes go; ``write(bytes)`` must write them all.
        chunk_size: a chunk is finished once its records exceed this many bytes.
        compression: ``"zstd"``, ``"lz4"`` or ``"none"``.
        profile: the header's profile.
        library: the header's library name.
        zstd_level: the zstd compression level (the library's is 3).
    """

    def __init__(
        self,
        file: Any,
        *,
        chunk_size: int,
        compression: str,
        profile: str = "",
        library: str = "hilswarm",
        zstd_level: int = ZSTD_LEVEL,
    ) -> None:
        check_chunk_options(chunk_size, compression)
        self._file = file
        self._chunk_size = chunk_size
        self.compression, self._compress = _compressor(compression, zstd_level)
        name = self.compression.encode()
        self._compression_field = struct.pack("<I", len(name)) + name
        self._parts: list[bytes] = []  # records of the chunk in progress
        self._size = 0  # their length [bytes]
        self._indexes: list[list[int]] = [[]]  # per channel id: log time, offset, ...
        self._touched: list[int] = []  # channel ids with messages in this chunk, in order
        self._schemas: list[McapSchema] = []
        self._channels: list[McapChannel] = []
        self._counts: list[int] = [0]  # messages per channel id
        self._count_order: list[int] = []  # channel ids in order of their first message
        self._times: list[int] = []  # log times of the chunk's messages [ns]
        self._chunk_indexes: list[ChunkIndex] = []
        self._start_time = 0
        self._end_time = 0
        self.message_count = 0
        self._position = 0  # bytes written to the file
        builder = RecordBuilder()
        Header(profile=profile, library=library).write(builder)
        self._write(MCAP0_MAGIC + builder.end())

    def _write(self, data: bytes) -> None:
        self._file.write(data)
        self._position += len(data)

    def _add_record(self, record: McapSchema | McapChannel) -> None:
        builder = RecordBuilder()
        record.write(builder)
        data = builder.end()
        self._parts.append(data)
        self._size += len(data)
        if self._size > self._chunk_size:
            self.finish_chunk()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Register a schema (recorded in the chunk in progress); returns its id (1, 2, ...)."""
        schema = McapSchema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._add_record(schema)
        return schema.id

    def register_channel(
        self,
        topic: str,
        message_encoding: str,
        schema_id: int,
        metadata: Mapping[str, str] | None = None,
    ) -> int:
        """Register a channel (recorded in the chunk in progress); returns its id (1, 2, ...)."""
        channel = McapChannel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=dict(metadata or {}),
        )
        if channel.id > 0xFFFF:
            raise RecordingError(f"too many channels for MCAP (topic {topic})")
        self._channels.append(channel)
        self._indexes.append([])
        self._counts.append(0)
        self._add_record(channel)
        return channel.id

    def add_message(self, channel_id: int, data: bytes, log_time: int, publish_time: int) -> None:
        """Add a message to the chunk in progress (times [ns], non-negative ints).

        The sequence number is the message's place in the file (modulo 2**32).
        """
        offset = self._size
        size = len(data)
        self._parts += (
            _pack_message_head(
                _OP_MESSAGE,
                _MESSAGE_FIXED + size,
                channel_id,
                self.message_count & 0xFFFFFFFF,
                log_time,
                publish_time,
            ),
            data,
        )
        index = self._indexes[channel_id]
        if not index:
            self._touched.append(channel_id)
        index += (log_time, offset)
        self._times.append(log_time)
        self.message_count += 1
        self._size = offset = offset + _MESSAGE_HEAD_SIZE + size
        if offset > self._chunk_size:
            self.finish_chunk()

    def finish_chunk(self) -> None:
        """Write the chunk in progress and its message indexes (nothing without messages)."""
        if not self._touched:  # no message in this chunk
            return
        records = b"".join(self._parts)
        times = self._times
        start, end = min(times), max(times)
        data = records if self._compress is None else self._compress(records)
        head = _CHUNK_HEAD.pack(
            _OP_CHUNK,
            8 + 8 + 8 + 4 + len(self._compression_field) + 8 + len(data),
            start,
            end,
            len(records),
            zlib.crc32(records),
        )
        chunk = b"".join((head, self._compression_field, _U64.pack(len(data)), data))
        chunk_start = self._position
        index_start = position = chunk_start + len(chunk)
        # One message index record per channel of the chunk, in order of first message.
        parts = [chunk]
        index_offsets: dict[int, int] = {}
        indexes, counts, order = self._indexes, self._counts, self._count_order
        for channel_id in self._touched:
            entries = indexes[channel_id]
            n = len(entries)  # two per message: log time, offset
            parts.append(_index_record(channel_id, entries))
            index_offsets[channel_id] = position
            position += _INDEX_HEAD_SIZE + 8 * n
            if not counts[channel_id]:
                order.append(channel_id)
            counts[channel_id] += n >> 1
            entries.clear()
        self._write(b"".join(parts))
        if not self._chunk_indexes:
            self._start_time = start
        else:
            self._start_time = min(self._start_time, start)
        self._end_time = max(self._end_time, end)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=start,
                message_end_time=end,
                chunk_start_offset=chunk_start,
                chunk_length=len(chunk),
                message_index_offsets=index_offsets,
                message_index_length=position - index_start,
                compression=self.compression,
                compressed_size=len(data),
                uncompressed_size=len(records),
            )
        )
        self._parts = []
        self._size = 0
        self._touched = []
        self._times = []

    def finish(self) -> None:
        """Write the last chunk, the data end, the summary and the footer (as the library)."""
        self.finish_chunk()
        builder = RecordBuilder()
        DataEnd(0).write(builder)
        self._write(builder.end())
        summary_start = self._position
        summary = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: int, records: Iterable[Any]) -> None:
            group_start = summary.count
            for record in records:
                record.write(summary)
            offsets.append(
                SummaryOffset(
                    group_opcode=opcode,
                    group_start=summary_start + group_start,
                    group_length=summary.count - group_start,
                )
            )

        statistics = Statistics(
            attachment_count=0,
            channel_count=len(self._channels),
            channel_message_counts={i: self._counts[i] for i in self._count_order},
            chunk_count=len(self._chunk_indexes),
            message_count=self.message_count,
            metadata_count=0,
            message_start_time=self._start_time,
            message_end_time=self._end_time,
            schema_count=len(self._schemas),
        )
        group(Opcode.SCHEMA, self._schemas)
        group(Opcode.CHANNEL, self._channels)
        group(Opcode.STATISTICS, (statistics,))
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, ())
        group(Opcode.METADATA_INDEX, ())
        summary_offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        summary_data = summary.end()
        crc = zlib.crc32(summary_data)
        crc = zlib.crc32(
            struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start, summary_offset_start),
            crc,
        )
        builder = RecordBuilder()
        Footer(
            summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc
        ).write(builder)
        self._write(summary_data + builder.end() + MCAP0_MAGIC)

"""MCAP recording with JSON messages and JSON Schema, so Foxglove can open and plot them.

Writing: :class:`McapJsonWriter` registers one channel per topic and writes

* vector topics (:meth:`McapJsonWriter.write`): every message is
  ``{"k": <tick>, "t": <experiment time [s]>, "values": [...], <field>: <value>, ...}``;
  the topic contract is ``/<agent>/y``, ``/<agent>/u``, ``/<agent>/x_hat``,
  ``/<agent>/telemetry/<channel>``, ``/orchestrator/ticks``;
* free-form JSON topics (:meth:`McapJsonWriter.write_json`) such as ``/experiment`` and
  ``/<agent>/status``.

Message encoding is ``json`` and schema encoding ``jsonschema`` (what Foxglove reads). Chunks are
small (32 KiB by default, zstd level 1 by default) and written straight to the file descriptor,
so a crashed process loses at most the chunk in progress. JSON has no NaN/Infinity: non-finite
numbers become ``null``. The MCAP records are written by :class:`ChunkedMcapWriter`, which
writes what the ``mcap`` library's ``Writer`` writes at a fraction of its cost per message;
:meth:`McapJsonWriter.write_floats_many` is the hot path of a run recording.

Reading: :func:`iter_messages` yields ``(topic, log_time_ns, message)`` in file order and stops
cleanly at the first incomplete record of a truncated file; :func:`read_schemas` returns the
JSON Schema of every topic; :func:`recover` rewrites the readable part of a damaged file as a
valid MCAP file.
"""

from __future__ import annotations

import json
import logging
import math
import os
import struct
import sys
import zlib
from array import array
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Protocol, Self

import lz4.frame
import numpy as np
import zstandard
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.record_schema import BASE_KEYS, experiment_log_time_ns, vector_schema
from mcap.data_stream import RecordBuilder
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.reader import StreamReader
from mcap.records import Channel as McapChannel
from mcap.records import (
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Statistics,
    SummaryOffset,
)
from mcap.records import Message as McapMessage
from mcap.records import Schema as McapSchema
from mcap.writer import MCAP0_MAGIC, Writer
from numpy.typing import ArrayLike

logger = logging.getLogger(__name__)

#: Default chunk size [bytes]: small, so a crash loses little.
DEFAULT_CHUNK_SIZE = 32 * 1024


#: Chunk compressions a writer offers.
COMPRESSIONS = ("zstd", "lz4", "none")
#: Chunk compression of recordings (see ``docs/recording.md`` for the measurement).
DEFAULT_COMPRESSION = "zstd"

#: Schema of a free-form JSON topic registered without a schema.
ANY_OBJECT_SCHEMA: dict[str, Any] = {"type": "object"}


def finite_or_none(value: float) -> float | None:
    """``value`` as a float, or ``None`` if it is NaN or infinite (JSON has neither)."""
    number = float(value)
    return number if math.isfinite(number) else None


def json_number(value: float) -> str:
    """``value`` as JSON text: Python's shortest round-trip form, ``null`` when not finite."""
    text = float.__repr__(value)
    return "null" if "n" in text else text  # only "nan" and "inf" contain an "n"


def vector_json(
    k: int, t: float, values: Sequence[float], quoted_fields: Sequence[str] | None = None
) -> bytes:
    """The JSON bytes of one vector message, as ``json.dumps`` of the message dict would give.

    ``{"k":k,"t":t,"values":[...],"<field>":values[i],...}`` with non-finite numbers as
    ``null``. Built from text templates: a few microseconds for a short vector, about a fifth
    of building the dict and encoding it with ``json``.

    Args:
        k: tick index.
        t: experiment time [s].
        values: the vector as Python floats (numpy float64 scalars are floats too).
        quoted_fields: JSON-quoted field names (``'"x"'``), one per value, or ``None``.
    """
    numbers = list(map(float.__repr__, values))
    text = ",".join(numbers)
    if "n" in text:  # a NaN or an infinity: JSON has neither
        numbers = ["null" if "n" in number else number for number in numbers]
        text = ",".join(numbers)
    t_text = float.__repr__(float(t))
    if "n" in t_text:
        t_text = "null"
    if quoted_fields:
        named = "".join(
            f",{name}:{number}" for name, number in zip(quoted_fields, numbers, strict=True)
        )
        return f'{{"k":{int(k)},"t":{t_text},"values":[{text}]{named}}}'.encode()
    return f'{{"k":{int(k)},"t":{t_text},"values":[{text}]}}'.encode()


def json_safe(obj: Any) -> Any:
    """A copy of ``obj`` that ``json.dumps(..., allow_nan=False)`` accepts.

    numpy arrays and scalars become lists and Python numbers, tuples become lists, and
    non-finite floats become ``None``.
    """
    if isinstance(obj, bool | int | str) or obj is None:
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        return json_safe(obj.item())
    if isinstance(obj, Mapping):
        return {str(key): json_safe(value) for key, value in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(item) for item in obj]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise RecordingError(f"cannot encode {type(obj).__name__} {obj!r} as JSON")


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
        self._metadata_indexes: list[MetadataIndex] = []
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

    def add_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        """Write a metadata record (between chunks: the chunk in progress is written first)."""
        self.finish_chunk()
        builder = RecordBuilder()
        Metadata(name=name, metadata=dict(metadata)).write(builder)
        data = builder.end()
        self._metadata_indexes.append(
            MetadataIndex(offset=self._position, length=len(data), name=name)
        )
        self._write(data)

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
            metadata_count=len(self._metadata_indexes),
            message_start_time=self._start_time,
            message_end_time=self._end_time,
            schema_count=len(self._schemas),
        )
        group(Opcode.SCHEMA, self._schemas)
        group(Opcode.CHANNEL, self._channels)
        group(Opcode.STATISTICS, (statistics,))
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, ())
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
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


#: JSON text of recent experiment times ``t``: every agent's messages of a tick share their
#: ``t``, and formatting a float is the dearest part of a message. Bounded by
#: :data:`_T_TEXTS_SIZE`; cleared when full.
_T_TEXTS: dict[float, str] = {}
_T_TEXTS_SIZE = 256


def _t_text(t: float) -> str:
    """``t`` as JSON text (``null`` when not finite), remembered in :data:`_T_TEXTS`."""
    text = float.__repr__(float(t))
    if "n" in text:  # only "nan" and "inf" contain an "n"
        return "null"
    if t:  # not 0.0 or -0.0, which are equal keys with two texts
        if len(_T_TEXTS) >= _T_TEXTS_SIZE:
            _T_TEXTS.clear()
        _T_TEXTS[t] = text
    return text


class _Topic:
    """A registered topic: its channel, schema, field names and JSON template."""

    __slots__ = (
        "channel_id", "fields", "name", "quoted_fields", "schema", "template", "wall_template",
        "width",
    )  # fmt: skip

    def __init__(
        self, name: str, channel_id: int, schema: dict[str, Any], fields: tuple[str, ...] | None
    ) -> None:
        self.name = name
        self.channel_id = channel_id
        self.schema = schema
        self.fields = fields
        self.width = None if fields is None else len(fields)
        self.quoted_fields = None if fields is None else tuple(json.dumps(f) for f in fields)
        # The JSON text of a message with "%" holes: k, t, the values and each named field.
        named = "".join(f",{name.replace('%', '%%')}:%s" for name in self.quoted_fields or ())
        self.template = '{"k":%d,"t":%s,"values":[%s]' + named + "}"
        # The same with the wall time [ns] the message was received at (experiment clock).
        self.wall_template = '{"k":%d,"t":%s,"wall_ns":%d,"values":[%s]' + named + "}"

    def vector_bytes(
        self, k: int, t: float, values: Sequence[float], wall_ns: int | None = None
    ) -> bytes:
        """:func:`vector_json` of a message of this topic, from its template.

        Raises:
            RecordingError: not one value per field, or values that are not floats.
        """
        width = self.width
        try:
            if width is None:  # values only: no list of the numbers needed
                text = ",".join(map(float.__repr__, values))
                numbers: list[str] = []
            elif len(values) == width:
                numbers = list(map(float.__repr__, values))
                text = ",".join(numbers)
            else:
                raise RecordingError(
                    f"topic {self.name}: expected {width} values {self.fields}, got {len(values)}"
                )
            t_text = _T_TEXTS.get(t) or _t_text(t)
        except TypeError as exc:
            raise RecordingError(
                f"topic {self.name}: values must be floats, got {values!r}"
            ) from exc
        if "n" in text:  # a NaN or an infinity: JSON has neither
            numbers = ["null" if "n" in number else number for number in text.split(",")]
            text = ",".join(numbers)
        if wall_ns is not None:
            if width is None:
                return (self.wall_template % (int(k), t_text, wall_ns, text)).encode()
            return (self.wall_template % (int(k), t_text, wall_ns, text, *numbers)).encode()
        if width is None:
            return (self.template % (int(k), t_text, text)).encode()
        return (self.template % (int(k), t_text, text, *numbers)).encode()


class Mirror(Protocol):
    """Something that sees what a :class:`McapJsonWriter` writes (the live view)."""

    def add_channel(self, channel_id: int, topic: str, schema: Mapping[str, Any]) -> None:
        """A topic was registered (its JSON Schema); must not block."""

    def log(self, channel_id: int, data: bytes, log_time_ns: int) -> None:
        """A message was written (its JSON bytes); must not block."""


class McapJsonWriter:
    """Writes one MCAP file of JSON messages, one channel (with its JSON Schema) per topic.

    Args:
        path: file to create (overwritten if it exists).
        chunk_size: target chunk size [bytes]; a chunk is written to the file descriptor as soon
            as it is full, so a crash loses at most this much.
        compression: ``"zstd"`` (default, :data:`DEFAULT_COMPRESSION`), ``"lz4"`` or
            ``"none"``.
        profile: the MCAP header profile (empty: none).
        time_origin_ns: when given [ns, wall clock], the log time of a message with an
            experiment time ``t`` is ``time_origin_ns + t``
            (:func:`~hilswarm.agents.record_schema.experiment_log_time_ns`) and the log time
            passed to a write method, the wall clock, goes into the message as ``wall_ns``.
        mirror: also hands every channel and message to this (e.g. the live view); ``None``
            costs nothing.

    Use as a context manager, or call :meth:`close` (which writes the summary and footer).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: str = DEFAULT_COMPRESSION,
        profile: str = "",
        time_origin_ns: int | None = None,
        mirror: Mirror | None = None,
    ) -> None:
        check_chunk_options(chunk_size, compression)
        self.path = Path(path)
        self._origin = time_origin_ns
        self._file = _DirectFile(self.path)
        try:
            self._writer = ChunkedMcapWriter(
                self._file, chunk_size=chunk_size, compression=compression, profile=profile
            )
        except BaseException:
            self._file.close()
            raise
        self._topics: dict[str, _Topic] = {}
        self._closed = False
        self._mirror = mirror
        self._add_message = self._writer.add_message if mirror is None else self._mirrored

    @property
    def messages_written(self) -> int:
        """Messages written so far."""
        return self._writer.message_count

    @property
    def topics(self) -> tuple[str, ...]:
        """Registered topics, in registration order."""
        return tuple(self._topics)

    def has_topic(self, topic: str) -> bool:
        """True if ``topic`` is registered (no copy of :attr:`topics`: cheap per message)."""
        return topic in self._topics

    def topic_fields(self, topic: str) -> tuple[str, ...] | None:
        """The field names of vector topic ``topic`` (``None``: none, or not registered)."""
        entry = self._topics.get(topic)
        return None if entry is None else entry.fields

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run."""
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"MCAP writer for {self.path} is closed")

    def _register(self, topic: str, schema: dict[str, Any], fields: tuple[str, ...] | None) -> None:
        title = str(schema.get("title", ""))
        # A Foxglove well-known schema keeps its name (foxglove.PoseInFrame): panels key on it.
        name = title if title.startswith("foxglove.") else topic
        schema_id = self._writer.register_schema(
            name=name, encoding="jsonschema", data=json.dumps(schema).encode()
        )
        channel_id = self._writer.register_channel(
            topic=topic, message_encoding="json", schema_id=schema_id
        )
        if self._mirror is not None:
            self._mirror.add_channel(channel_id, topic, schema)
        self._topics[topic] = _Topic(topic, channel_id, schema, fields)

    @staticmethod
    def _check_topic_name(topic: str) -> None:
        if not isinstance(topic, str) or not topic.startswith("/") or len(topic) < 2:
            raise RecordingError(f"topic must be a string starting with '/', got {topic!r}")

    def add_topic(
        self,
        topic: str,
        fields: Sequence[str] | None = None,
        units: Mapping[str, str] | None = None,
    ) -> None:
        """Register a vector topic; its messages carry ``k``, ``t``, ``values`` and ``fields``.

        With ``fields`` (one name per vector entry) every message also carries
        ``{field: values[i]}`` beside ``values``, and the schema names them, so Foxglove can
        plot ``/a/y.x`` as well as ``/a/y.values[0]``; ``units`` (field -> unit) go into the
        schema's descriptions. Registering a topic again with the same fields does nothing.

        Raises:
            RecordingError: bad topic or field names, a name that clashes with ``k``/``t``/
                ``values``, or the topic exists with other fields or as a JSON topic.
        """
        self._check_open()
        self._check_topic_name(topic)
        names: tuple[str, ...] | None = None
        if fields is not None:
            if isinstance(fields, str):
                raise RecordingError(f"topic {topic}: fields must be a sequence, got {fields!r}")
            names = tuple(fields)
            for name in names:
                if not isinstance(name, str) or not name or name in BASE_KEYS:
                    raise RecordingError(
                        f"topic {topic}: field names must be non-empty strings other than "
                        f"{BASE_KEYS}, got {name!r}"
                    )
            if len(set(names)) != len(names):
                raise RecordingError(f"topic {topic}: field names repeat: {names}")
        existing = self._topics.get(topic)
        if existing is not None:
            if existing.schema.get("required") != list(BASE_KEYS) or existing.fields != names:
                raise RecordingError(
                    f"topic {topic} is registered already with fields {existing.fields}, "
                    f"cannot register it with {names}"
                )
            return
        self._register(topic, vector_schema(topic, names, units), names)

    def write(
        self,
        topic: str,
        *,
        k: int,
        t: float,
        values: ArrayLike,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        **extra: Any,
    ) -> None:
        """Write one vector message to a topic registered with :meth:`add_topic`.

        Args:
            topic: the registered topic.
            k: tick index.
            t: experiment time [s].
            values: the vector (any length for topics without fields, one entry per field
                otherwise). NaN and ±inf are written as JSON ``null``.
            log_time_ns: MCAP log time [ns] (the recorder's clock).
            publish_time_ns: MCAP publish time [ns]; defaults to ``log_time_ns``.
            **extra: more JSON-encodable keys written beside ``values`` (non-finite numbers
                inside become ``null`` too).

        Raises:
            RecordingError: unknown topic, wrong number of values, a clashing extra key.
        """
        self._check_open()
        entry = self._topics.get(topic)
        if entry is None:
            raise RecordingError(f"topic {topic!r} is not registered: call add_topic() first")
        vector = np.asarray(values, dtype=np.float64).reshape(-1)
        if not extra:
            self.write_floats(
                topic,
                k=k,
                t=t,
                values=vector.tolist(),
                log_time_ns=log_time_ns,
                publish_time_ns=publish_time_ns,
            )
            return
        message: dict[str, Any] = {
            "k": int(k),
            "t": finite_or_none(t),
            "values": [finite_or_none(v) for v in vector.tolist()],
        }
        if entry.fields is not None:
            if vector.shape[0] != len(entry.fields):
                raise RecordingError(
                    f"topic {topic}: expected {len(entry.fields)} values {entry.fields}, "
                    f"got {vector.shape[0]}"
                )
            message.update(zip(entry.fields, message["values"], strict=True))
        for key, value in extra.items():
            if key in message:
                raise RecordingError(f"topic {topic}: extra key {key!r} clashes with a field")
            message[key] = json_safe(value)
        self._add(entry.channel_id, message, log_time_ns, publish_time_ns)

    def write_floats(
        self,
        topic: str,
        *,
        k: int,
        t: float,
        values: Sequence[float],
        log_time_ns: int,
        publish_time_ns: int | None = None,
    ) -> None:
        """:meth:`write` for a vector that is already a sequence of Python floats (fast path).

        Raises:
            RecordingError: unknown topic, wrong number of values.
        """
        self._check_open()
        entry = self._topics.get(topic)
        if entry is None:
            raise RecordingError(f"topic {topic!r} is not registered: call add_topic() first")
        if type(log_time_ns) is not int or log_time_ns < 0:
            _check_log_time(log_time_ns)
            log_time_ns = int(log_time_ns)
        if self._origin is None:
            data = entry.vector_bytes(k, t, values)
        else:
            data = entry.vector_bytes(k, t, values, log_time_ns)
            log_time_ns = experiment_log_time_ns(self._origin, t)
        if publish_time_ns is None:
            publish_time_ns = log_time_ns
        else:
            _check_log_time(publish_time_ns)
        self._add_message(entry.channel_id, data, log_time_ns, int(publish_time_ns))

    def write_floats_many(
        self,
        rows: Iterable[tuple[str, int, float, Sequence[float], int]],
        *,
        register: bool = False,
    ) -> int:
        """:meth:`write_floats` for many messages, in order (the record stream's hot path).

        Args:
            rows: per message ``(topic, k, t, values, log_time_ns)``; values are Python floats,
                ``t`` in [s], the log time (also the publish time) in [ns].
            register: register topics not seen yet as vector topics without field names
                (otherwise they are refused).

        Returns:
            The number of messages written.

        Raises:
            RecordingError: as :meth:`write_floats`; the messages before the refused one are
                written, none after it.
        """
        self._check_open()
        topics = self._topics
        add = self._add_message
        origin = self._origin
        count = 0
        for topic, k, t, values, log_time_ns in rows:
            entry = topics.get(topic)
            if entry is None:
                if not register:
                    raise RecordingError(
                        f"topic {topic!r} is not registered: call add_topic() first"
                    )
                self.add_topic(topic)
                entry = topics[topic]
            if type(log_time_ns) is not int or log_time_ns < 0:
                _check_log_time(log_time_ns)
                log_time_ns = int(log_time_ns)  # noqa: PLW2901 - a numpy integer
            if origin is None:
                data = entry.vector_bytes(k, t, values)
            else:
                data = entry.vector_bytes(k, t, values, log_time_ns)
                log_time_ns = experiment_log_time_ns(origin, t)  # noqa: PLW2901
            add(entry.channel_id, data, log_time_ns, log_time_ns)
            count += 1
        return count

    def write_json(
        self,
        topic: str,
        obj: Mapping[str, Any],
        log_time_ns: int,
        schema: Mapping[str, Any] | None = None,
    ) -> None:
        """Write a free-form JSON object (``/experiment``, ``/<agent>/status``, ...).

        The first write registers the topic with ``schema`` (a JSON Schema; default: any
        object). Later writes may repeat the same schema or pass ``None``. Non-finite numbers
        anywhere in ``obj`` become ``null``; numpy arrays become lists.

        Raises:
            RecordingError: bad topic, ``obj`` not a mapping or not JSON-encodable, or a schema
                different from the one the topic was registered with.
        """
        self._check_open()
        self._check_topic_name(topic)
        if not isinstance(obj, Mapping):
            raise RecordingError(f"topic {topic}: message must be a mapping, got {type(obj)}")
        entry = self._topics.get(topic)
        if entry is None:
            chosen = dict(schema) if schema is not None else dict(ANY_OBJECT_SCHEMA)
            self._register(topic, chosen, None)
            entry = self._topics[topic]
        elif schema is not None and dict(schema) != entry.schema:
            raise RecordingError(f"topic {topic} is registered already with another schema")
        self._add(entry.channel_id, json_safe(obj), log_time_ns, None)

    def write_encoded(
        self,
        topic: str,
        data: bytes,
        log_time_ns: int,
        schema: Mapping[str, Any] | None = None,
        *,
        t: float | None = None,
    ) -> None:
        """Write a JSON object that is already encoded (UTF-8, no NaN/Infinity: ``null``).

        With an experiment clock (``time_origin_ns``) and ``t`` given, the log time is that
        of ``t`` (the caller encodes ``wall_ns`` in ``data`` itself).

        For writers that build the JSON text of a frequent message themselves (templates are
        several times cheaper than building and encoding a dict). The topic is registered
        like :meth:`write_json` does.

        Raises:
            RecordingError: bad topic, ``data`` not bytes, or another schema than registered.
        """
        self._check_open()
        if not isinstance(data, bytes | bytearray):
            raise RecordingError(f"topic {topic}: encoded message must be bytes, got {type(data)}")
        entry = self._topics.get(topic)
        if entry is None:
            self._check_topic_name(topic)
            chosen = dict(schema) if schema is not None else dict(ANY_OBJECT_SCHEMA)
            self._register(topic, chosen, None)
            entry = self._topics[topic]
        elif schema is not None and dict(schema) != entry.schema:
            raise RecordingError(f"topic {topic} is registered already with another schema")
        if self._origin is not None and t is not None:
            log_time_ns = experiment_log_time_ns(self._origin, t)
        self._add_encoded(entry.channel_id, bytes(data), log_time_ns, None)

    def _add(
        self,
        channel_id: int,
        message: Mapping[str, Any],
        log_time_ns: int,
        publish_time_ns: int | None,
    ) -> None:
        t = message.get("t")
        if self._origin is not None and isinstance(t, int | float) and "wall_ns" not in message:
            _check_log_time(log_time_ns)
            message = {**message, "wall_ns": int(log_time_ns)}
            log_time_ns = experiment_log_time_ns(self._origin, float(t))
        data = json.dumps(message, allow_nan=False, separators=(",", ":")).encode()
        self._add_encoded(channel_id, data, log_time_ns, publish_time_ns)

    def _add_encoded(
        self, channel_id: int, data: bytes, log_time_ns: int, publish_time_ns: int | None
    ) -> None:
        _check_log_time(log_time_ns)
        log_time = int(log_time_ns)
        if publish_time_ns is None:
            publish_time = log_time
        else:
            _check_log_time(publish_time_ns)
            publish_time = int(publish_time_ns)
        self._add_message(channel_id, data, log_time, publish_time)

    def _mirrored(self, channel_id: int, data: bytes, log_time: int, publish_time: int) -> None:
        self._writer.add_message(channel_id, data, log_time, publish_time)
        self._mirror.log(channel_id, data, log_time)  # type: ignore[union-attr]

    def add_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        """Write an MCAP metadata record ``name`` (string keys and values)."""
        self._check_open()
        self._writer.add_metadata(name, metadata)

    def flush(self) -> None:
        """Finish the chunk in progress and hand everything written so far to the OS."""
        self._check_open()
        self._writer.finish_chunk()

    def close(self) -> None:
        """Write the last chunk, summary and footer, and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _check_log_time(log_time_ns: Any) -> None:
    """Raise :class:`RecordingError` unless ``log_time_ns`` is a non-negative int [ns]."""
    if isinstance(log_time_ns, bool) or not isinstance(log_time_ns, int | np.integer):
        raise RecordingError(f"log_time_ns must be an int [ns], got {log_time_ns!r}")
    if log_time_ns < 0:
        raise RecordingError(f"log_time_ns must be >= 0 [ns], got {log_time_ns}")


class _StrictReads:
    """File wrapper whose short reads raise ``EndOfFile`` (so a cut record is never parsed)."""

    def __init__(self, file: IO[bytes]) -> None:
        self._file = file

    def read(self, size: int = -1) -> bytes:
        data = self._file.read(size)
        if size is not None and size > 0 and len(data) < size:
            raise EndOfFile()
        return data


def _iter_records(path: str | os.PathLike[str]) -> Iterator[Any]:
    """Records of an MCAP file in order; stops at the first incomplete or damaged record."""
    with open(path, "rb") as file:
        reader = StreamReader(_StrictReads(file), validate_crcs=True)  # type: ignore[arg-type]
        records = reader.records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except EndOfFile:
                logger.warning("%s is truncated: read up to the last complete record", path)
                return
            except (McapError, ValueError, OSError) as exc:
                logger.warning("%s is damaged (%s): read up to the last good record", path, exc)
                return
            yield record


def iter_messages(
    path: str | os.PathLike[str], topics: Iterable[str] | None = None
) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """Yield ``(topic, log_time_ns, message)`` for every message of an MCAP JSON file.

    Messages come in file order. A truncated file (a crashed recorder) yields every message of
    its complete chunks and stops at the first incomplete record without raising.

    Args:
        path: the MCAP file.
        topics: only these topics (default: all).
    """
    wanted = None if topics is None else set(topics)
    channels: dict[int, str] = {}
    for record in _iter_records(path):
        if isinstance(record, McapChannel):
            channels[record.id] = record.topic
        elif isinstance(record, McapMessage):
            topic = channels.get(record.channel_id)
            if topic is None:
                raise RecordingError(f"{path}: message on unknown channel {record.channel_id}")
            if wanted is None or topic in wanted:
                yield topic, record.log_time, json.loads(record.data)


def read_metadata(path: str | os.PathLike[str]) -> dict[str, dict[str, str]]:
    """The metadata records of an MCAP file by name (readable part of a truncated file)."""
    return {
        record.name: dict(record.metadata)
        for record in _iter_records(path)
        if isinstance(record, Metadata)
    }


def read_schemas(path: str | os.PathLike[str]) -> dict[str, dict[str, Any]]:
    """The JSON Schema of every topic in an MCAP file (readable part of a truncated file)."""
    schemas: dict[int, dict[str, Any]] = {}
    result: dict[str, dict[str, Any]] = {}
    for record in _iter_records(path):
        if isinstance(record, McapSchema):
            if record.encoding != "jsonschema":
                raise RecordingError(
                    f"{path}: schema {record.name!r} has encoding {record.encoding!r}, "
                    "expected 'jsonschema'"
                )
            schemas[record.id] = json.loads(record.data)
        elif isinstance(record, McapChannel):
            result[record.topic] = schemas.get(record.schema_id, {})
    return result


def recover(source: str | os.PathLike[str], destination: str | os.PathLike[str]) -> int:
    """Rewrite the readable part of a (truncated) MCAP file as a complete, indexed MCAP file.

    Returns:
        The number of messages copied.

    Raises:
        RecordingError: ``source`` and ``destination`` are the same file.
    """
    if Path(source).resolve() == Path(destination).resolve():
        raise RecordingError(f"recover: destination {destination} must differ from the source")
    copied = 0
    with open(destination, "wb") as out:
        writer = Writer(out, chunk_size=DEFAULT_CHUNK_SIZE)
        writer.start(library="hilswarm recover")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for record in _iter_records(source):
            if isinstance(record, McapSchema) and record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(
                    name=record.name, encoding=record.encoding, data=record.data
                )
            elif isinstance(record, McapChannel) and record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    topic=record.topic,
                    message_encoding=record.message_encoding,
                    schema_id=schema_ids.get(record.schema_id, 0),
                    metadata=dict(record.metadata),
                )
            elif isinstance(record, McapMessage) and record.channel_id in channel_ids:
                writer.add_message(
                    channel_id=channel_ids[record.channel_id],
                    log_time=record.log_time,
                    data=record.data,
                    publish_time=record.publish_time,
                    sequence=record.sequence,
                )
                copied += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(name=record.name, data=dict(record.metadata))
        writer.finish()
    return copied

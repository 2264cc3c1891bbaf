"""MCAP recording with JSON messages and JSON Schema, so Foxglove can open and plot them.

Writing: :class:`McapJsonWriter` registers one channel per topic and writes

* vector topics (:meth:`McapJsonWriter.write`, :meth:`~McapJsonWriter.write_floats`): every
  message is ``{"k": <tick>, "t": <experiment time [s]>, "values": [...], <field>: <value>,
  ...}``; the topic contract is ``/<agent>/y``, ``/<agent>/u``, ``/<agent>/x_hat``,
  ``/<agent>/telemetry/<channel>``, ``/orchestrator/ticks``;
* free-form JSON topics (:meth:`McapJsonWriter.write_json`) such as ``/experiment`` and
  ``/<agent>/status``;
* metadata records (:meth:`McapJsonWriter.add_metadata`), such as the run's ``hilswarm.run``.

Message encoding is ``json`` and schema encoding ``jsonschema`` (what Foxglove reads). The MCAP
records themselves (chunks, message and chunk indexes, CRCs, statistics, summary) are written by
foxglove-sdk's MCAP writer, the Rust writer Foxglove maintains (:func:`open_writer`); this
module adds the topic contract and fast JSON text for vector messages, and
:meth:`McapJsonWriter.write_floats_many` is the hot path of a run recording. Chunks are zstd
(level 1, :data:`ZSTD_LEVEL`) by default, ``lz4`` or uncompressed on request, and small
(:data:`DEFAULT_CHUNK_SIZE`, or ``chunk_size=None``: a chunk ends only at
:meth:`McapJsonWriter.flush`, where the recorder process acknowledges). A chunk goes to the file
when it is full or flushed, so a crashed process loses about the chunk in progress. JSON has no
NaN/Infinity: non-finite numbers become ``null``. A :class:`Mirror` (the live view) can be
handed every channel and message too.

Reading, with the ``mcap`` package's non-seeking ``StreamReader``: :func:`iter_messages` yields
``(topic, log_time_ns, message)`` in file order and stops cleanly at the first incomplete
record of a truncated file; :func:`read_schemas` returns the JSON Schema of every topic and
:func:`read_metadata` the metadata records; :func:`recover` rewrites the readable part of a
damaged file as a valid MCAP file.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import sys
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Protocol, Self

import foxglove
import numpy as np
from foxglove import Channel, Schema
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.record_schema import BASE_KEYS, experiment_log_time_ns, vector_schema
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import StreamReader
from mcap.records import Channel as McapChannel
from mcap.records import Message as McapMessage
from mcap.records import Metadata
from mcap.records import Schema as McapSchema
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


#: zstd level of recordings: on their small JSON chunks level 1 compresses as well as level 3
#: in half the time (``benchmarks/record_stream.py``, ``docs/recording.md``). The level is not
#: part of the file: any reader decompresses it.
ZSTD_LEVEL = 1

_COMPRESSIONS: dict[str, MCAPCompression | None] = {
    "zstd": MCAPCompression.Zstd,
    "lz4": MCAPCompression.Lz4,
    "none": None,
}


def check_chunk_options(chunk_size: Any, compression: Any) -> None:
    """Raise :class:`RecordingError` unless ``chunk_size`` [bytes] and ``compression`` are valid.

    ``chunk_size`` may be ``None``: chunks end only at :meth:`McapJsonWriter.flush`.
    """
    if chunk_size is not None and (
        isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1
    ):
        raise RecordingError(f"chunk_size must be a positive int [bytes], got {chunk_size!r}")
    if compression not in COMPRESSIONS:
        raise RecordingError(
            f"compression must be one of {sorted(COMPRESSIONS)}, got {compression!r}"
        )


def open_writer(
    path: str | os.PathLike[str],
    *,
    chunk_size: int | None = DEFAULT_CHUNK_SIZE,
    compression: str = DEFAULT_COMPRESSION,
) -> tuple[foxglove.Context, foxglove.mcap.MCAPWriter]:
    """A foxglove-sdk MCAP writer on ``path`` (replaced if it exists) with its own context.

    foxglove-sdk's writer is the MCAP writer Foxglove maintains (Rust, chunked, indexed, CRCs,
    summary); a message costs about a microsecond through its channel binding, less than the
    hand-written writer this project had (``benchmarks/record_stream.py``). Every channel
    made on the returned context is written to this file and to no other sink.

    Raises:
        RecordingError: bad options, or the file cannot be created.
    """
    check_chunk_options(chunk_size, compression)
    options = MCAPWriteOptions(
        compression=_COMPRESSIONS[compression],
        chunk_size=chunk_size,
        compression_level=ZSTD_LEVEL if compression == "zstd" else 0,
        compression_threads=0,  # compress on the writing thread: the recorder's own core
    )
    context = foxglove.Context()
    try:
        writer = foxglove.open_mcap(
            Path(path), allow_overwrite=True, context=context, writer_options=options
        )
    except (RuntimeError, OSError) as exc:
        raise RecordingError(f"cannot create the MCAP file {path}: {exc}") from exc
    return context, writer


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
        "fields", "log", "name", "quoted_fields", "schema", "template", "wall_template", "width",
    )  # fmt: skip

    def __init__(
        self,
        name: str,
        log: Any,
        schema: dict[str, Any],
        fields: tuple[str, ...] | None,
    ) -> None:
        self.name = name
        self.log = log  # the channel's raw binding: log(data: bytes, log_time_ns: int)
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
        chunk_size: target chunk size [bytes]; a chunk is written to the file as soon as it is
            full, so a crash loses at most this much. ``None``: chunks end only at
            :meth:`flush` (the recorder process ends them where it acknowledges).
        compression: ``"zstd"`` (default, :data:`DEFAULT_COMPRESSION`), ``"lz4"`` or
            ``"none"``.
        time_origin_ns: when given [ns, wall clock], the log time of a message with an
            experiment time ``t`` is ``time_origin_ns + t``
            (:func:`~hilswarm.agents.record_schema.experiment_log_time_ns`) and the log time
            passed to a write method, the wall clock, goes into the message as ``wall_ns``.
        mirror: also hands every channel and message to this (e.g. the live view); ``None``
            costs nothing.

    The MCAP records are written by foxglove-sdk's writer (:func:`open_writer`); this class
    adds the topic contract and fast JSON text for vector messages.

    Use as a context manager, or call :meth:`close` (which writes the summary and footer).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int | None = DEFAULT_CHUNK_SIZE,
        compression: str = DEFAULT_COMPRESSION,
        time_origin_ns: int | None = None,
        mirror: Mirror | None = None,
    ) -> None:
        self.path = Path(path)
        self._origin = time_origin_ns
        self._mirror = mirror
        self._context, self._writer = open_writer(
            self.path, chunk_size=chunk_size, compression=compression
        )
        self._topics: dict[str, _Topic] = {}
        self._channels: list[Channel] = []
        self._closed = False
        self._count = 0

    @property
    def messages_written(self) -> int:
        """Messages written so far."""
        return self._count

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
        channel = Channel(
            topic,
            schema=Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode()),
            message_encoding="json",
            context=self._context,
        )
        self._channels.append(channel)
        # the raw binding (what Channel.log calls for bytes), a few tenths of a µs cheaper
        log = channel.base.log
        mirror = self._mirror
        if mirror is not None:
            channel_id = channel.id()
            mirror.add_channel(channel_id, topic, schema)
            file_log, mirror_log = log, mirror.log

            def log(data: bytes, log_time_ns: int) -> None:
                file_log(data, log_time_ns)
                mirror_log(channel_id, data, log_time_ns)

        self._topics[topic] = _Topic(topic, log, schema, fields)

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
        **extra: Any,
    ) -> None:
        """Write one vector message to a topic registered with :meth:`add_topic`.

        Args:
            topic: the registered topic.
            k: tick index.
            t: experiment time [s].
            values: the vector (any length for topics without fields, one entry per field
                otherwise). NaN and ±inf are written as JSON ``null``.
            log_time_ns: MCAP log time [ns] (also its publish time).
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
        self._add(entry, message, log_time_ns)

    def write_floats(
        self,
        topic: str,
        *,
        k: int,
        t: float,
        values: Sequence[float],
        log_time_ns: int,
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
        entry.log(data, log_time_ns)
        self._count += 1

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
            entry.log(data, log_time_ns)
            count += 1
            self._count += 1
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
        self._add(entry, json_safe(obj), log_time_ns)

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
        self._add_encoded(entry, bytes(data), log_time_ns)

    def _add(self, entry: _Topic, message: Mapping[str, Any], log_time_ns: int) -> None:
        t = message.get("t")
        if self._origin is not None and isinstance(t, int | float) and "wall_ns" not in message:
            _check_log_time(log_time_ns)
            message = {**message, "wall_ns": int(log_time_ns)}
            log_time_ns = experiment_log_time_ns(self._origin, float(t))
        data = json.dumps(message, allow_nan=False, separators=(",", ":")).encode()
        self._add_encoded(entry, data, log_time_ns)

    def _add_encoded(self, entry: _Topic, data: bytes, log_time_ns: int) -> None:
        _check_log_time(log_time_ns)
        entry.log(data, int(log_time_ns))
        self._count += 1

    def add_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        """Write an MCAP metadata record ``name`` (string keys and values)."""
        self._check_open()
        try:
            self._writer.write_metadata(name, dict(metadata))
        except RuntimeError as exc:
            raise RecordingError(f"writing metadata {name!r} to {self.path} failed: {exc}") from exc

    def flush(self) -> None:
        """Finish the chunk in progress and hand everything written so far to the OS.

        Raises:
            RecordingError: the file could not be written (e.g. the disk is full).
        """
        self._check_open()
        try:
            self._writer.flush()
        except RuntimeError as exc:  # foxglove-sdk reports I/O errors as FoxgloveError
            raise RecordingError(f"writing {self.path} failed: {exc}") from exc

    def close(self) -> None:
        """Write the last chunk, summary and footer, and close the file (idempotent).

        Raises:
            RecordingError: the file could not be written (e.g. the disk is full).
        """
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.close()
        except RuntimeError as exc:
            raise RecordingError(f"closing {self.path} failed: {exc}") from exc
        finally:
            for channel in self._channels:
                channel.close()

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
        if size is not None and size > sys.maxsize:
            # A chunk the writer had begun when it was killed: foxglove-sdk's (mcap-rust) writer
            # puts all-ones sizes in a chunk's header until the chunk is finished.
            raise EndOfFile()
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
            except (McapError, ValueError, OSError, OverflowError) as exc:
                logger.warning("%s is damaged (%s): read up to the last good record", path, exc)
                return
            yield record


def iter_messages(
    path: str | os.PathLike[str],
    topics: Iterable[str] | None = None,
    *,
    schemas: dict[str, dict[str, Any]] | None = None,
) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """Yield ``(topic, log_time_ns, message)`` for every message of an MCAP JSON file.

    Messages come in file order. A truncated file (a crashed recorder) yields every message of
    its complete chunks and stops at the first incomplete record without raising.

    Args:
        path: the MCAP file.
        topics: only these topics (default: all).
        schemas: filled, as the file is read, with the JSON Schema of every topic (as
            :func:`read_schemas` gives them), so one pass reads both (and a damaged file is
            reported once).
    """
    wanted = None if topics is None else set(topics)
    channels: dict[int, str] = {}
    known: dict[int, dict[str, Any]] = {}
    for record in _iter_records(path):
        if schemas is not None and isinstance(record, McapSchema):
            known[record.id] = _json_schema(path, record)
        if isinstance(record, McapChannel):
            channels[record.id] = record.topic
            if schemas is not None:
                schemas[record.topic] = known.get(record.schema_id, {})
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
            schemas[record.id] = _json_schema(path, record)
        elif isinstance(record, McapChannel):
            result[record.topic] = schemas.get(record.schema_id, {})
    return result


def _json_schema(path: str | os.PathLike[str], record: McapSchema) -> dict[str, Any]:
    """The JSON Schema a Schema record holds.

    Raises:
        RecordingError: the record is not a JSON Schema.
    """
    if record.encoding != "jsonschema":
        raise RecordingError(
            f"{path}: schema {record.name!r} has encoding {record.encoding!r}, "
            "expected 'jsonschema'"
        )
    return json.loads(record.data)


def recover(source: str | os.PathLike[str], destination: str | os.PathLike[str]) -> int:
    """Rewrite the readable part of a (truncated) MCAP file as a complete, indexed MCAP file.

    Returns:
        The number of messages copied.

    Raises:
        RecordingError: ``source`` and ``destination`` are the same file, or the destination
            cannot be written (e.g. the disk is full; what was written of it is removed).
    """
    if Path(source).resolve() == Path(destination).resolve():
        raise RecordingError(f"recover: destination {destination} must differ from the source")
    copied = 0
    context, writer = open_writer(destination)
    closed = False
    try:
        schemas: dict[int, McapSchema] = {}
        logs: dict[int, Any] = {}
        kept: list[Channel] = []
        for record in _iter_records(source):
            if isinstance(record, McapSchema):
                schemas.setdefault(record.id, record)
            elif isinstance(record, McapChannel) and record.id not in logs:
                known = schemas.get(record.schema_id)
                channel = Channel(
                    record.topic,
                    schema=None
                    if known is None
                    else Schema(name=known.name, encoding=known.encoding, data=known.data),
                    message_encoding=record.message_encoding,
                    context=context,
                    metadata=dict(record.metadata) or None,
                )
                kept.append(channel)
                logs[record.id] = channel.base.log
            elif isinstance(record, McapMessage) and record.channel_id in logs:
                logs[record.channel_id](record.data, record.log_time)
                copied += 1
            elif isinstance(record, Metadata):
                writer.write_metadata(record.name, dict(record.metadata))
        closed = True
        writer.close()
    except RuntimeError as exc:  # foxglove-sdk's I/O errors (FoxgloveError)
        if not closed:
            with contextlib.suppress(RuntimeError):
                writer.close()
        Path(destination).unlink(missing_ok=True)
        raise RecordingError(f"writing {destination} failed: {exc}") from exc
    return copied

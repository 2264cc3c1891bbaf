"""MCAP recording with JSON messages and JSON Schema, so Foxglove can open and plot them.

Writing: :class:`McapJsonWriter` registers one channel per topic and writes

* vector topics (:meth:`McapJsonWriter.write`): every message is
  ``{"k": <tick>, "t": <experiment time [s]>, "values": [...], <field>: <value>, ...}``;
  the topic contract is ``/<agent>/y``, ``/<agent>/u``, ``/<agent>/x_hat``,
  ``/<agent>/telemetry/<channel>``, ``/orchestrator/ticks``;
* free-form JSON topics (:meth:`McapJsonWriter.write_json`) such as ``/experiment`` and
  ``/<agent>/status``.

Message encoding is ``json`` and schema encoding ``jsonschema`` (what Foxglove reads). Chunks are
small (32 KiB by default) and written straight to the file descriptor, so a crashed process loses
at most the chunk in progress. JSON has no NaN/Infinity: non-finite numbers become ``null``.

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
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Self

import numpy as np
from hilswarm.agents.errors import RecordingError
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import StreamReader
from mcap.records import Channel as McapChannel
from mcap.records import Message as McapMessage
from mcap.records import Schema as McapSchema
from mcap.writer import CompressionType, Writer
from numpy.typing import ArrayLike

logger = logging.getLogger(__name__)

#: Default chunk size [bytes]: small, so a crash loses little.
DEFAULT_CHUNK_SIZE = 32 * 1024

#: Keys every vector message has.
BASE_KEYS = ("k", "t", "values")

_COMPRESSIONS = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}

#: Schema of a free-form JSON topic registered without a schema.
ANY_OBJECT_SCHEMA: dict[str, Any] = {"type": "object"}


def vector_schema(topic: str, fields: Sequence[str] | None = None) -> dict[str, Any]:
    """The JSON Schema of a vector topic: ``k``, ``t``, ``values`` and the named ``fields``."""
    properties: dict[str, Any] = {
        "k": {"type": "integer", "description": "tick index"},
        "t": {"type": "number", "description": "experiment time [s]"},
        "values": {
            "type": "array",
            "items": {"type": ["number", "null"]},
            "description": "the vector; null marks a non-finite (NaN/inf) entry",
        },
    }
    for index, field in enumerate(fields or ()):
        properties[field] = {
            "type": ["number", "null"],
            "description": f"values[{index}]",
        }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": topic,
        "type": "object",
        "properties": properties,
        "required": list(BASE_KEYS),
    }


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
    """A write-only file whose every write goes straight to the OS (no user-space buffer).

    Not an ``io.RawIOBase`` on purpose: the mcap ``Writer`` would wrap one in a
    ``BufferedWriter`` and keep the data in the process until the end.
    """

    def __init__(self, path: Path) -> None:
        self._raw = open(path, "wb", buffering=0)  # noqa: SIM115

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            written = self._raw.write(view)
            if written is None:
                raise OSError(f"non-blocking write to {self._raw.name} did not proceed")
            view = view[written:]
        return len(data)

    def tell(self) -> int:
        return self._raw.tell()

    def flush(self) -> None:
        self._raw.flush()

    def close(self) -> None:
        self._raw.close()


class _Topic:
    __slots__ = ("channel_id", "fields", "quoted_fields", "schema")

    def __init__(self, channel_id: int, schema: dict[str, Any], fields: tuple[str, ...] | None):
        self.channel_id = channel_id
        self.schema = schema
        self.fields = fields
        self.quoted_fields = None if fields is None else tuple(json.dumps(f) for f in fields)


class McapJsonWriter:
    """Writes one MCAP file of JSON messages, one channel (with its JSON Schema) per topic.

    Args:
        path: file to create (overwritten if it exists).
        chunk_size: target chunk size [bytes]; a chunk is written to the file descriptor as soon
            as it is full, so a crash loses at most this much.
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
        profile: the MCAP header profile (empty: none).

    Use as a context manager, or call :meth:`close` (which writes the summary and footer).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: str = "zstd",
        profile: str = "",
    ) -> None:
        if not isinstance(chunk_size, int) or chunk_size < 1:
            raise RecordingError(f"chunk_size must be a positive int [bytes], got {chunk_size!r}")
        if compression not in _COMPRESSIONS:
            raise RecordingError(
                f"compression must be one of {sorted(_COMPRESSIONS)}, got {compression!r}"
            )
        self.path = Path(path)
        self._file = _DirectFile(self.path)
        self._writer = Writer(
            self._file, chunk_size=chunk_size, compression=_COMPRESSIONS[compression]
        )
        self._writer.start(profile=profile, library="hilswarm")
        self._topics: dict[str, _Topic] = {}
        self._closed = False
        self.messages_written = 0

    @property
    def topics(self) -> tuple[str, ...]:
        """Registered topics, in registration order."""
        return tuple(self._topics)

    def has_topic(self, topic: str) -> bool:
        """True if ``topic`` is registered (no copy of :attr:`topics`: cheap per message)."""
        return topic in self._topics

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run."""
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"MCAP writer for {self.path} is closed")

    def _register(self, topic: str, schema: dict[str, Any], fields: tuple[str, ...] | None) -> None:
        schema_id = self._writer.register_schema(
            name=topic, encoding="jsonschema", data=json.dumps(schema).encode()
        )
        channel_id = self._writer.register_channel(
            topic=topic, message_encoding="json", schema_id=schema_id
        )
        self._topics[topic] = _Topic(channel_id, schema, fields)

    @staticmethod
    def _check_topic_name(topic: str) -> None:
        if not isinstance(topic, str) or not topic.startswith("/") or len(topic) < 2:
            raise RecordingError(f"topic must be a string starting with '/', got {topic!r}")

    def add_topic(self, topic: str, fields: Sequence[str] | None = None) -> None:
        """Register a vector topic; its messages carry ``k``, ``t``, ``values`` and ``fields``.

        With ``fields`` (one name per vector entry) every message also carries
        ``{field: values[i]}`` beside ``values``, and the schema names them, so Foxglove can
        plot ``/a/y.x`` as well as ``/a/y.values[0]``. Registering a topic again with the
        same fields does nothing.

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
        self._register(topic, vector_schema(topic, names), names)

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
        if entry.fields is not None and len(values) != len(entry.fields):
            raise RecordingError(
                f"topic {topic}: expected {len(entry.fields)} values {entry.fields}, "
                f"got {len(values)}"
            )
        try:
            data = vector_json(k, t, values, entry.quoted_fields)
        except TypeError as exc:
            raise RecordingError(f"topic {topic}: values must be floats, got {values!r}") from exc
        self._add_encoded(entry.channel_id, data, log_time_ns, publish_time_ns)

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
    ) -> None:
        """Write a JSON object that is already encoded (UTF-8, no NaN/Infinity: ``null``).

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
        self._add_encoded(entry.channel_id, bytes(data), log_time_ns, None)

    def _add(
        self,
        channel_id: int,
        message: Mapping[str, Any],
        log_time_ns: int,
        publish_time_ns: int | None,
    ) -> None:
        data = json.dumps(message, allow_nan=False, separators=(",", ":")).encode()
        self._add_encoded(channel_id, data, log_time_ns, publish_time_ns)

    def _add_encoded(
        self, channel_id: int, data: bytes, log_time_ns: int, publish_time_ns: int | None
    ) -> None:
        if isinstance(log_time_ns, bool) or not isinstance(log_time_ns, int | np.integer):
            raise RecordingError(f"log_time_ns must be an int [ns], got {log_time_ns!r}")
        if log_time_ns < 0:
            raise RecordingError(f"log_time_ns must be >= 0 [ns], got {log_time_ns}")
        self._writer.add_message(
            channel_id=channel_id,
            log_time=int(log_time_ns),
            data=data,
            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
            sequence=self.messages_written & 0xFFFFFFFF,
        )
        self.messages_written += 1

    def flush(self) -> None:
        """Finish the chunk in progress and hand everything written so far to the OS."""
        self._check_open()
        self._writer.flush()

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
        writer.finish()
    return copied

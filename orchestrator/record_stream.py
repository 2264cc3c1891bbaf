"""The record stream: what the instance manager hands to the recorder, as an MCAP data stream.

The manager must not spend its tick on JSON or MCAP chunking. It keeps the bus messages it
receives as they came (the agents' ``y`` payloads with their tick-report attachments, status
JSON, telemetry batches) and one small message per tick with the tick's timing account. Every
flush period it logs what it kept on the channels of an **MCAP stream** written by
foxglove-sdk's MCAP writer (:class:`RecordWriter`: no chunks, no compression, no indexes, so
nothing seeks back and the bytes can go down a pipe as they are made), as one numbered batch,
and hands the batch to a :class:`RecordSink`: usually the pipe of the
recorder process (:mod:`hilswarm.orchestrator.recorder_process`), which decodes it with a
:class:`~hilswarm.orchestrator.stream_recorder.StreamRecorder` and writes the run's MCAP file
(JSON, chunked, compressed, the topics of ``docs/recording.md``).

What the pipe carries is a complete MCAP file: the magic, a Header (profile
:data:`PROFILE`), Schema, Channel and Message records, at the end DataEnd, Footer and the
magic; any MCAP reader opens it. Channels (topic, the message encoding and the schema's name
give the layout; the channel's metadata ``kind`` and ``agent``, the agent's index in the
experiment, say what it carries), little-endian:

* ``agent/<name>/y`` (``y``) — ``uint32 payload length``, the ``y`` payload
  (:func:`~hilswarm.agents.bus.encode_vector`), the tick-report attachment
  (:func:`~hilswarm.agents.bus.encode_report`; none for a ``y`` without one).
* ``agent/<name>/late`` (``late``) — ``int64 k``, ``float64 answer_s``: an agent's ``y_k``
  that came after tick ``k`` was closed without it (its answer time after the tick's send [s]);
  follows that ``y``. Recorded on ``/orchestrator/late`` with the ledger fields of its report.
* ``agent/<name>/status`` (``status``, JSON) — the agent's status message as sent.
* ``agent/<name>/<leaf>`` (``vector``) — a vector the agent puts on another key
  (``telemetry/<channel>``), as sent.
* ``agent/<name>/telemetry`` (``telemetry``) — the agent's telemetry batch as sent
  (:func:`~hilswarm.agents.bus.encode_telemetry_batch`).
* ``orchestrator/ticks`` (``tick``) — ``int64 k``, ``float64 scheduled_s, send_delay_s,
  completion_s`` (NaN: not complete), ``uint16 n_late, n_missing``, the late and missing agent
  indices (``uint16``), then per agent its answer time after the send [s] (``float64``, NaN:
  no answer).
* ``orchestrator/events`` (``event``, JSON) — ``{"agent", "state", "k", "t", "detail"}``: a
  status the manager records itself (an agent lost, e-stop, the reason of a stop).
* ``gateway/<leaf>`` (``gateway``, JSON) — the XBee gateway's ``stats`` and ``status`` as sent.
* ``stream/batch`` (``batch``) — ``uint64 seq``: the last message of batch ``seq``. The
  recorder acknowledges batches by it.

Every message's log time is the manager's wall clock when it kept the message [ns].
"""

from __future__ import annotations

import errno
import io
import json
import struct
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import foxglove
import numpy as np
from foxglove import Channel, Schema
from foxglove.mcap import MCAPWriteOptions

#: The MCAP Header's profile of a record stream.
PROFILE = "hilswarm-record-stream"
#: The MCAP magic, at both ends of a stream.
MAGIC = b"\x89MCAP0\r\n"
#: MCAP opcodes the stream holds.
OP_HEADER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE = 0x01, 0x03, 0x04, 0x05
#: An MCAP record's head: opcode, body length.
RECORD = struct.Struct("<BQ")
#: A Message record's body head: channel id, sequence, log time [ns], publish time [ns].
MESSAGE = struct.Struct("<HIQQ")

#: Channel kinds (the channel metadata's ``kind``).
Y, LATE, STATUS, VECTOR, TELEMETRY, TICK, EVENT, GATEWAY, BATCH = (
    "y", "late", "status", "vector", "telemetry", "tick", "event", "gateway", "batch",
)  # fmt: skip

#: Per kind: message encoding, schema name, the layout (the schema's text).
_KINDS: dict[str, tuple[str, str, str]] = {
    Y: ("hilswarm.y", "hilswarm.record.y", "uint32 payload length, y payload, tick report"),
    LATE: ("hilswarm.late", "hilswarm.record.late", "int64 k, float64 answer_s"),
    STATUS: ("json", "", ""),
    VECTOR: ("hilswarm.vector", "hilswarm.record.vector", "int64 k, float64 t, float64 values[]"),
    TELEMETRY: ("hilswarm.telemetry", "hilswarm.record.telemetry", "telemetry batch as sent"),
    TICK: (
        "hilswarm.tick",
        "hilswarm.record.tick",
        "int64 k, float64 scheduled_s, send_delay_s, completion_s, uint16 n_late, n_missing, "
        "uint16 late[n_late], uint16 missing[n_missing], float64 answer_s[agents]",
    ),
    EVENT: ("json", "", ""),
    GATEWAY: ("json", "", ""),
    BATCH: ("hilswarm.batch", "hilswarm.record.batch", "uint64 seq"),
}

#: Message layouts of the stream (the channel list above): a ``y`` message's head (payload
#: length), a ``late`` message, a ``tick`` message's head, a batch marker.
Y_HEAD = struct.Struct("<I")
LATE_LAYOUT = struct.Struct("<qd")
TICK_HEAD = struct.Struct("<qdddHH")
BATCH_SEQ = struct.Struct("<Q")

#: Agent index of events that concern the orchestrator itself (``/orchestrator/status``).
ORCHESTRATOR = "orchestrator"


@dataclass(frozen=True)
class RecordBatch:
    """A numbered piece of the record stream: whole MCAP records, the last the batch marker."""

    data: bytes
    seq: int
    count: int  # messages in it, the marker not counted
    defines: bool  # it holds Schema or Channel records (a new channel's first message)


class RecordSink(Protocol):
    """Where the manager's record stream goes (the recorder process's pipe, or a recorder
    in-process)."""

    def write(
        self,
        data: bytes,
        *,
        seq: int,
        count: int = 0,
        tick: int = -1,
        first_tick: int = -1,
        defines: bool = False,
    ) -> None:
        """Take batch ``seq`` of the stream (whole records; ``count`` messages, made at the
        manager's ``tick``, of ticks from ``first_tick`` on, the manager's tick when it began
        gathering them; -1: unknown; ``defines``: it holds Schema or Channel records)."""


def hand_over(
    sink: RecordSink, batch: RecordBatch, *, tick: int = -1, first_tick: int = -1
) -> None:
    """Hand ``batch`` to ``sink`` (made at the manager's ``tick``, of ticks from ``first_tick``
    on; -1: unknown)."""
    sink.write(
        batch.data,
        seq=batch.seq,
        count=batch.count,
        tick=tick,
        first_tick=first_tick,
        defines=batch.defines,
    )


class _Spool(io.RawIOBase):
    """The file the MCAP writer writes into: it keeps the bytes until they are taken, and
    refuses to seek back (the stream's writer options never need it)."""

    def __init__(self) -> None:
        super().__init__()
        self._parts: list[bytes] = []
        self._position = 0

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def write(self, data: Any) -> int:
        self._parts.append(bytes(data))
        size = len(self._parts[-1])
        self._position += size
        return size

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        target = offset if whence == io.SEEK_SET else self._position + offset
        if whence not in (io.SEEK_SET, io.SEEK_CUR) or target != self._position:
            raise OSError(errno.ESPIPE, "the record stream cannot seek back")
        return target

    def tell(self) -> int:
        return self._position

    def take(self) -> bytes:
        data = b"".join(self._parts)
        self._parts.clear()
        return data


def writer_options() -> MCAPWriteOptions:
    """foxglove-sdk MCAP writer options of a record stream: records written in order, once."""
    return MCAPWriteOptions(
        compression=None,
        profile=PROFILE,
        use_chunks=False,
        emit_statistics=False,
        emit_summary_offsets=False,
        emit_message_indexes=False,
        emit_chunk_indexes=False,
        repeat_channels=False,
        repeat_schemas=False,
        calculate_data_section_crc=False,
        calculate_summary_section_crc=False,
    )


#: A message kept: the function that logs it (None: a ``y``) and its arguments.
_Kept = tuple[Callable[..., None] | None, tuple[Any, ...]]


class RecordWriter:
    """The manager's side of the record stream: keeps messages, hands out numbered batches.

    The message methods (:meth:`y`, :meth:`status`, ...) only keep what they are given (a tuple
    appended to a list: the bus callbacks stay short). :meth:`write` logs what :meth:`cut`
    took on the MCAP writer and returns it as the next batch (:meth:`write_end`: the last,
    which ends the stream). foxglove-sdk's log call lets go of the GIL, so it runs there,
    outside the caller's lock, never inside a bus callback.

    Threads: the message methods and :meth:`cut` must be serialised by the caller (the
    manager calls them under its lock); :meth:`write` and :meth:`write_end` by one thread at a
    time, in the order of the cuts. :meth:`take` and :meth:`close` do both, for one thread.

    Args:
        names: the experiment's agent names, in order (an agent's index is its position).
    """

    def __init__(self, names: Sequence[str]) -> None:
        self.names = list(names)
        self._spool = _Spool()
        self._context = foxglove.Context()
        self._writer = foxglove.open_mcap(
            self._spool, context=self._context, writer_options=writer_options()
        )
        self._channels: list[Channel] = []
        self._logs: dict[tuple[str, int, str], Callable[[bytes, int], None]] = {}
        self._y_logs = [self._log_of(Y, i) for i in range(len(self.names))]
        # what the message methods keep: (emit, its arguments); emit None: a y (the most
        # frequent message, logged inline)
        self._kept: list[_Kept] = []
        self._emit_bound = self._emit
        self._defines = False
        self._seq = 0
        self.closed = False

    def _log_of(self, kind: str, agent: int = -1, leaf: str = "") -> Callable[[bytes, int], None]:
        """The log function of a channel (made on first use: its first message also writes
        its Schema and Channel records, which the batch then says it holds)."""
        key = (kind, agent, leaf)
        log = self._logs.get(key)
        if log is not None:
            return log
        encoding, schema_name, layout = _KINDS[kind]
        if agent >= 0:
            topic = f"agent/{self.names[agent]}/{leaf or kind}"
        else:
            topic = {TICK: "orchestrator/ticks", EVENT: "orchestrator/events",
                     GATEWAY: f"gateway/{leaf}", BATCH: "stream/batch"}[kind]  # fmt: skip
        if encoding == "json":
            schema = Schema(name="", encoding="", data=b"")
        else:
            schema = Schema(name=schema_name, encoding="text", data=layout.encode())
        metadata = {"kind": kind} | ({"agent": str(agent)} if agent >= 0 else {})
        channel = Channel(
            topic,
            schema=schema,
            message_encoding=encoding,
            context=self._context,
            metadata=metadata,
        )
        self._channels.append(channel)
        raw = channel.base.log  # the raw binding (what Channel.log calls for bytes)

        def first(data: bytes, log_time_ns: int) -> None:
            self._defines = True
            self._logs[key] = raw
            if kind == Y:
                self._y_logs[agent] = raw
            raw(data, log_time_ns)

        self._logs[key] = first
        return first

    @property
    def pending(self) -> int:
        """Messages kept since the last cut."""
        return len(self._kept)

    # -- keeping (cheap: the bus callbacks call these) ---------------------------------------

    def y(self, agent: int, log_time_ns: int, payload: bytes, attachment: bytes) -> None:
        """An agent's ``y`` message (payload and tick-report attachment as received)."""
        self._kept.append((None, (agent, log_time_ns, payload, attachment)))

    def late(self, agent: int, k: int, log_time_ns: int, answer_s: float) -> None:
        """An answer (``y_k`` of ``agent``) that came after tick ``k`` closed without it,
        ``answer_s`` [s] after the tick's send."""
        data = LATE_LAYOUT.pack(k, answer_s)
        self._kept.append((self._emit_bound, (LATE, agent, "", log_time_ns, data)))

    def status(self, agent: int, log_time_ns: int, payload: bytes) -> None:
        """An agent's status message (its JSON as received)."""
        self._kept.append((self._emit_bound, (STATUS, agent, "", log_time_ns, payload)))

    def vector(self, agent: int, log_time_ns: int, leaf: str, payload: bytes) -> None:
        """A vector an agent publishes on another key (``telemetry/<channel>``)."""
        self._kept.append((self._emit_bound, (VECTOR, agent, leaf, log_time_ns, payload)))

    def telemetry(self, agent: int, log_time_ns: int, payload: bytes) -> None:
        """An agent's telemetry batch (as received; decoded by the recorder)."""
        self._kept.append((self._emit_bound, (TELEMETRY, agent, "", log_time_ns, payload)))

    def gateway(self, log_time_ns: int, leaf: str, payload: bytes) -> None:
        """An XBee gateway message (``gateway/<leaf>``, JSON as sent)."""
        self._kept.append((self._emit_bound, (GATEWAY, -1, leaf, log_time_ns, payload)))

    def event(
        self, log_time_ns: int, agent: str, state: str, *, k: int, t: float, detail: str
    ) -> None:
        """A status the manager records itself (``agent`` may be :data:`ORCHESTRATOR`)."""
        message = {"agent": agent, "state": state, "k": int(k), "t": float(t), "detail": detail}
        self._kept.append(
            (self._emit_bound, (EVENT, -1, "", log_time_ns, json.dumps(message).encode()))
        )

    def tick(
        self,
        k: int,
        log_time_ns: int,
        *,
        scheduled_s: float,
        send_delay_s: float,
        completion_s: float,
        late: Sequence[int],
        missing: Sequence[int],
        answer_s: np.ndarray,
    ) -> None:
        """Tick ``k``'s timing account (times [s]; NaN: not complete / no answer)."""
        data = (
            TICK_HEAD.pack(k, scheduled_s, send_delay_s, completion_s, len(late), len(missing))
            + struct.pack(f"<{len(late) + len(missing)}H", *late, *missing)
            + np.ascontiguousarray(answer_s, dtype="<f8").tobytes()
        )
        self._kept.append((self._emit_bound, (TICK, -1, "", log_time_ns, data)))

    def cut(self) -> list[_Kept]:
        """The messages kept so far (the next batch's), in order; keeping starts afresh."""
        kept, self._kept = self._kept, []
        return kept

    # -- writing (the MCAP writer) -----------------------------------------------------------

    def _emit(self, kind: str, agent: int, leaf: str, log_time_ns: int, data: bytes) -> None:
        self._log_of(kind, agent, leaf)(data, log_time_ns)

    def write(self, kept: list[_Kept], log_time_ns: int) -> RecordBatch | None:
        """Log ``kept`` (a :meth:`cut`) as the next batch (``None``: nothing kept)."""
        if self.closed or not kept:
            return None
        self._log_all(kept, log_time_ns)
        self._writer.flush()
        return self._batch(len(kept))

    def write_end(self, kept: list[_Kept], log_time_ns: int) -> RecordBatch:
        """End the stream (DataEnd, Footer): the last batch, with ``kept`` (a :meth:`cut`)."""
        if self.closed:
            raise ValueError("the record stream is closed")
        self._log_all(kept, log_time_ns)
        self._writer.close()
        self.closed = True
        return self._batch(len(kept))

    def take(self, log_time_ns: int) -> RecordBatch | None:
        """:meth:`cut` and :meth:`write` at once (for a caller on one thread)."""
        return self.write(self.cut(), log_time_ns)

    def close(self, log_time_ns: int) -> RecordBatch:
        """:meth:`cut` and :meth:`write_end` at once (for a caller on one thread)."""
        return self.write_end(self.cut(), log_time_ns)

    def _log_all(self, kept: list[_Kept], log_time_ns: int) -> None:
        y_logs, pack = self._y_logs, Y_HEAD.pack
        for emit, args in kept:
            if emit is None:  # a y: agent, log time, payload, attachment
                payload = args[2]
                y_logs[args[0]](pack(len(payload)) + payload + args[3], args[1])
            else:
                emit(*args)
        self._seq += 1
        self._log_of(BATCH)(BATCH_SEQ.pack(self._seq), log_time_ns)

    def _batch(self, count: int) -> RecordBatch:
        batch = RecordBatch(self._spool.take(), self._seq, count, self._defines)
        self._defines = False
        return batch


def records(data: bytes | memoryview, offset: int = 0) -> Iterator[tuple[int, int, int]]:
    """``(opcode, body start, body end)`` of the whole records in ``data`` from ``offset``
    (the magic skipped where it stands; a cut record at the end is left)."""
    end = len(data)
    head = RECORD.size
    while end - offset >= head:
        if data[offset] == MAGIC[0] and data[offset : offset + len(MAGIC)] == MAGIC:
            offset += len(MAGIC)
            continue
        opcode, length = RECORD.unpack_from(data, offset)
        stop = offset + head + length
        if stop > end:
            return
        yield opcode, offset + head, stop
        offset = stop


def definitions(data: bytes) -> bytes:
    """The Header, Schema and Channel records of a batch: what a reader needs before its
    messages (a restarted recorder gets them first)."""
    kept = [
        data[start - RECORD.size : stop]
        for opcode, start, stop in records(data)
        if opcode in (OP_HEADER, OP_SCHEMA, OP_CHANNEL)
    ]
    return b"".join(kept)

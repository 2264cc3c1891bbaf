"""The record stream: what the instance manager hands to the recorder, as compact binary frames.

The manager must not spend its tick on JSON or MCAP. It keeps the bus messages it receives as
they came (the agents' ``y`` payloads with their tick-report attachments, raw status JSON),
adds one small binary frame per tick with the tick's timing account, and writes the frames in
batches to a :class:`RecordSink` — usually the pipe of the recorder process
(:mod:`hilswarm.orchestrator.recorder_process`), which decodes them with a
:class:`FrameRecorder` and writes the MCAP file. The decoding side does all the per-message
work: ``/<agent>/y``, ``/<agent>/u`` and ``/<agent>/x_hat`` from one ``y`` frame, the per-agent
sense/compute/actuate times of ``/orchestrator/ticks`` from the reports of that tick.

Frame layout (little-endian): ``uint8 kind``, ``uint32 body length``, body:

* ``Y`` — ``uint16 agent``, ``int64 log time [ns]``, ``uint32 payload length``, the ``y``
  payload (:func:`~hilswarm.agents.bus.encode_vector`), the report attachment.
* ``TICK`` — ``int64 k``, ``int64 log time [ns]``, ``float64 scheduled_s, send_delay_s,
  completion_s`` (NaN: not complete), ``uint16 n_late, n_missing``, the late and missing agent
  indices (``uint16``), then per agent its answer time after the send [s] (``float64``, NaN:
  no answer).
* ``STATUS`` — ``uint16 agent``, ``int64 log time [ns]``, the agent's status JSON as sent.
* ``EVENT`` — ``int64 log time [ns]``, JSON ``{"agent", "state", "k", "t", "detail"}``: a
  status the manager itself records (an agent lost, e-stop, the reason of a stop).
* ``VECTOR`` — ``uint16 agent``, ``int64 log time [ns]``, ``uint16 leaf length``, the key leaf
  (``telemetry/<channel>``), a vector payload.
* ``TELEMETRY`` — ``uint16 agent``, ``int64 log time [ns]``, the agent's telemetry batch as
  sent (:func:`~hilswarm.agents.bus.encode_telemetry_batch`); the recorder writes one message
  per row on ``/<agent>/telemetry/<channel>``, with the channel's field names.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Iterator, Sequence
from typing import Any, Protocol

import numpy as np
from hilswarm.agents import bus
from hilswarm.agents.errors import HilswarmError, RecordingError
from hilswarm.agents.mcap_io import json_number
from hilswarm.agents.telemetry import telemetry_topic
from hilswarm.orchestrator.experiment import Experiment
from hilswarm.orchestrator.recorder import TICKS_SCHEMA, TICKS_TOPIC, Recorder

logger = logging.getLogger(__name__)

Y, TICK, STATUS, EVENT, VECTOR, TELEMETRY = 1, 2, 3, 4, 5, 6

_HEAD = struct.Struct("<BI")
_Y_HEAD = struct.Struct("<BIHqI")
_TICK_HEAD = struct.Struct("<BIqqdddHH")
_AGENT_HEAD = struct.Struct("<BIHq")
_EVENT_HEAD = struct.Struct("<BIq")
_VECTOR_HEAD = struct.Struct("<BIHqH")

#: Agent index of events that concern the orchestrator itself (``/orchestrator/status``).
ORCHESTRATOR = "orchestrator"


class RecordSink(Protocol):
    """Where the manager's frames go (the recorder process's pipe, or a recorder in-process)."""

    def write(self, data: bytes) -> None:
        """Take a batch of whole frames."""


# -- encoding (the manager's side) ------------------------------------------------------------


def y_frame(agent: int, log_time_ns: int, payload: bytes, attachment: bytes) -> bytes:
    """Frame of an agent's ``y`` message (payload and tick-report attachment as received)."""
    size = _Y_HEAD.size - _HEAD.size + len(payload) + len(attachment)
    return _Y_HEAD.pack(Y, size, agent, log_time_ns, len(payload)) + payload + attachment


def tick_frame(
    k: int,
    log_time_ns: int,
    *,
    scheduled_s: float,
    send_delay_s: float,
    completion_s: float,
    late: Sequence[int],
    missing: Sequence[int],
    answer_s: np.ndarray,
) -> bytes:
    """Frame of tick ``k``'s timing account (times [s]; NaN: not complete / no answer)."""
    indices = struct.pack(f"<{len(late) + len(missing)}H", *late, *missing)
    answers = np.ascontiguousarray(answer_s, dtype="<f8").tobytes()
    size = _TICK_HEAD.size - _HEAD.size + len(indices) + len(answers)
    head = _TICK_HEAD.pack(
        TICK, size, k, log_time_ns, scheduled_s, send_delay_s, completion_s, len(late),
        len(missing),
    )  # fmt: skip
    return head + indices + answers


def status_frame(agent: int, log_time_ns: int, payload: bytes) -> bytes:
    """Frame of an agent's status message (its JSON as received)."""
    size = _AGENT_HEAD.size - _HEAD.size + len(payload)
    return _AGENT_HEAD.pack(STATUS, size, agent, log_time_ns) + payload


def event_frame(
    log_time_ns: int, agent: str, state: str, *, k: int, t: float, detail: str
) -> bytes:
    """Frame of a status the manager records itself (``agent`` may be ``"orchestrator"``)."""
    payload = json.dumps(
        {"agent": agent, "state": state, "k": int(k), "t": float(t), "detail": detail}
    ).encode()
    return _EVENT_HEAD.pack(EVENT, _EVENT_HEAD.size - _HEAD.size + len(payload), log_time_ns) + (
        payload
    )


def vector_frame(agent: int, log_time_ns: int, leaf: str, payload: bytes) -> bytes:
    """Frame of a vector an agent publishes on another key (``telemetry/<channel>``)."""
    name = leaf.encode()
    size = _VECTOR_HEAD.size - _HEAD.size + len(name) + len(payload)
    return _VECTOR_HEAD.pack(VECTOR, size, agent, log_time_ns, len(name)) + name + payload


def telemetry_frame(agent: int, log_time_ns: int, payload: bytes) -> bytes:
    """Frame of an agent's telemetry batch (as received; decoded by the recorder)."""
    size = _AGENT_HEAD.size - _HEAD.size + len(payload)
    return _AGENT_HEAD.pack(TELEMETRY, size, agent, log_time_ns) + payload


# -- decoding (the recorder's side) -----------------------------------------------------------


class FrameReader:
    """Splits a byte stream into frames (bytes may arrive cut anywhere)."""

    def __init__(self) -> None:
        self._pending = b""

    def feed(self, data: bytes) -> Iterator[tuple[int, bytes]]:
        """Yield ``(kind, frame)`` for every whole frame (``frame`` includes its header)."""
        buffer = self._pending + data if self._pending else data
        offset, end = 0, len(buffer)
        head = _HEAD
        while end - offset >= head.size:
            kind, size = head.unpack_from(buffer, offset)
            stop = offset + head.size + size
            if stop > end:
                break
            yield kind, buffer[offset:stop]
            offset = stop
        self._pending = buffer[offset:]

    @property
    def pending(self) -> int:
        """Bytes of an incomplete frame held back [bytes]."""
        return len(self._pending)


class FrameRecorder:
    """Turns frames into MCAP messages on ``recorder`` (the topics of ``docs/recording.md``).

    Args:
        recorder: the run's recorder.
        experiment: the experiment being recorded (agent order, ``dt``).
    """

    def __init__(self, recorder: Recorder, experiment: Experiment) -> None:
        self.recorder = recorder
        self.experiment = experiment
        self.names = experiment.agent_names
        self.dt = experiment.dt
        self._quoted = [json.dumps(name) for name in self.names]
        self._y_topics = [f"/{name}/y" for name in self.names]
        self._u_topics = [f"/{name}/u" for name in self.names]
        self._x_topics = [f"/{name}/x_hat" for name in self.names]
        # Per agent, the (k, timing) of its latest y: the sense/compute/actuate of tick k.
        self._timings: list[tuple[int, bus.AgentTiming] | None] = [None] * len(self.names)
        self._ticks_registered = False
        self._plain_y: set[int] = set()
        # Telemetry topics seen: topic -> field names it was registered with (None: plain).
        self._telemetry_topics: dict[str, tuple[str, ...] | None] = {}
        self.telemetry_rows = 0
        self.frames = 0
        self.errors = 0

    def write(self, data: bytes) -> None:
        """:class:`RecordSink` interface: decode and record a batch of whole frames."""
        reader = FrameReader()
        for kind, frame in reader.feed(data):
            self.apply(kind, frame)
        if reader.pending:
            raise RecordingError(f"record stream: {reader.pending} bytes of a cut frame")

    def apply(self, kind: int, frame: bytes) -> None:
        """Record one frame; a bad frame is logged and counted, never fatal."""
        self.frames += 1
        try:
            if kind == Y:
                self._y(frame)
            elif kind == TICK:
                self._tick(frame)
            elif kind == STATUS:
                self._status(frame)
            elif kind == EVENT:
                self._event(frame)
            elif kind == VECTOR:
                self._vector(frame)
            elif kind == TELEMETRY:
                self._telemetry(frame)
            else:
                raise RecordingError(f"unknown frame kind {kind}")
        except (HilswarmError, ValueError, struct.error, IndexError) as exc:
            self.errors += 1
            logger.error("record stream: frame of kind %d not recorded: %s", kind, exc)

    def _y(self, frame: bytes) -> None:
        _, _, i, log_ns, n_payload = _Y_HEAD.unpack_from(frame)
        start = _Y_HEAD.size
        payload = frame[start : start + n_payload]
        k, t, values = bus.unpack_vector(payload)
        timing, u, x_hat = bus.unpack_report(frame[start + n_payload :])
        self._timings[i] = (k, timing)
        recorder = self.recorder
        topic = self._y_topics[i]
        if i in self._plain_y:
            self._plain_vector(topic, k, t, values, log_ns)
        else:
            try:
                recorder.write_floats(topic, k=k, t=t, values=values, log_time_ns=log_ns)
            except RecordingError:  # y does not match the vehicle's output names
                logger.warning("%s: %d values, not its named outputs: recorded plain", topic,
                               len(values))  # fmt: skip
                self._plain_y.add(i)
                self._plain_vector(topic, k, t, values, log_ns)
        if u:
            t_u = t - self.dt
            recorder.write_floats(self._u_topics[i], k=k, t=t_u, values=u, log_time_ns=log_ns)
            if x_hat:
                recorder.write_floats(
                    self._x_topics[i], k=k, t=t_u, values=x_hat, log_time_ns=log_ns
                )

    def _plain_vector(
        self, topic: str, k: int, t: float, values: Sequence[float], log_ns: int
    ) -> None:
        message = {"k": k, "t": t, "values": list(values)}
        self.recorder.write_message(topic, message, log_time_ns=log_ns)

    def _tick(self, frame: bytes) -> None:
        (_, _, k, log_ns, scheduled, send_delay, completion, n_late, n_missing) = (
            _TICK_HEAD.unpack_from(frame)
        )
        offset = _TICK_HEAD.size
        indices = struct.unpack_from(f"<{n_late + n_missing}H", frame, offset)
        offset += 2 * (n_late + n_missing)
        n = len(self.names)
        answers = struct.unpack_from(f"<{n}d", frame, offset)
        quoted = self._quoted
        late = ",".join(quoted[j] for j in indices[:n_late])
        missing = ",".join(quoted[j] for j in indices[n_late:])
        agents = []
        for i, answer in enumerate(answers):
            if math.isnan(answer):
                continue
            entry = self._timings[i]
            if entry is not None and entry[0] == k:
                timing = entry[1]
                sense, compute, actuate, skipped = (
                    timing.sense_s, timing.compute_s, timing.actuate_s, timing.skipped
                )  # fmt: skip
            else:
                sense = compute = actuate = math.nan
                skipped = 0
            agents.append(
                f'{quoted[i]}:{{"answer_s":{json_number(answer)},"sense_s":{json_number(sense)},'
                f'"compute_s":{json_number(compute)},"actuate_s":{json_number(actuate)},'
                f'"skipped":{int(skipped)}}}'
            )
        text = (
            f'{{"k":{k},"t":{json_number(k * self.dt)},"values":[],'
            f'"scheduled_s":{json_number(scheduled)},"send_delay_s":{json_number(send_delay)},'
            f'"completion_s":{json_number(completion)},"late":[{late}],"missing":[{missing}],'
            f'"agents":{{{",".join(agents)}}}}}'
        )
        schema = None if self._ticks_registered else TICKS_SCHEMA
        self.recorder.write_encoded(TICKS_TOPIC, text.encode(), log_time_ns=log_ns, schema=schema)
        self._ticks_registered = True

    def _status(self, frame: bytes) -> None:
        _, _, i, log_ns = _AGENT_HEAD.unpack_from(frame)
        message = bus.decode_json(frame[_AGENT_HEAD.size :])
        detail = str(message.get("detail", ""))
        if message.get("kind") == "set":
            detail = f"{detail} (ok={message.get('ok')})"
        self.recorder.write_status(
            self.names[i],
            state=str(message.get("state", "")),
            k=int(message.get("k", 0)),
            t=float(message.get("t", 0.0)),
            log_time_ns=log_ns,
            detail=detail,
        )

    def _event(self, frame: bytes) -> None:
        _, _, log_ns = _EVENT_HEAD.unpack_from(frame)
        message: dict[str, Any] = json.loads(frame[_EVENT_HEAD.size :])
        self.recorder.write_status(
            str(message["agent"]),
            state=str(message["state"]),
            k=int(message["k"]),
            t=float(message["t"]),
            log_time_ns=log_ns,
            detail=str(message.get("detail", "")),
        )

    def _vector(self, frame: bytes) -> None:
        _, _, i, log_ns, n_leaf = _VECTOR_HEAD.unpack_from(frame)
        start = _VECTOR_HEAD.size
        leaf = frame[start : start + n_leaf].decode()
        k, t, values = bus.unpack_vector(frame[start + n_leaf :])
        self.recorder.write_floats(
            f"/{self.names[i]}/{leaf}", k=k, t=t, values=values, log_time_ns=log_ns
        )

    def _telemetry(self, frame: bytes) -> None:
        _, _, i, log_ns = _AGENT_HEAD.unpack_from(frame)
        agent = self.names[i]
        for rows in bus.decode_telemetry_batch(frame[_AGENT_HEAD.size :]):
            topic = telemetry_topic(agent, rows.channel)
            fields = self._telemetry_fields(topic, rows.fields)
            k_list, t_list, value_rows = rows.k.tolist(), rows.t.tolist(), rows.values.tolist()
            if fields is None:
                for k, t, values in zip(k_list, t_list, value_rows, strict=True):
                    self._plain_vector(topic, k, t, values, log_ns)
            else:
                write = self.recorder.write_floats
                for k, t, values in zip(k_list, t_list, value_rows, strict=True):
                    write(topic, k=k, t=t, values=values, log_time_ns=log_ns)
            self.telemetry_rows += len(k_list)

    def _telemetry_fields(self, topic: str, fields: tuple[str, ...]) -> tuple[str, ...] | None:
        """Register ``topic`` with ``fields`` on first sight; ``None``: record it plain."""
        if topic not in self._telemetry_topics:
            registered: tuple[str, ...] | None = fields
            try:
                self.recorder.add_topic(topic, fields=fields)
            except RecordingError as exc:  # a field called "k", or a clash: plain values
                logger.warning("%s without field names: %s", topic, exc)
                registered = None
            self._telemetry_topics[topic] = registered
        known = self._telemetry_topics[topic]
        if known is not None and known != fields:
            raise RecordingError(f"{topic}: fields changed from {known} to {fields} in the run")
        return known

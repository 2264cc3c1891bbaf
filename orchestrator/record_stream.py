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
* ``LATE`` — ``uint16 agent``, ``int64 k``, ``int64 log time [ns]``, ``float64 answer_s``: an
  agent's ``y_k`` that came after tick ``k`` was closed without it (its answer time after the
  tick's send [s]); follows that ``y``'s own ``Y`` frame. Recorded on ``/orchestrator/late``
  with the ledger fields of its report.
* ``GATEWAY`` — ``int64 log time [ns]``, ``uint16 leaf length``, the key leaf (``stats``,
  ``status``), the XBee gateway's JSON as sent (with ``k``, ``t``, ``values``); recorded on
  ``/gateway/<leaf>``.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, Protocol

import numpy as np
from hilswarm.agents import bus
from hilswarm.agents.errors import HilswarmError, RecordingError
from hilswarm.agents.telemetry import telemetry_topic
from hilswarm.orchestrator import pose_topic
from hilswarm.orchestrator.experiment import Experiment
from hilswarm.orchestrator.recorder import (
    LATE_SCHEMA,
    LATE_TOPIC,
    TICKS_SCHEMA,
    TICKS_TOPIC,
    Recorder,
)

logger = logging.getLogger(__name__)

Y, TICK, STATUS, EVENT, VECTOR, TELEMETRY, GATEWAY, LATE = 1, 2, 3, 4, 5, 6, 7, 8

_HEAD = struct.Struct("<BI")
_Y_HEAD = struct.Struct("<BIHqI")
_TICK_HEAD = struct.Struct("<BIqqdddHH")
_AGENT_HEAD = struct.Struct("<BIHq")
_EVENT_HEAD = struct.Struct("<BIq")
_VECTOR_HEAD = struct.Struct("<BIHqH")
_GATEWAY_HEAD = struct.Struct("<BIqH")
_LATE_FRAME = struct.Struct("<BIHqqd")
#: Layouts of the bus payloads a Y frame carries, unpacked in place by the recorder: the head
#: of :func:`~hilswarm.agents.bus.encode_vector` (k, t) and of
#: :func:`~hilswarm.agents.bus.encode_report` (compute_s, actuate_s, sense_s, link_s, skipped,
#: retries, n_u, n_x; after u and x_hat, for a link through the XBee gateway, the 2 float64
#: gateway_s, radio_s).
_VECTOR = struct.Struct("<qd")
_REPORT = struct.Struct("<ddddHHHH")
_STAGES_SIZE = 16
#: The timing of a y frame without a report.
_NO_TIMING = (0.0, 0.0, 0.0, 0.0, 0, 0)
_FLOATS: dict[int, struct.Struct] = {}
#: Y frame layouts a FrameRecorder remembers (one per frame length).
_Y_LAYOUTS = 256
#: Tick reports an agent may have ahead of (or left behind) the ticks accounted, before the
#: older ones are dropped.
_TIMINGS_KEPT = 64


def _floats(n: int) -> struct.Struct:
    """A cached ``struct.Struct`` of ``n`` little-endian float64."""
    layout = _FLOATS.get(n)
    if layout is None:
        layout = _FLOATS[n] = struct.Struct(f"<{n}d")
    return layout


#: An agent's entry in the tick ledger (``/orchestrator/ticks`` "agents", ``/orchestrator/late``)
#: [s], in the order of :func:`ledger_times`; then ``skipped`` and ``retries`` (counts).
LEDGER_FIELDS = ("answer_s", "bus_s", "compute_s", "actuate_s", "link_s", "sense_s")
#: The entry's gateway stages, after :data:`LEDGER_FIELDS`, for a link through the XBee gateway.
GATEWAY_LEDGER_FIELDS = ("gateway_bus_s", "gateway_s", "radio_s")


def ledger_times(
    answer: float, timing: tuple[Any, ...] | None
) -> tuple[tuple[float, ...], int, int]:
    """An answer's ledger times [s] (:data:`LEDGER_FIELDS`, then :data:`GATEWAY_LEDGER_FIELDS`
    when its report has the gateway stages), skipped ticks and link retries, from its answer
    time after the tick's send [s] and its report's timing (``None``: no report, NaN times)."""
    if timing is None:
        return (answer, math.nan, math.nan, math.nan, math.nan, math.nan), 0, 0
    compute, actuate, sense, link, skipped, retries = timing[:6]
    # the rest of the answer time: bus delivery both ways (and, in lockstep, the wait for the
    # neighbours' outputs)
    times = (answer, answer - (compute + actuate + sense + link), compute, actuate, link, sense)
    if len(timing) > 6:  # through the XBee gateway: the link's bus hops, the gateway, the radio
        gateway, radio = timing[6:8]
        times += (link - gateway - radio, gateway, radio)
    return times, int(skipped), int(retries)


#: Agent index of events that concern the orchestrator itself (``/orchestrator/status``).
ORCHESTRATOR = "orchestrator"


class RecordSink(Protocol):
    """Where the manager's frames go (the recorder process's pipe, or a recorder in-process)."""

    def write(self, data: bytes, *, count: int = 0, tick: int = -1, first_tick: int = -1) -> None:
        """Take a batch of whole frames (``count`` of them, made at the manager's ``tick``, of
        ticks from ``first_tick`` on, the manager's tick when it began gathering them; -1:
        unknown)."""


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


def late_frame(agent: int, k: int, log_time_ns: int, answer_s: float) -> bytes:
    """Frame of an answer (``y_k`` of ``agent``) that came after tick ``k`` closed without
    it, ``answer_s`` [s] after the tick's send."""
    size = _LATE_FRAME.size - _HEAD.size
    return _LATE_FRAME.pack(LATE, size, agent, k, log_time_ns, answer_s)


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


def gateway_frame(log_time_ns: int, leaf: str, payload: bytes) -> bytes:
    """Frame of an XBee gateway message (``gateway/<leaf>``, JSON as sent)."""
    name = leaf.encode()
    size = _GATEWAY_HEAD.size - _HEAD.size + len(name) + len(payload)
    return _GATEWAY_HEAD.pack(GATEWAY, size, log_time_ns, len(name)) + name + payload


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
        # Per agent, its part of /orchestrator/ticks "agents" with "%" holes for the numbers;
        # with the gateway stages for a tick whose report has them (an xbee:// link).
        times = ",".join(f'"{field}":%s' for field in LEDGER_FIELDS)
        gateway = ",".join(f'"{field}":%s' for field in GATEWAY_LEDGER_FIELDS)
        self._agent_templates = [
            quoted.replace("%", "%%") + f':{{{times},"skipped":%d,"retries":%d}}'
            for quoted in self._quoted
        ]
        self._gateway_templates = [
            template[:-1] + f",{gateway}}}" for template in self._agent_templates
        ]
        self._y_topics = [f"/{name}/y" for name in self.names]
        self._u_topics = [f"/{name}/u" for name in self.names]
        self._x_topics = [f"/{name}/x_hat" for name in self.names]
        # Per agent, k -> (compute_s, actuate_s, sense_s, link_s, skipped, retries[, gateway_s,
        # radio_s]) of its y_k not yet in a tick's ledger (in lockstep an agent's y_{k+1} can
        # come before tick k is complete).
        self._timings: list[dict[int, tuple[Any, ...]]] = [{} for _ in self.names]
        self._ticks_registered = False
        self._late_registered = False
        self._wall = recorder.experiment_clock  # /orchestrator/ticks carries wall_ns
        self._plain_y: set[int] = set()
        # Topics whose field names did not match the values (recorded plain from then on).
        self._plain_topics: set[str] = set()
        # Per frame length, the layout of the last Y frame of that length: (struct, n_y, n_u,
        # n_x, n_g), n_u = n_x = -1 for a frame without a report, n_g = 2 with gateway stages.
        self._y_layouts: dict[int, tuple[struct.Struct, int, int, int, int]] = {}
        # Per agent, the number of field names of its y topic (None: no names), once known.
        self._y_width: dict[int, int | None] = {}
        # The same for the u and x_hat topics, by topic.
        self._topic_widths: dict[str, int | None] = {}
        # Vector messages (topic, k, t, values, log time) not yet handed to the recorder.
        self._rows: list[tuple[str, int, float, Sequence[float], int]] = []
        # Telemetry topics seen: topic -> field names it was registered with (None: plain).
        self._telemetry_topics: dict[str, tuple[str, ...] | None] = {}
        self.telemetry_rows = 0
        self.frames = 0
        self.errors = 0

    def write(self, data: bytes, *, count: int = 0, tick: int = -1, first_tick: int = -1) -> None:
        """:class:`RecordSink` interface: decode and record a batch of whole frames."""
        del count, tick, first_tick  # written here and now: nothing to account for
        reader = FrameReader()
        self.apply_all(reader.feed(data))
        if reader.pending:
            raise RecordingError(f"record stream: {reader.pending} bytes of a cut frame")

    def apply(self, kind: int, frame: bytes) -> None:
        """Record one frame; a bad frame is logged and counted, never fatal."""
        self.apply_all(((kind, frame),))

    def apply_all(self, frames: Iterable[tuple[int, bytes]]) -> None:
        """Record frames in order; a bad frame is logged and counted, never fatal.

        The vector messages of consecutive ``Y`` and telemetry frames are handed to the
        recorder together (one call, one lock), before any other message, so the file holds
        the messages in frame order.
        """
        rows = self._rows
        for kind, frame in frames:
            self.frames += 1
            try:
                if kind == Y:
                    self._y(frame, rows)
                    continue
                if kind == TELEMETRY:
                    self._telemetry(frame, rows)
                    continue
                if rows:
                    self._flush_rows()
                if kind == TICK:
                    self._tick(frame)
                elif kind == STATUS:
                    self._status(frame)
                elif kind == EVENT:
                    self._event(frame)
                elif kind == VECTOR:
                    self._vector(frame)
                elif kind == GATEWAY:
                    self._gateway(frame)
                elif kind == LATE:
                    self._late(frame)
                else:
                    raise RecordingError(f"unknown frame kind {kind}")
            except (HilswarmError, ValueError, struct.error, IndexError) as exc:
                self.errors += 1
                logger.error("record stream: frame of kind %d not recorded: %s", kind, exc)
        if rows:
            self._flush_rows()

    def _flush_rows(self) -> None:
        """Write the vector messages gathered from frames so far (a refused one is skipped)."""
        rows, recorder = self._rows, self.recorder
        start = 0
        while start < len(rows):  # each pass writes or skips at least one message
            before = recorder.message_count
            try:
                recorder.write_floats_many(rows[start:] if start else rows)
                break
            except (HilswarmError, ValueError, struct.error) as exc:
                start += recorder.message_count - before
                self.errors += 1
                logger.error("record stream: %s not recorded: %s", rows[start][0], exc)
                start += 1
        rows.clear()

    def _y_fields_match(self, i: int, n_values: int) -> bool:
        """True if agent ``i``'s ``y`` of ``n_values`` entries is written with field names."""
        width = self._y_width.get(i, -1)
        if width == -1:
            fields = self.recorder.topic_fields(self._y_topics[i])
            width = self._y_width[i] = None if fields is None else len(fields)
        if width is None or width == n_values:
            return True
        # y does not match the vehicle's output names: plain from now on
        logger.warning("%s: %d values, not its named outputs: recorded plain",
                       self._y_topics[i], n_values)  # fmt: skip
        self._plain_y.add(i)
        return False

    def _y(self, frame: bytes, rows: list[tuple[str, int, float, Sequence[float], int]]) -> None:
        i, log_ns, k, t, values, timing, u, x_hat = self._unpack_y(frame)
        self._timings[i][k] = timing
        if i not in self._plain_y and self._y_fields_match(i, len(values)):
            rows.append((self._y_topics[i], k, t, values, log_ns))
        else:
            if rows:
                self._flush_rows()
            self._plain_vector(self._y_topics[i], k, t, values, log_ns)
        if u:
            t_u = t - self.dt
            self._signal_row(rows, (self._u_topics[i], k, t_u, u, log_ns))
            if x_hat:
                self._signal_row(rows, (self._x_topics[i], k, t_u, x_hat, log_ns))

    def _signal_row(
        self,
        rows: list[tuple[str, int, float, Sequence[float], int]],
        row: tuple[str, int, float, Sequence[float], int],
    ) -> None:
        """Queue ``u``/``x_hat``; one whose size does not match its names is recorded plain."""
        topic, k, t, values, log_ns = row
        if topic not in self._plain_topics:
            fields = self._topic_widths.get(topic, -1)
            if fields == -1:
                names = self.recorder.topic_fields(topic)
                fields = self._topic_widths[topic] = None if names is None else len(names)
            if fields is None or fields == len(values):
                rows.append(row)
                return
            logger.warning("%s: %d values, not its %d named entries: recorded plain",
                           topic, len(values), fields)  # fmt: skip
            self._plain_topics.add(topic)
        if rows:
            self._flush_rows()
        self._plain_vector(topic, k, t, values, log_ns)

    def _unpack_y(self, frame: bytes) -> tuple[Any, ...]:
        """The numbers of a Y frame: agent, log time [ns], k, t [s], y, the timing
        ``(compute_s, actuate_s, sense_s, link_s, skipped, retries)`` (followed by ``gateway_s,
        radio_s`` when the report has them), u, x_hat (the vectors as tuples of floats).

        Frames of one length almost always have one layout (an agent's y, u and x_hat keep
        their sizes): all numbers are unpacked at once with the layout last seen for the
        length, after checking that the sizes the frame states are the ones it assumes.
        """
        cached = self._y_layouts.get(len(frame))
        if cached is not None:
            layout, n_y, n_u, n_x, n_g = cached
            numbers = layout.unpack_from(frame)
            end_y = 7 + n_y
            if numbers[4] == _VECTOR.size + 8 * n_y:
                if n_u < 0:  # no report
                    return (*numbers[2:4], *numbers[5:7], numbers[7:], _NO_TIMING, (), ())
                if numbers[end_y + 6] == n_u and numbers[end_y + 7] == n_x:
                    u_end = end_y + 8 + n_u
                    if n_g:
                        x_end = u_end + n_x
                        return (
                            numbers[2], numbers[3], numbers[5], numbers[6], numbers[7:end_y],
                            numbers[end_y : end_y + 6] + numbers[x_end:],
                            numbers[end_y + 8 : u_end], numbers[u_end:x_end],
                        )  # fmt: skip
                    return (
                        numbers[2], numbers[3], numbers[5], numbers[6], numbers[7:end_y],
                        numbers[end_y : end_y + 6], numbers[end_y + 8 : u_end], numbers[u_end:],
                    )  # fmt: skip
        _, _, i, log_ns, n_payload = _Y_HEAD.unpack_from(frame)
        start = _Y_HEAD.size
        n_y, odd = divmod(n_payload - _VECTOR.size, 8)
        if n_y < 0 or odd or start + n_payload > len(frame):
            raise RecordingError(f"y payload of {n_payload} bytes: expected 16 + 8 per value")
        k, t = _VECTOR.unpack_from(frame, start)
        values = _floats(n_y).unpack_from(frame, start + _VECTOR.size)
        # The tick report (bus.encode_report), unpacked here: no objects per frame.
        report = start + n_payload
        size = len(frame) - report
        if size:
            if size < _REPORT.size:
                raise RecordingError(f"tick report of {size} bytes, expected >= {_REPORT.size}")
            *timing, n_u, n_x = _REPORT.unpack_from(frame, report)
            n_g = 2 if size == _REPORT.size + 8 * (n_u + n_x) + _STAGES_SIZE else 0
            if size != _REPORT.size + 8 * (n_u + n_x + n_g):
                raise RecordingError(f"tick report of {size} bytes does not hold {n_u} + {n_x}")
            report += _REPORT.size
            u = _floats(n_u).unpack_from(frame, report)
            x_hat = _floats(n_x).unpack_from(frame, report + 8 * n_u)
            if n_g:  # gateway_s, radio_s
                timing += _floats(2).unpack_from(frame, report + 8 * (n_u + n_x))
            layout = f"<BIHqIqd{n_y}dddddHHHH{n_u}d{n_x}d{n_g}d"
        else:
            timing = _NO_TIMING
            u = x_hat = ()
            n_u = n_x = -1
            n_g = 0
            layout = f"<BIHqIqd{n_y}d"
        if len(self._y_layouts) < _Y_LAYOUTS:
            self._y_layouts[len(frame)] = (struct.Struct(layout), n_y, n_u, n_x, n_g)
        return i, log_ns, k, t, values, tuple(timing), u, x_hat

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
        answers = _floats(n).unpack_from(frame, offset)
        quoted = self._quoted
        late = ",".join(quoted[j] for j in indices[:n_late])
        missing = ",".join(quoted[j] for j in indices[n_late:])
        # Every number of the message, formatted at once; non-finite ones become null.
        numbers: list[float] = [k * self.dt, scheduled, send_delay, completion]
        templates, gateways = self._agent_templates, self._gateway_templates
        answered: list[tuple[str, int, int, int, int]] = []  # template, numbers, counts
        timings = self._timings
        for i, answer in enumerate(answers):
            kept = timings[i]
            timing = kept.pop(k, None)
            if len(kept) > _TIMINGS_KEPT:  # of ticks never accounted (no answer in time)
                for old in [j for j in kept if j < k]:
                    del kept[old]
            if math.isnan(answer):  # no answer
                continue
            start = len(numbers)
            times, skipped, retries = ledger_times(answer, timing)
            numbers += times
            template = templates[i] if len(times) == len(LEDGER_FIELDS) else gateways[i]
            answered.append((template, start, len(times), skipped, retries))
        texts = list(map(float.__repr__, numbers))
        if "n" in "".join(texts):
            texts = ["null" if "n" in text else text for text in texts]
        agents = ",".join(
            [
                template
                % (*texts[start : start + 6], skipped, retries, *texts[start + 6 : start + n])
                for template, start, n, skipped, retries in answered
            ]
        )
        wall = f'"wall_ns":{log_ns},' if self._wall else ""
        text = (
            f'{{"k":{k},"t":{texts[0]},{wall}"values":[],'
            f'"scheduled_s":{texts[1]},"send_delay_s":{texts[2]},'
            f'"completion_s":{texts[3]},"late":[{late}],"missing":[{missing}],'
            f'"agents":{{{agents}}}}}'
        )
        schema = None if self._ticks_registered else TICKS_SCHEMA
        self.recorder.write_encoded(
            TICKS_TOPIC, text.encode(), log_time_ns=log_ns, schema=schema, t=k * self.dt
        )
        self._ticks_registered = True

    def _late(self, frame: bytes) -> None:
        _, _, i, k, log_ns, answer = _LATE_FRAME.unpack_from(frame)
        times, skipped, retries = ledger_times(answer, self._timings[i].pop(k, None))
        fields = LEDGER_FIELDS + GATEWAY_LEDGER_FIELDS
        message: dict[str, Any] = {"k": k, "t": k * self.dt, "values": [], "agent": self.names[i]}
        if self._wall:
            message["wall_ns"] = log_ns
        message.update(
            (field, value if math.isfinite(value) else None)
            for field, value in zip(fields, times, strict=False)
        )
        message.update(skipped=skipped, retries=retries)
        schema = None if self._late_registered else LATE_SCHEMA
        self.recorder.write_encoded(
            LATE_TOPIC,
            json.dumps(message).encode(),
            log_time_ns=log_ns,
            schema=schema,
            t=k * self.dt,
        )
        self._late_registered = True

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
            counters={f: message[f] for f in bus.STATUS_COUNTER_FIELDS if f in message},
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

    def _gateway(self, frame: bytes) -> None:
        _, _, log_ns, n_leaf = _GATEWAY_HEAD.unpack_from(frame)
        start = _GATEWAY_HEAD.size
        leaf = frame[start : start + n_leaf].decode()
        message = bus.decode_json(frame[start + n_leaf :])
        message.setdefault("k", 0)
        message.setdefault("t", 0.0)
        message.setdefault("values", [])
        self.recorder.write_message(f"/gateway/{leaf}", message, log_time_ns=log_ns)

    def _telemetry(
        self, frame: bytes, rows: list[tuple[str, int, float, Sequence[float], int]]
    ) -> None:
        _, _, i, log_ns = _AGENT_HEAD.unpack_from(frame)
        agent = self.names[i]
        for channel in bus.decode_telemetry_batch(frame[_AGENT_HEAD.size :]):
            topic = telemetry_topic(agent, channel.channel)
            fields = self._telemetry_fields(topic, channel.fields)
            k_list = channel.k.tolist()
            t_list = channel.t.tolist()
            value_rows = channel.values.tolist()
            if fields is None:
                if rows:
                    self._flush_rows()
                for k, t, values in zip(k_list, t_list, value_rows, strict=True):
                    self._plain_vector(topic, k, t, values, log_ns)
            else:
                rows += [
                    (topic, k, t, values, log_ns)
                    for k, t, values in zip(k_list, t_list, value_rows, strict=True)
                ]
            self.telemetry_rows += len(k_list)
            if pose_topic.is_pose_channel(channel.channel, channel.fields):
                self._poses(agent, zip(k_list, t_list, value_rows, strict=True), log_ns, rows)

    def _poses(
        self,
        agent: str,
        samples: Iterable[tuple[int, float, Sequence[float]]],
        log_ns: int,
        rows: list[tuple[str, int, float, Sequence[float], int]],
    ) -> None:
        """``/<agent>/pose`` (foxglove.PoseInFrame) from the agent's mocap rows."""
        if rows:
            self._flush_rows()
        topic = pose_topic.pose_topic(agent)
        for k, t, values in samples:
            message = pose_topic.pose_message(k, t, values, log_ns)
            if message is None:
                continue
            if self._wall:
                message["wall_ns"] = log_ns
            self.recorder.write_encoded(
                topic,
                json.dumps(message).encode(),
                log_time_ns=log_ns,
                schema=pose_topic.POSE_IN_FRAME_SCHEMA,
                t=t,
            )

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

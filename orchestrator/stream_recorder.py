"""The recorder's side of the record stream: MCAP records of the manager in, the run's topics out.

:class:`StreamRecorder` reads the record stream (:mod:`hilswarm.orchestrator.record_stream`: an
MCAP stream of the bus messages as the manager kept them) and writes the topics of
``docs/recording.md`` on a :class:`~hilswarm.orchestrator.recorder.Recorder`: ``/<agent>/y``,
``/<agent>/u`` and ``/<agent>/x_hat`` from one ``y`` message, the per-agent ledger of
``/orchestrator/ticks`` from the reports of that tick, statuses, telemetry, poses. It does all
the per-message work (decoding, JSON), in the recorder process, off the manager's tick.

It applies whole batches only (up to a batch marker; the rest waits for the next bytes), so
what it has written and flushed is exactly the batches it acknowledges: a restarted recorder
sent the unacknowledged batches again neither loses nor repeats a message.
"""

from __future__ import annotations

import io
import json
import logging
import math
import struct
from collections.abc import Iterable, Sequence
from typing import Any

from hilswarm.agents import bus
from hilswarm.agents.errors import HilswarmError, RecordingError
from hilswarm.agents.telemetry import telemetry_topic
from hilswarm.orchestrator import pose_topic
from hilswarm.orchestrator.experiment import Experiment
from hilswarm.orchestrator.record_stream import (
    BATCH,
    BATCH_SEQ,
    EVENT,
    GATEWAY,
    LATE,
    LATE_LAYOUT,
    MAGIC,
    MESSAGE,
    OP_CHANNEL,
    OP_HEADER,
    OP_MESSAGE,
    PROFILE,
    STATUS,
    TELEMETRY,
    TICK,
    TICK_HEAD,
    VECTOR,
    Y_HEAD,
    Y,
    records,
)
from hilswarm.orchestrator.recorder import (
    LATE_SCHEMA,
    LATE_TOPIC,
    TICKS_SCHEMA,
    TICKS_TOPIC,
    Recorder,
)
from mcap.data_stream import ReadDataStream
from mcap.records import Channel as ChannelRecord
from mcap.records import Header as HeaderRecord

logger = logging.getLogger(__name__)

#: Layouts of the bus payloads a ``y`` message carries, unpacked in place: the head of
#: :func:`~hilswarm.agents.bus.encode_vector` (k, t) and of
#: :func:`~hilswarm.agents.bus.encode_report` (compute_s, actuate_s, sense_s, link_s, skipped,
#: retries, n_u, n_x; after u and x_hat, for a link through the XBee gateway, the 2 float64
#: gateway_s, radio_s).
_VECTOR = struct.Struct("<qd")
_REPORT = struct.Struct("<ddddHHHH")
_STAGES_SIZE = 16
#: The timing of a y without a report.
_NO_TIMING = (0.0, 0.0, 0.0, 0.0, 0, 0)
_FLOATS: dict[int, struct.Struct] = {}
#: y layouts a StreamRecorder remembers (one per message length).
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


#: Vector messages to write: topic, k, t [s], values, log time [ns].
_Rows = list[tuple[str, int, float, Sequence[float], int]]
#: A channel's route: kind, agent index (-1: none), key leaf ("" : none).
_Route = tuple[str, int, str]
#: A record read: opcode, body start, body end, a message's head (None: not a message).
_Parsed = tuple[int, int, int, tuple[int, int, int, int] | None]


class StreamRecorder:
    """Turns the record stream into MCAP messages on ``recorder`` (the topics of
    ``docs/recording.md``). Also a :class:`~hilswarm.orchestrator.record_stream.RecordSink`,
    for a recorder in the manager's process.

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
        # Per message length, the layout of the last y of that length: (struct, n_y, n_u, n_x,
        # n_g), n_u = n_x = -1 for a y without a report, n_g = 2 with gateway stages.
        self._y_layouts: dict[int, tuple[struct.Struct, int, int, int, int]] = {}
        # Per agent, the number of field names of its y topic (None: no names), once known.
        self._y_width: dict[int, int | None] = {}
        # The same for the u and x_hat topics, by topic.
        self._topic_widths: dict[str, int | None] = {}
        # Vector messages (topic, k, t, values, log time) not yet handed to the recorder.
        self._rows: _Rows = []
        # Telemetry topics seen: topic -> field names it was registered with (None: plain).
        self._telemetry_topics: dict[str, tuple[str, ...] | None] = {}
        # The stream's channels: id -> route; the batch marker's channel id.
        self._routes: dict[int, _Route] = {}
        self._batch_channel = -1
        self._unknown_channels: set[int] = set()
        self._pending = b""
        self.telemetry_rows = 0
        self.messages = 0
        self.errors = 0

    # -- the stream -------------------------------------------------------------------------

    @property
    def pending(self) -> int:
        """Bytes held back: a batch not complete yet (or a cut record) [bytes]."""
        return len(self._pending)

    def write(
        self,
        data: bytes,
        *,
        seq: int = -1,
        count: int = 0,
        tick: int = -1,
        first_tick: int = -1,
        defines: bool = False,
    ) -> None:
        """:class:`RecordSink` interface: decode and record a batch of whole records."""
        del seq, count, tick, first_tick, defines  # written here and now
        self.feed(data, whole=True)
        if self._pending:
            raise RecordingError(f"record stream: {len(self._pending)} bytes of a cut record")

    def feed(self, data: bytes, *, whole: bool = False) -> int | None:
        """Record the whole batches in the bytes so far (all whole records with ``whole``,
        as at the end of the stream); returns the last batch's number (``None``: no batch
        ended)."""
        buffer = self._pending + data if self._pending else data
        parsed: list[_Parsed] = []
        through, last_seq, consumed = 0, None, 0
        unpack_message = MESSAGE.unpack_from
        for opcode, start, stop in records(buffer):
            head = None
            if opcode == OP_MESSAGE:
                head = unpack_message(buffer, start)
                if head[0] == self._batch_channel:
                    last_seq = BATCH_SEQ.unpack_from(buffer, start + MESSAGE.size)[0]
                    through, consumed = len(parsed) + 1, stop
            elif opcode == OP_CHANNEL:
                self._define(buffer[start:stop])
            elif opcode == OP_HEADER:
                self._check_header(buffer[start:stop])
            parsed.append((opcode, start, stop, head))
        if whole:
            through = len(parsed)
            consumed = parsed[-1][2] if parsed else 0
            if buffer[consumed:] == MAGIC:
                consumed = len(buffer)  # the closing magic
        self._pending = buffer[consumed:]
        self._apply(buffer, parsed[:through])
        return last_seq

    def _check_header(self, body: bytes) -> None:
        header = HeaderRecord.read(ReadDataStream(io.BytesIO(body)))
        if header.profile != PROFILE:
            raise RecordingError(f"not a record stream: MCAP profile {header.profile!r}")

    def _define(self, body: bytes) -> None:
        """A Channel record: where its messages go."""
        channel = ChannelRecord.read(ReadDataStream(io.BytesIO(body)))
        kind = channel.metadata.get("kind", "")
        agent = int(channel.metadata.get("agent", -1))
        parts = channel.topic.split("/", 2)
        if agent >= 0:
            if not 0 <= agent < len(self.names) or parts[1:2] != [self.names[agent]]:
                raise RecordingError(f"record stream: channel {channel.topic} of agent {agent}")
            leaf = parts[2] if len(parts) == 3 else ""
        else:
            leaf = channel.topic.split("/", 1)[1] if kind == GATEWAY else ""
        self._routes[channel.id] = (kind, agent, leaf)
        if kind == BATCH:
            self._batch_channel = channel.id

    def _apply(self, buffer: bytes, parsed: Iterable[_Parsed]) -> None:
        """Record the messages in order; a bad message is logged and counted, never fatal.

        The vector messages of consecutive ``y`` and telemetry messages are handed to the
        recorder together (one call, one lock), before any other message, so the file holds
        the messages in stream order.
        """
        rows, routes = self._rows, self._routes
        body = MESSAGE.size
        for _opcode, start, stop, head in parsed:
            if head is None:
                continue  # Header, Schema, Channel (read as they came), DataEnd, Footer
            route = routes.get(head[0])
            if route is None:
                self._unknown(head[0])
                continue
            kind, i, leaf = route
            if kind == BATCH:
                continue
            self.messages += 1
            log_ns = head[2]
            data = buffer[start + body : stop]
            try:
                if kind == Y:
                    self._y(i, log_ns, data, rows)
                    continue
                if kind == TELEMETRY:
                    self._telemetry(i, log_ns, data, rows)
                    continue
                if rows:
                    self._flush_rows()
                if kind == TICK:
                    self._tick(log_ns, data)
                elif kind == STATUS:
                    self._status(i, log_ns, data)
                elif kind == EVENT:
                    self._event(log_ns, data)
                elif kind == VECTOR:
                    self._vector(i, leaf, log_ns, data)
                elif kind == GATEWAY:
                    self._gateway(leaf, log_ns, data)
                elif kind == LATE:
                    self._late(i, log_ns, data)
                else:
                    raise RecordingError(f"unknown channel kind {kind!r}")
            except (HilswarmError, ValueError, struct.error, IndexError) as exc:
                self.errors += 1
                logger.error("record stream: a %s message not recorded: %s", kind, exc)
        if rows:
            self._flush_rows()

    def _unknown(self, channel_id: int) -> None:
        self.errors += 1
        if channel_id not in self._unknown_channels:
            self._unknown_channels.add(channel_id)
            logger.error("record stream: messages on channel %d, never defined", channel_id)

    # -- the topics -------------------------------------------------------------------------

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

    def _y(
        self,
        i: int,
        log_ns: int,
        data: bytes,
        rows: _Rows,
    ) -> None:
        k, t, values, timing, u, x_hat = self._unpack_y(data)
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
        rows: _Rows,
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

    def _unpack_y(self, data: bytes) -> tuple[Any, ...]:
        """The numbers of a ``y`` message: k, t [s], y, the timing ``(compute_s, actuate_s,
        sense_s, link_s, skipped, retries)`` (followed by ``gateway_s, radio_s`` when the report
        has them), u, x_hat (the vectors as tuples of floats).

        Messages of one length almost always have one layout (an agent's y, u and x_hat keep
        their sizes): all numbers are unpacked at once with the layout last seen for the
        length, after checking that the sizes the message states are the ones it assumes.
        """
        cached = self._y_layouts.get(len(data))
        if cached is not None:
            layout, n_y, n_u, n_x, n_g = cached
            numbers = layout.unpack_from(data)
            end_y = 3 + n_y
            if numbers[0] == _VECTOR.size + 8 * n_y:
                if n_u < 0:  # no report
                    return (numbers[1], numbers[2], numbers[3:], _NO_TIMING, (), ())
                if numbers[end_y + 6] == n_u and numbers[end_y + 7] == n_x:
                    u_end = end_y + 8 + n_u
                    if n_g:
                        x_end = u_end + n_x
                        return (
                            numbers[1], numbers[2], numbers[3:end_y],
                            numbers[end_y : end_y + 6] + numbers[x_end:],
                            numbers[end_y + 8 : u_end], numbers[u_end:x_end],
                        )  # fmt: skip
                    return (
                        numbers[1], numbers[2], numbers[3:end_y],
                        numbers[end_y : end_y + 6], numbers[end_y + 8 : u_end], numbers[u_end:],
                    )  # fmt: skip
        (n_payload,) = Y_HEAD.unpack_from(data)
        start = Y_HEAD.size
        n_y, odd = divmod(n_payload - _VECTOR.size, 8)
        if n_y < 0 or odd or start + n_payload > len(data):
            raise RecordingError(f"y payload of {n_payload} bytes: expected 16 + 8 per value")
        k, t = _VECTOR.unpack_from(data, start)
        values = _floats(n_y).unpack_from(data, start + _VECTOR.size)
        # The tick report (bus.encode_report), unpacked here: no objects per message.
        report = start + n_payload
        size = len(data) - report
        if size:
            if size < _REPORT.size:
                raise RecordingError(f"tick report of {size} bytes, expected >= {_REPORT.size}")
            *timing, n_u, n_x = _REPORT.unpack_from(data, report)
            n_g = 2 if size == _REPORT.size + 8 * (n_u + n_x) + _STAGES_SIZE else 0
            if size != _REPORT.size + 8 * (n_u + n_x + n_g):
                raise RecordingError(f"tick report of {size} bytes does not hold {n_u} + {n_x}")
            report += _REPORT.size
            u = _floats(n_u).unpack_from(data, report)
            x_hat = _floats(n_x).unpack_from(data, report + 8 * n_u)
            if n_g:  # gateway_s, radio_s
                timing += _floats(2).unpack_from(data, report + 8 * (n_u + n_x))
            layout = f"<Iqd{n_y}dddddHHHH{n_u}d{n_x}d{n_g}d"
        else:
            timing = _NO_TIMING
            u = x_hat = ()
            n_u = n_x = -1
            n_g = 0
            layout = f"<Iqd{n_y}d"
        if len(self._y_layouts) < _Y_LAYOUTS:
            self._y_layouts[len(data)] = (struct.Struct(layout), n_y, n_u, n_x, n_g)
        return k, t, values, tuple(timing), u, x_hat

    def _plain_vector(
        self, topic: str, k: int, t: float, values: Sequence[float], log_ns: int
    ) -> None:
        message = {"k": k, "t": t, "values": list(values)}
        self.recorder.write_message(topic, message, log_time_ns=log_ns)

    def _tick(self, log_ns: int, data: bytes) -> None:
        k, scheduled, send_delay, completion, n_late, n_missing = TICK_HEAD.unpack_from(data)
        offset = TICK_HEAD.size
        indices = struct.unpack_from(f"<{n_late + n_missing}H", data, offset)
        offset += 2 * (n_late + n_missing)
        n = len(self.names)
        answers = _floats(n).unpack_from(data, offset)
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

    def _late(self, i: int, log_ns: int, data: bytes) -> None:
        k, answer = LATE_LAYOUT.unpack_from(data)
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

    def _status(self, i: int, log_ns: int, data: bytes) -> None:
        message = bus.decode_json(data)
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

    def _event(self, log_ns: int, data: bytes) -> None:
        message: dict[str, Any] = json.loads(data)
        self.recorder.write_status(
            str(message["agent"]),
            state=str(message["state"]),
            k=int(message["k"]),
            t=float(message["t"]),
            log_time_ns=log_ns,
            detail=str(message.get("detail", "")),
        )

    def _vector(self, i: int, leaf: str, log_ns: int, data: bytes) -> None:
        k, t, values = bus.unpack_vector(data)
        self.recorder.write_floats(
            f"/{self.names[i]}/{leaf}", k=k, t=t, values=values, log_time_ns=log_ns
        )

    def _gateway(self, leaf: str, log_ns: int, data: bytes) -> None:
        message = bus.decode_json(data)
        message.setdefault("k", 0)
        message.setdefault("t", 0.0)
        message.setdefault("values", [])
        self.recorder.write_message(f"/gateway/{leaf}", message, log_time_ns=log_ns)

    def _telemetry(
        self,
        i: int,
        log_ns: int,
        data: bytes,
        rows: _Rows,
    ) -> None:
        agent = self.names[i]
        for channel in bus.decode_telemetry_batch(data):
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
        rows: _Rows,
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

"""The Zenoh bus: key space, compact binary messages and session configurations.

Shared by agent processes and the orchestrator (this module imports nothing from
``hilswarm.orchestrator``).

Key space, one run of an experiment per prefix ``hilswarm/<exp>/<run_id>/`` (the run id is
made fresh by every ``hilswarm run``, so nothing of another run, even of the same experiment,
is ever consumed):

* ``tick`` — the instance manager's tick messages (:func:`encode_tick`), each releasing the
  ticks up to its ``k`` (:class:`TickMessage`), or, in a self-clocked realtime run, its
  schedules (:func:`encode_schedule`, :class:`ScheduleMessage`).
* ``control`` — swarm-wide commands (:class:`ControlCommand`: stop, estop, pause, resume),
  put by the instance manager only.
* ``manager/request`` — an operator's command (``hilswarm stop``), same layout as ``control``;
  the manager forwards it on ``control`` at once.
* ``manager/status`` — the manager's own state (JSON).
* ``agent/<name>/y`` — the agent's output y_k (:func:`encode_vector`), with its tick report
  (:func:`encode_report`: timings, u_k, x_hat_k) as attachment, so the manager and its
  recorder get everything of a tick in one message. Neighbours subscribe to this *explicit* key.
* ``agent/<name>/u``, ``agent/<name>/x_hat`` — applied input u_k and controller state, for
  other listeners (tools, dashboards); an agent publishes there only while someone subscribes.
* ``agent/<name>/status`` — lifecycle transitions and acknowledgements (JSON, rare).
* ``agent/<name>/set`` — a queryable: parameter changes, answered with an acknowledgement.
* ``agent/<name>/flush`` — answered by no one: the agent's last query before it closes its
  session (:func:`flush_barrier`), so its last messages have reached the router first.
* ``agent/<name>/telemetry`` — the vehicle's telemetry channels, in batches
  (:func:`encode_telemetry_batch`): the rows appended since the previous batch, every
  :data:`TELEMETRY_PERIOD_S` of wall time and once more when the agent goes safe or stops.
* ``agent/<name>/telemetry/<channel>`` — a single telemetry vector (:func:`encode_vector`),
  for tools that publish one; agents publish batches.
* ``agent/<name>/link/tx``, ``agent/<name>/link/rx`` — wire-protocol bytes between an agent
  with an ``xbee://`` link and the XBee gateway; ``agent/<name>/link/robot/{in,out}`` — the UART
  of its simulated robot behind the simulated air.
* ``gateway/status``, ``gateway/stats`` — the XBee gateway's state (JSON) and per-tick radio
  figures.
* ``alive/<name>`` — the agent's liveliness token (kill -9 is seen when it disappears).
* ``mocap/<body>`` — a rigid body's pose from the experiment's mocap process
  (:mod:`hilswarm.agents.mocap.message`); ``mocap_status`` — that process's status (JSON);
  ``mocap_truth/<body>`` — a simulated plant's true pose, for the mocap simulator only;
  ``mocap_clock`` — the frame clock (frame number and time per frame,
  :mod:`hilswarm.agents.mocap.frame_clock`) the manager locks the realtime ticks to.

Agents subscribe only to explicit keys, never wildcards, so a non-neighbour's output is never
delivered to them. The orchestrator's recorder may use wildcards.

Per-tick vectors use a fixed little-endian layout (no JSON on the hot path): ``k`` int64,
``t`` float64 [s, experiment time], then the values as float64. ``NaN`` is a valid value.

Configurations: the orchestrator opens a *router* session listening on loopback (a free port
it binds itself, read back with :func:`bound_endpoints`); agents are *clients* of it (a peer
mesh does not scale past a few dozen processes on two cores, a peer hub does not relay between
peers, and even peers linked to their graph neighbours only were slower than clients of the
router: docs/running.md, "Levers"). :func:`session_config` builds every configuration, in one
place: multicast scouting and gossip are off; the link lease is short (1 s) so that a hung
process is dropped quickly; :class:`SessionSecurity` adds Zenoh's user/password
authentication, TLS and the router's access control (see docs/security.md).

:data:`LEAN_RUNTIME` runs Zenoh's receiving side on one application worker thread and its
transmitting side on one more (the ``ZENOH_RUNTIME`` environment variable): a client then runs
5 threads instead of 9, with fewer thread switches per message. :func:`open_session` applies it
in every hilswarm process unless ``ZENOH_RUNTIME`` is already set (a user's own setting wins).
It needs bus callbacks that never block, which every hilswarm callback keeps to: they hand
their work to a thread (the agent's worker, the manager's ticking thread) or store a value.
"""

from __future__ import annotations

import base64
import enum
import json
import logging
import os
import re
import struct
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents.errors import HilswarmError

logger = logging.getLogger(__name__)

#: First chunk of every key.
KEY_ROOT = "hilswarm"
#: Link lease [ms]: a silent peer is dropped after this long.
LEASE_MS = 1000
#: Keep-alive messages sent per lease period.
KEEP_ALIVES_PER_LEASE = 4

#: Batches a link's transmission queue holds per priority on the tick path (Zenoh's default is
#: 2). Tick-path messages are *express* (each one its own batch), so with the default a router
#: forwarding a tick and two neighbours' outputs to one agent blocks until that agent's link
#: has written the first ones; under load such blocked routing cost more CPU than the routing.
TICK_PATH_QUEUE_BATCHES = 16

#: Zenoh QoS of everything on the tick path: reliable, never dropped, first in every queue.
TICK_PATH_QOS: dict[str, Any] = {
    "congestion_control": zenoh.CongestionControl.BLOCK,
    "priority": zenoh.Priority.REAL_TIME,
    "reliability": zenoh.Reliability.RELIABLE,
    "express": True,
}
#: QoS of recorded but non-critical data (u, x_hat, telemetry, status): reliable, blocking.
DATA_QOS: dict[str, Any] = {
    "congestion_control": zenoh.CongestionControl.BLOCK,
    "priority": zenoh.Priority.DATA_HIGH,
    "reliability": zenoh.Reliability.RELIABLE,
}

_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")


class BusConnectionError(HilswarmError, ConnectionError):
    """The bus session could not be opened (no router at the endpoint, refused credentials,
    port in use, ...)."""


class BusMessageError(HilswarmError, ValueError):
    """A bus message does not follow its binary or JSON layout."""


class BusKeyError(HilswarmError, ValueError):
    """A name cannot be used in a bus key (empty, or contains '/', '*', '$', '?', '#', space)."""


class BusEndpointError(HilswarmError, ValueError):
    """A string is not a Zenoh endpoint (``<protocol>/<address>``, e.g. ``tcp/127.0.0.1:7447``)."""


def check_key_name(name: str, *, what: str) -> str:
    """Return ``name`` if it is usable as one chunk of a key, else raise :class:`BusKeyError`."""
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise BusKeyError(
            f"{what} {name!r} cannot be used in a bus key: expected letters, digits, '_', '.', '-' "
            "(no '/', '*', '$', '?', '#' or spaces), not starting with '.' or '-'"
        )
    return name


@dataclass(frozen=True)
class BusKeys:
    """The keys of one run of an experiment.

    Args:
        experiment: experiment name (one key chunk).
        run_id: the run's id (one key chunk; ``hilswarm run`` makes a fresh one per run).
            Empty: keys without a run id, ``hilswarm/<exp>/...`` (tools and benchmarks).
    """

    experiment: str
    run_id: str = ""

    def __post_init__(self) -> None:
        check_key_name(self.experiment, what="experiment name")
        if self.run_id:
            check_key_name(self.run_id, what="run id")

    @property
    def prefix(self) -> str:
        """``hilswarm/<exp>/<run_id>`` (``hilswarm/<exp>`` without a run id)."""
        if self.run_id:
            return f"{KEY_ROOT}/{self.experiment}/{self.run_id}"
        return f"{KEY_ROOT}/{self.experiment}"

    @property
    def tick(self) -> str:
        """Key of the manager's tick messages."""
        return f"{self.prefix}/tick"

    @property
    def control(self) -> str:
        """Key of swarm-wide commands (stop, estop, pause, resume)."""
        return f"{self.prefix}/control"

    @property
    def manager_status(self) -> str:
        """Key on which the instance manager announces its own state (JSON)."""
        return f"{self.prefix}/manager/status"

    @property
    def manager_request(self) -> str:
        """Key of operators' commands to the manager (:func:`encode_control` layout)."""
        return f"{self.prefix}/manager/request"

    def agent(self, name: str, leaf: str) -> str:
        """Key ``hilswarm/<exp>/agent/<name>/<leaf>`` (leaf: y, u, x_hat, status, set)."""
        check_key_name(name, what="agent name")
        return f"{self.prefix}/agent/{name}/{leaf}"

    def y(self, name: str) -> str:
        """Key of agent ``name``'s output y_k."""
        return self.agent(name, "y")

    def u(self, name: str) -> str:
        """Key of agent ``name``'s applied input u_k."""
        return self.agent(name, "u")

    def x_hat(self, name: str) -> str:
        """Key of agent ``name``'s controller state x_hat_k."""
        return self.agent(name, "x_hat")

    def status(self, name: str) -> str:
        """Key of agent ``name``'s lifecycle status (JSON)."""
        return self.agent(name, "status")

    def set(self, name: str) -> str:
        """Key of agent ``name``'s parameter queryable."""
        return self.agent(name, "set")

    def flush(self, name: str) -> str:
        """Key of agent ``name``'s flush barrier (:func:`flush_barrier`; no queryable)."""
        return self.agent(name, "flush")

    def telemetry_batches(self, name: str) -> str:
        """Key of agent ``name``'s telemetry batches (:func:`encode_telemetry_batch`)."""
        return self.agent(name, "telemetry")

    def telemetry(self, name: str, channel: str) -> str:
        """Key of agent ``name``'s telemetry channel ``channel``."""
        check_key_name(channel, what="telemetry channel")
        return self.agent(name, f"telemetry/{channel}")

    def link_tx(self, name: str) -> str:
        """Key of the wire-protocol bytes agent ``name`` sends to its board via the gateway."""
        return self.agent(name, "link/tx")

    def link_rx(self, name: str) -> str:
        """Key of the wire-protocol bytes the gateway received from agent ``name``'s board."""
        return self.agent(name, "link/rx")

    def link_robot(self, name: str, direction: str) -> str:
        """Key of a simulated robot's UART bytes (``direction``: ``in`` to it, ``out`` from it)."""
        if direction not in ("in", "out"):
            raise BusKeyError(f"robot UART direction must be 'in' or 'out', got {direction!r}")
        return self.agent(name, f"link/robot/{direction}")

    def gateway(self, leaf: str) -> str:
        """Key ``hilswarm/<exp>/gateway/<leaf>`` (``status``, ``stats``)."""
        return f"{self.prefix}/gateway/{leaf}"

    def alive(self, name: str) -> str:
        """Key of agent ``name``'s liveliness token."""
        check_key_name(name, what="agent name")
        return f"{self.prefix}/alive/{name}"

    def mocap(self, body: str) -> str:
        """Key of rigid body ``body``'s pose, published by the mocap process."""
        check_key_name(body, what="mocap body")
        return f"{self.prefix}/mocap/{body}"

    @property
    def mocap_status(self) -> str:
        """Key of the mocap process's status (JSON: connected, bodies seen, server lost)."""
        return f"{self.prefix}/mocap_status"

    @property
    def mocap_clock(self) -> str:
        """Key of the mocap process's frame clock (frame number and time, once per frame)."""
        return f"{self.prefix}/mocap_clock"

    def mocap_truth(self, body: str) -> str:
        """Key of a simulated body's true pose (agents -> the mocap simulator only)."""
        check_key_name(body, what="mocap body")
        return f"{self.prefix}/mocap_truth/{body}"

    # Wildcards: for the orchestrator and its recorder only, never for agents.
    @property
    def all_agent_data(self) -> str:
        """Wildcard matching every key under ``agent/`` (recorder only)."""
        return f"{self.prefix}/agent/**"

    @property
    def all_outputs(self) -> str:
        """Wildcard matching every agent's y key (instance manager only)."""
        return f"{self.prefix}/agent/*/y"

    @property
    def all_alive(self) -> str:
        """Wildcard matching every liveliness token of the experiment (manager only)."""
        return f"{self.prefix}/alive/*"

    def parse_agent_key(self, key: str) -> tuple[str, str]:
        """Split ``hilswarm/<exp>/agent/<name>/<leaf...>`` into ``(name, leaf)``.

        Raises:
            BusKeyError: ``key`` is not an agent key of this experiment.
        """
        head = f"{self.prefix}/agent/"
        if not key.startswith(head):
            raise BusKeyError(f"key {key!r} is not under {head!r}")
        name, sep, leaf = key[len(head) :].partition("/")
        if not sep or not name or not leaf:
            raise BusKeyError(f"key {key!r}: expected {head}<name>/<leaf>")
        return name, leaf

    def parse_alive_key(self, key: str) -> str:
        """Return the agent name of a liveliness key ``hilswarm/<exp>/alive/<name>``."""
        head = f"{self.prefix}/alive/"
        if not key.startswith(head) or "/" in key[len(head) :] or len(key) == len(head):
            raise BusKeyError(f"key {key!r}: expected {head}<name>")
        return key[len(head) :]


# ---------------------------------------------------------------------------------------------
# Messages
# ---------------------------------------------------------------------------------------------

_VECTOR_HEADER = struct.Struct("<qd")
_TICK_HEADER = struct.Struct("<qdBH")
#: Flag bits of a tick message.
TICK_REALTIME = 0x01
#: Flag bit of a schedule message (:class:`ScheduleMessage`, sent on the tick key).
TICK_SCHEDULE = 0x02
_SCHEDULE_TAIL = struct.Struct("<qdd")
#: Offset of the flags in a tick or schedule message (after ``k`` and ``t``) [bytes].
_TICK_FLAGS_AT = struct.calcsize("<qd")
_REPORT_HEADER = struct.Struct("<ddddHHHH")
_GATEWAY_STAGES = struct.Struct("<dd")


def encode_vector(k: int, t: float, values: np.ndarray | Sequence[float]) -> bytes:
    """Encode a per-tick vector: ``k`` (tick), ``t`` [s, experiment time], ``values``.

    ``values`` is written as float64; ``NaN`` marks an unavailable component.
    """
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 1:
        raise BusMessageError(f"vector values must be one-dimensional, got shape {array.shape}")
    return _VECTOR_HEADER.pack(k, t) + array.tobytes()


def decode_vector(payload: bytes | bytearray | memoryview) -> tuple[int, float, np.ndarray]:
    """Decode :func:`encode_vector`'s bytes into ``(k, t, values)`` (values: a float64 copy)."""
    size = len(payload)
    if size < _VECTOR_HEADER.size or (size - _VECTOR_HEADER.size) % 8:
        raise BusMessageError(
            f"vector message of {size} bytes: expected 16 header bytes plus 8 per value"
        )
    k, t = _VECTOR_HEADER.unpack_from(payload)
    values = np.frombuffer(payload, dtype="<f8", offset=_VECTOR_HEADER.size).copy()
    return k, t, values


@dataclass(frozen=True)
class TickMessage:
    """One tick message of the instance manager: it *releases* every tick up to ``k``.

    Running tick ``k`` means: compute u_k from u_{k-1}, y_{k-1} and the neighbours' y_{k-1},
    apply it, let the plant advance, sense y_k and publish it (``k = 0``: only sense y_0).

    * Realtime: one message per tick, on the wall-clock schedule. Every y_{k-1} is in when it
      is sent, except those of the agents in ``missing`` (late or lost): their neighbours see
      ``None`` for them. An agent runs the newest tick released.
    * Lockstep: ticks are released a window ahead (one message covers several ticks); an
      agent runs each released tick as soon as its own neighbours' y_{k-1} are in.
      ``missing`` lists the lost agents, whose outputs count as ``None`` from then on. The
      same ``k`` may be sent again when an agent is lost, to announce it.

    The mode travels in every message, so an agent (also one started on another machine with
    ``hilswarm agent``) always runs ticks the way the manager schedules them.

    Attributes:
        k: the newest tick released (>= 0).
        t: experiment time of tick ``k`` [s] (``k * dt``).
        missing: indices (experiment order) of agents whose outputs are not coming.
        realtime: ``True`` in realtime mode, ``False`` in lockstep.
    """

    k: int
    t: float
    missing: tuple[int, ...] = ()
    realtime: bool = False


def encode_tick(message: TickMessage) -> bytes:
    """Encode a :class:`TickMessage`.

    Layout (little-endian): int64 k, float64 t [s], uint8 flags (:data:`TICK_REALTIME`),
    uint16 count, then ``count`` uint16 agent indices.
    """
    missing = message.missing
    flags = TICK_REALTIME if message.realtime else 0
    return _TICK_HEADER.pack(message.k, message.t, flags, len(missing)) + struct.pack(
        f"<{len(missing)}H", *missing
    )


def decode_tick(payload: bytes | bytearray | memoryview) -> TickMessage:
    """Decode :func:`encode_tick`'s bytes."""
    size = len(payload)
    if size < _TICK_HEADER.size:
        raise BusMessageError(
            f"tick message of {size} bytes: expected at least {_TICK_HEADER.size}"
        )
    k, t, flags, count = _TICK_HEADER.unpack_from(payload)
    if flags & TICK_SCHEDULE:
        raise BusMessageError("a schedule message, not a tick message")
    if size != _TICK_HEADER.size + 2 * count:
        raise BusMessageError(f"tick message of {size} bytes does not hold {count} indices")
    missing = struct.unpack_from(f"<{count}H", payload, _TICK_HEADER.size) if count else ()
    return TickMessage(k, t, tuple(missing), realtime=bool(flags & TICK_REALTIME))


@dataclass(frozen=True)
class ScheduleMessage:
    """The instance manager's schedule of a self-clocked realtime run (on the tick key).

    Agents on the manager's host keep the schedule themselves instead of waiting for one tick
    message per period: tick ``j`` (``first <= j <= last``) is due at ``t0 + j * dt`` on
    ``CLOCK_MONOTONIC``, the system-wide clock of ``time.monotonic`` and ``time.perf_counter``
    on Linux (so the manager's and the agents' readings are the same clock). The manager sends
    one at the start and again whenever the schedule changes: a pause ends it at ``last``, a
    resume re-anchors it (new ``t0`` and ``first``), and a change of ``missing`` (an agent
    lost) repeats it with the same anchor.

    Attributes:
        first: the first tick of this schedule (>= 0).
        last: its last tick (>= ``first``).
        t0: when tick 0 would be due [s, CLOCK_MONOTONIC] (tick ``j`` at ``t0 + j * dt``).
        dt: control period [s] (the experiment's).
        missing: indices (experiment order) of agents lost: their outputs are not coming.
    """

    first: int
    last: int
    t0: float
    dt: float
    missing: tuple[int, ...] = ()


def is_schedule(payload: bytes | bytearray | memoryview) -> bool:
    """Is this message on the tick key a schedule (:func:`encode_schedule`)?"""
    return len(payload) > _TICK_FLAGS_AT and bool(payload[_TICK_FLAGS_AT] & TICK_SCHEDULE)


def encode_schedule(message: ScheduleMessage) -> bytes:
    """Encode a :class:`ScheduleMessage`.

    Layout (little-endian): the tick message's (int64 ``first``, float64 ``first * dt`` [s],
    uint8 flags ``TICK_REALTIME | TICK_SCHEDULE``, uint16 count, ``count`` uint16 agent
    indices), then int64 ``last``, float64 ``t0`` [s], float64 ``dt`` [s].
    """
    missing = message.missing
    return (
        _TICK_HEADER.pack(
            message.first,
            message.first * message.dt,
            TICK_REALTIME | TICK_SCHEDULE,
            len(missing),
        )
        + struct.pack(f"<{len(missing)}H", *missing)
        + _SCHEDULE_TAIL.pack(message.last, message.t0, message.dt)
    )


def decode_schedule(payload: bytes | bytearray | memoryview) -> ScheduleMessage:
    """Decode :func:`encode_schedule`'s bytes."""
    size = len(payload)
    if size < _TICK_HEADER.size + _SCHEDULE_TAIL.size:
        raise BusMessageError(f"schedule message of {size} bytes: too short")
    first, _t, flags, count = _TICK_HEADER.unpack_from(payload)
    if not flags & TICK_SCHEDULE:
        raise BusMessageError("a tick message, not a schedule message")
    if size != _TICK_HEADER.size + 2 * count + _SCHEDULE_TAIL.size:
        raise BusMessageError(f"schedule message of {size} bytes does not hold {count} indices")
    missing = struct.unpack_from(f"<{count}H", payload, _TICK_HEADER.size) if count else ()
    last, t0, dt = _SCHEDULE_TAIL.unpack_from(payload, _TICK_HEADER.size + 2 * count)
    return ScheduleMessage(first, last, t0, dt, tuple(missing))


@dataclass(frozen=True)
class AgentTiming:
    """Where one agent spent one tick.

    Attributes:
        compute_s: controller step [s, wall clock].
        actuate_s: applying ``u`` on the vehicle (limits, calibration, staging the outputs)
            [s, wall clock].
        sense_s: sensing y_k [s, wall clock].
        skipped: ticks the agent dropped since its last answer because it fell behind.
        link_s: the board round trip (request out, board turnaround, reply in; re-sends
            included) [s, wall clock]; 0 without a board.
        retries: re-sends of the board request in this tick (links that count them).
        gateway_s: of ``link_s``, the XBee gateway's own time (queueing, gathering, packing)
            [s, the gateway's clock]; ``None`` for links without a gateway.
        radio_s: of ``link_s``, the radio's time as the gateway measures it (UARTs, air, the
            robot's turnaround) [s, the gateway's clock]; ``None`` for links without a gateway.
    """

    compute_s: float = 0.0
    actuate_s: float = 0.0
    sense_s: float = 0.0
    skipped: int = 0
    link_s: float = 0.0
    retries: int = 0
    gateway_s: float | None = None
    radio_s: float | None = None


def encode_report(timing: AgentTiming, u: np.ndarray | None, x_hat: np.ndarray | None) -> bytes:
    """Encode an agent's tick report, the attachment of its y_k message.

    Layout: timing (compute, actuate, sense, link [s] as 4 float64; skipped ticks and link
    retries as 2 uint16, saturating), the sizes of u and x_hat (2 uint16), then u_k (the input
    applied over [t_{k-1}, t_k); empty at tick 0 and when not actuating) and x_hat_k (the
    controller state after computing u_k), as float64; for a link through the XBee gateway
    (``timing.gateway_s`` set) then ``gateway_s`` and ``radio_s`` [s] as 2 float64. The recorder
    unpacks it in ``orchestrator/record_stream.py``.
    """
    u_bytes = b"" if u is None else np.asarray(u, dtype="<f8").tobytes()
    x_bytes = b"" if x_hat is None else np.asarray(x_hat, dtype="<f8").tobytes()
    stages = b""
    if timing.gateway_s is not None:
        radio_s = 0.0 if timing.radio_s is None else timing.radio_s
        stages = _GATEWAY_STAGES.pack(timing.gateway_s, radio_s)
    return (
        _REPORT_HEADER.pack(
            timing.compute_s,
            timing.actuate_s,
            timing.sense_s,
            timing.link_s,
            min(timing.skipped, 0xFFFF),
            min(timing.retries, 0xFFFF),
            len(u_bytes) // 8,
            len(x_bytes) // 8,
        )
        + u_bytes
        + x_bytes
        + stages
    )


def unpack_vector(payload: bytes | bytearray | memoryview) -> tuple[int, float, tuple[float, ...]]:
    """Like :func:`decode_vector`, but the values as a tuple of floats (cheap for short vectors)."""
    size = len(payload)
    if size < _VECTOR_HEADER.size or (size - _VECTOR_HEADER.size) % 8:
        raise BusMessageError(
            f"vector message of {size} bytes: expected 16 header bytes plus 8 per value"
        )
    k, t = _VECTOR_HEADER.unpack_from(payload)
    values = _floats((size - _VECTOR_HEADER.size) // 8).unpack_from(payload, _VECTOR_HEADER.size)
    return k, t, values


_FLOATS: dict[int, struct.Struct] = {}


def _floats(n: int) -> struct.Struct:
    """A cached ``struct.Struct`` of ``n`` little-endian float64."""
    layout = _FLOATS.get(n)
    if layout is None:
        layout = _FLOATS[n] = struct.Struct(f"<{n}d")
    return layout


#: Wall time between two telemetry batches of an agent [s].
TELEMETRY_PERIOD_S = 0.25
#: Version byte that opens every telemetry batch.
TELEMETRY_BATCH_VERSION = 1

_BATCH_HEAD = struct.Struct("<BH")
_ROWS = struct.Struct("<I")


@dataclass(frozen=True)
class TelemetryRows:
    """Rows of one telemetry channel, as carried in a batch.

    Attributes:
        channel: channel name (last part of ``/<agent>/telemetry/<channel>``).
        fields: field names, one per value of a row.
        k: tick indices, shape ``(n,)``, int64.
        t: sample times [s, experiment time], shape ``(n,)``, float64.
        values: one row per sample, shape ``(n, len(fields))``, float64 (NaN: missing value).
    """

    channel: str
    fields: tuple[str, ...]
    k: np.ndarray
    t: np.ndarray
    values: np.ndarray


def _short_text(text: str, what: str) -> bytes:
    data = text.encode()
    if not 0 < len(data) < 256:
        raise BusMessageError(f"{what} {text!r}: expected 1..255 bytes of UTF-8")
    return bytes((len(data),)) + data


def telemetry_channel_head(channel: str, fields: Sequence[str]) -> bytes:
    """The part of a batch that names a channel and its fields (build it once per channel).

    Layout: ``uint8`` name length, name (UTF-8), ``uint8`` field count, per field ``uint8``
    length and name.
    """
    if not 0 < len(fields) < 256:
        raise BusMessageError(f"telemetry channel {channel!r}: expected 1..255 fields")
    parts = [_short_text(channel, "telemetry channel"), bytes((len(fields),))]
    parts += [_short_text(field, f"telemetry channel {channel!r}: field") for field in fields]
    return b"".join(parts)


def encode_telemetry_batch(
    channels: Iterable[tuple[bytes, np.ndarray, np.ndarray, np.ndarray]],
) -> bytes:
    """Encode a telemetry batch: the new rows of several channels in one message.

    Layout (little-endian): ``uint8`` version (:data:`TELEMETRY_BATCH_VERSION`), ``uint16``
    channel count, then per channel its head (:func:`telemetry_channel_head`), ``uint32`` row
    count ``n``, ``n`` int64 ``k``, ``n`` float64 ``t`` [s, experiment time] and ``n * fields``
    float64 values, row by row.

    Args:
        channels: per channel ``(head, k, t, values)``; ``values`` of shape ``(n, fields)``.
            A channel with no rows is left out.
    """
    parts: list[bytes] = []
    count = 0
    for head, k, t, values in channels:
        n = k.shape[0]
        if not n:
            continue
        if t.shape != (n,) or values.ndim != 2 or values.shape[0] != n:
            raise BusMessageError(
                f"telemetry rows: k {k.shape}, t {t.shape} and values {values.shape} disagree"
            )
        parts += [
            head,
            _ROWS.pack(n),
            np.ascontiguousarray(k, dtype="<i8").tobytes(),
            np.ascontiguousarray(t, dtype="<f8").tobytes(),
            np.ascontiguousarray(values, dtype="<f8").tobytes(),
        ]
        count += 1
    return _BATCH_HEAD.pack(TELEMETRY_BATCH_VERSION, count) + b"".join(parts)


def _read_text(payload: bytes | bytearray | memoryview, offset: int) -> tuple[str, int]:
    size = payload[offset]
    end = offset + 1 + size
    if end > len(payload):
        raise BusMessageError("telemetry batch cut inside a name")
    return bytes(payload[offset + 1 : end]).decode(), end


def decode_telemetry_batch(payload: bytes | bytearray | memoryview) -> list[TelemetryRows]:
    """Decode :func:`encode_telemetry_batch`'s bytes (arrays are copies).

    Raises:
        BusMessageError: unknown version, or the bytes do not hold what the counts say.
    """
    size = len(payload)
    if size < _BATCH_HEAD.size:
        raise BusMessageError(f"telemetry batch of {size} bytes: expected at least 3")
    version, count = _BATCH_HEAD.unpack_from(payload)
    if version != TELEMETRY_BATCH_VERSION:
        raise BusMessageError(
            f"telemetry batch version {version}, expected {TELEMETRY_BATCH_VERSION}"
        )
    offset = _BATCH_HEAD.size
    result: list[TelemetryRows] = []
    try:
        for _ in range(count):
            channel, offset = _read_text(payload, offset)
            n_fields = payload[offset]
            offset += 1
            fields = []
            for _ in range(n_fields):
                field_name, offset = _read_text(payload, offset)
                fields.append(field_name)
            (n,) = _ROWS.unpack_from(payload, offset)
            offset += _ROWS.size
            end = offset + 8 * n * (2 + n_fields)
            if end > size:
                raise BusMessageError(
                    f"telemetry batch: channel {channel!r} says {n} rows of {n_fields} fields, "
                    f"but only {size - offset} bytes follow"
                )
            k = np.frombuffer(payload, dtype="<i8", count=n, offset=offset).astype(np.int64)
            t = np.frombuffer(payload, dtype="<f8", count=n, offset=offset + 8 * n).copy()
            values = (
                np.frombuffer(payload, dtype="<f8", count=n * n_fields, offset=offset + 16 * n)
                .reshape(n, n_fields)
                .copy()
            )
            result.append(TelemetryRows(channel, tuple(fields), k, t, values))
            offset = end
    except (IndexError, struct.error, UnicodeDecodeError) as exc:
        raise BusMessageError(f"telemetry batch of {size} bytes is cut or garbled: {exc}") from exc
    if offset != size:
        raise BusMessageError(f"telemetry batch: {size - offset} bytes left after {count} channels")
    return result


class ControlCommand(enum.Enum):
    """Swarm-wide commands published on the ``control`` key."""

    STOP = "stop"  #: every agent to safe mode, then stopped; the run ends and is recorded
    ESTOP = "estop"  #: every agent to safe mode at once (board e-stop), then the run stops
    PAUSE = "pause"  #: no more ticks until resume; agents hold their last input
    RESUME = "resume"  #: ticks start again


def encode_control(command: ControlCommand, *, reason: str = "") -> bytes:
    """Encode a control command (small JSON: rare, human-inspectable)."""
    return json.dumps({"command": command.value, "reason": reason}).encode()


def decode_control(payload: bytes | bytearray | memoryview) -> tuple[ControlCommand, str]:
    """Decode :func:`encode_control`'s bytes into ``(command, reason)``."""
    try:
        data = json.loads(bytes(payload))
        return ControlCommand(data["command"]), str(data.get("reason", ""))
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError) as exc:
        known = ", ".join(c.value for c in ControlCommand)
        raise BusMessageError(f"bad control message {bytes(payload)!r}: expected {known}") from exc


#: Counter fields an agent's status message may carry (see ``hilswarm.agents.agent``):
#: ``malformed`` {key: count}, ``dropped`` {reason: count}, ``skipped`` (ticks missed),
#: ``link_faults`` (board link faults) and ``stale_samples`` (board answers marked STALE: the
#: XBee gateway's answers from a robot's last samples), and, self-clocked, ``inputs_missing``
#: {neighbour: [tick, ...]} (ticks run without that neighbour's output). Only non-zero ones
#: are sent; the recorder keeps them.
STATUS_COUNTER_FIELDS = (
    "malformed",
    "dropped",
    "skipped",
    "link_faults",
    "stale_samples",
    "inputs_missing",
)


def encode_json(data: dict[str, Any]) -> bytes:
    """Encode a status / acknowledgement message."""
    return json.dumps(data, allow_nan=True).encode()


def decode_json(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode a status / acknowledgement message."""
    try:
        data = json.loads(bytes(payload))
    except (ValueError, RecursionError) as exc:
        raise BusMessageError(f"bad JSON message {bytes(payload)[:80]!r}: {exc}") from exc
    if not isinstance(data, dict):
        raise BusMessageError(f"JSON message must be an object, got {type(data).__name__}")
    return data


# ---------------------------------------------------------------------------------------------
# Session configurations
# ---------------------------------------------------------------------------------------------


#: An endpoint, as the messages about a bad one show it.
ENDPOINT_EXAMPLE = "tcp/127.0.0.1:7447"
#: Zenoh's link protocols whose address is ``HOST:PORT``.
IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
#: Every link protocol Zenoh knows (whether this build of Zenoh has it is told at open).
ENDPOINT_PROTOCOLS = (*IP_PROTOCOLS, "unixsock-stream", "unixpipe", "serial", "vsock")
#: ``<protocol>/<address>[?<metadata>][#<config>]``, Zenoh's endpoint syntax, without spaces.
_ENDPOINT_RE = re.compile(
    r"^(?P<protocol>[a-z][a-z0-9-]*)/(?P<address>[^?#\s]+)(\?[^#\s]*)?(#\S*)?$"
)


def check_endpoint(text: str) -> str:
    """Return ``text`` if it is a Zenoh endpoint, else raise :class:`BusEndpointError`.

    The one check of endpoints: :func:`session_config` applies it to every endpoint it is
    given, and the CLI to its ``--connect``/``--listen`` options. Stricter than Zenoh's own
    parser, which takes ``tcp/foo`` or ``xyz/1.2.3.4:5`` and fails only when the session opens.
    """
    match = _ENDPOINT_RE.match(text) if isinstance(text, str) else None
    if match is None:
        raise BusEndpointError(f"{text!r} is not a Zenoh endpoint (e.g. {ENDPOINT_EXAMPLE})")
    protocol, address = match["protocol"], match["address"]
    if protocol not in ENDPOINT_PROTOCOLS:
        raise BusEndpointError(
            f"{text!r} is not a Zenoh endpoint: unknown protocol {protocol!r}; expected one of "
            f"{', '.join(ENDPOINT_PROTOCOLS)} (e.g. {ENDPOINT_EXAMPLE})"
        )
    if protocol in IP_PROTOCOLS:
        host, _, port = address.rpartition(":")
        if not host or not port.isdigit() or int(port) > 65535:
            raise BusEndpointError(
                f"{text!r} is not a Zenoh endpoint: {protocol}/ needs HOST:PORT with a port in "
                f"0..65535 (e.g. {ENDPOINT_EXAMPLE})"
            )
    return text


def loopback_endpoint(port: int = 0) -> str:
    """``tcp/127.0.0.1:<port>`` (port 0: a listening session binds a free port)."""
    if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port < 65536:
        raise BusKeyError(f"port must be an integer in 0..65535, got {port!r}")
    return f"tcp/127.0.0.1:{port}"


@dataclass(frozen=True)
class SessionSecurity:
    """What a session proves and what it checks, with Zenoh's own mechanisms.

    Attributes:
        user: user name this session authenticates with (``transport/auth/usrpwd``).
        password: its password.
        user_dictionary: router: path of the ``user:password`` file it accepts (mode 0600).
        ca_pem: trust this CA (PEM) for ``tls/`` endpoints (the run's own CA).
        certificate_pem: router: its TLS certificate (PEM, signed by the run's CA).
        private_key_pem: router: the certificate's private key (PEM).
        access_control: router: Zenoh's ``access_control`` section (default deny).
    """

    user: str | None = None
    password: str | None = None
    user_dictionary: str | None = None
    ca_pem: str | None = None
    certificate_pem: str | None = None
    private_key_pem: str | None = None
    access_control: Mapping[str, Any] | None = None


def _b64(text: str) -> str:
    return base64.b64encode(text.encode()).decode()


def session_config(
    mode: str,
    *,
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    security: SessionSecurity | None = None,
) -> zenoh.Config:
    """The configuration of every Zenoh session of hilswarm (the one place that builds them).

    Args:
        mode: ``"router"`` (the orchestrator's embedded router) or ``"client"``.
        listen: endpoints to listen on (port 0: a free port, see :func:`bound_endpoints`).
        connect: endpoints to connect to.
        security: credentials, TLS material and access control; ``None``: none.

    Raises:
        BusEndpointError: an endpoint that is not one (:func:`check_endpoint`).
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    config.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    config.insert_json5("transport/link/tx/keep_alive", str(KEEP_ALIVES_PER_LEASE))
    for priority in ("real_time", "data_high"):
        config.insert_json5(
            f"transport/link/tx/queue/size/{priority}", str(TICK_PATH_QUEUE_BATCHES)
        )
    for key, endpoints in (("listen", list(listen)), ("connect", list(connect))):
        for endpoint in endpoints:
            check_endpoint(endpoint)
        config.insert_json5(f"{key}/endpoints", json.dumps(endpoints))
    if mode == "router":  # lets bound_endpoints() read the ports it bound (local reads only)
        config.insert_json5("adminspace", '{"enabled": true, "permissions": {"read": true}}')
    if security is None:
        return config
    usrpwd: dict[str, str] = {}
    if security.user is not None:
        usrpwd = {"user": security.user, "password": security.password or ""}
    if security.user_dictionary is not None:
        usrpwd["dictionary_file"] = security.user_dictionary
    if usrpwd:
        config.insert_json5("transport/auth/usrpwd", json.dumps(usrpwd))
    tls: dict[str, Any] = {}
    if security.ca_pem:
        tls["root_ca_certificate_base64"] = _b64(security.ca_pem)
    if security.certificate_pem and security.private_key_pem:
        tls["listen_certificate_base64"] = _b64(security.certificate_pem)
        tls["listen_private_key_base64"] = _b64(security.private_key_pem)
    if tls:
        config.insert_json5("transport/link/tls", json.dumps(tls))
    if security.access_control is not None:
        config.insert_json5("access_control", json.dumps(dict(security.access_control)))
    return config


def listen_config(
    endpoints: Iterable[str], *, security: SessionSecurity | None = None
) -> zenoh.Config:
    """Config of the orchestrator's embedded router session listening on ``endpoints``.

    Agents connect to it as clients; it routes between them.
    """
    listen = list(endpoints)
    if not listen:
        raise BusKeyError("a listening session needs at least one endpoint")
    return session_config("router", listen=listen, security=security)


def client_config(
    endpoints: Iterable[str], *, security: SessionSecurity | None = None
) -> zenoh.Config:
    """Config of a client session (agent, CLI command, or orchestrator joining a zenohd)."""
    connect = list(endpoints)
    if not connect:
        raise BusKeyError("a client session needs at least one endpoint to connect to")
    return session_config("client", connect=connect, security=security)


def bound_endpoints(session: zenoh.Session, timeout_s: float = 2.0) -> list[str]:
    """The endpoints a router session actually listens on (ports bound for port 0).

    Read from the router's own admin space (``@/<zid>/router``), which
    :func:`session_config` enables for local reads.

    Raises:
        BusConnectionError: the router does not report its locators.
    """
    try:
        for reply in session.get(f"@/{session.zid()}/router", timeout=timeout_s):
            if reply.ok is not None:
                locators = json.loads(reply.ok.payload.to_bytes()).get("locators", [])
                return [str(locator) for locator in locators]
    except (zenoh.ZError, ValueError) as exc:
        raise BusConnectionError(f"cannot read the bus's listening endpoints: {exc}") from exc
    raise BusConnectionError("the bus did not report its listening endpoints")


def has_subscribers(publisher: zenoh.Publisher) -> bool:
    """True when ``publisher`` currently has matching subscribers.

    (``Publisher.matching_status`` is a ``MatchingStatus`` object in zenoh-python 1.x, not a
    bool: it is always truthy, so test its ``matching`` attribute.)
    """
    status = publisher.matching_status
    return bool(getattr(status, "matching", status))


#: Zenoh runtime pools for hilswarm processes (the ``ZENOH_RUNTIME`` environment variable,
#: read when a process opens its first session): accepting, receiving and the network pools
#: handed over to one application worker; transmitting keeps a thread of its own. Measured
#: against Zenoh's defaults in docs/running.md ("Zenoh runtime threads"): fewer threads and
#: thread switches per message. The transmit pool stays apart because a router forwards from
#: its receive tasks into queues that only transmit tasks drain: on one shared worker a full
#: queue (a large message to a busy agent) blocks the worker that would drain it, and every
#: link's lease runs out (found by tests/integration/test_swarm_runtime.py's 100 kB inputs).
LEAN_RUNTIME = (
    "(app: (worker_threads: 1), acc: (handover: app), rx: (handover: app), "
    "net: (handover: app), tx: (worker_threads: 1))"
)


def use_lean_runtime() -> None:
    """Give this process :data:`LEAN_RUNTIME` unless ``ZENOH_RUNTIME`` is set already.

    Effective until the process's first session opens (Zenoh reads it then); inherited by the
    processes it starts.
    """
    os.environ.setdefault("ZENOH_RUNTIME", LEAN_RUNTIME)


def open_session(config: zenoh.Config) -> zenoh.Session:
    """Open a Zenoh session, turning Zenoh's errors into :class:`BusConnectionError`.

    The message says what went wrong in the user's terms; Zenoh's own text goes to the debug
    log only. The process's Zenoh runtime is :data:`LEAN_RUNTIME` (see :func:`use_lean_runtime`).
    """
    use_lean_runtime()
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        logger.debug("zenoh.open failed: %s", exc)
        raise BusConnectionError(_explain_open_error(config, str(exc))) from None


#: Bound on waiting for the answer to :func:`flush_barrier`'s query [s].
FLUSH_TIMEOUT_S = 1.0


def flush_barrier(session: zenoh.Session, key: str, *, timeout_s: float = FLUSH_TIMEOUT_S) -> bool:
    """Wait until this session's messages put so far at :data:`DATA_QOS`'s priority (or a
    higher one) have reached the router: a query on ``key``, which no one answers, at that
    priority, behind them in the same queue. The router routes what came before it, then
    answers the query (no queryable: at once) with its end. ``True`` when the end came within
    ``timeout_s`` [s].

    Why: a session closed right after a put may lose it. Closing sends the undeclarations and
    the link's close at control priority, ahead of data still queued, and what was still
    queued can be lost (measured: an agent's last statuses, put ~0.7 ms before it closed its
    session, never reached the manager in 2 of 72 runs of one test on a loaded 2-core
    machine; none lost in 51 runs with this barrier).
    """
    start = time.monotonic()
    try:
        replies = session.get(
            key,
            timeout=timeout_s,
            congestion_control=DATA_QOS["congestion_control"],
            priority=DATA_QOS["priority"],
        )
        for _ in replies:  # ends with the query's end (none answers) or at its timeout
            pass
    except zenoh.ZError as exc:
        logger.debug("flush barrier on %s: %s", key, exc)
        return False
    return time.monotonic() - start < timeout_s


def _explain_open_error(config: zenoh.Config, raw: str) -> str:
    connect = json.loads(config.get_json("connect/endpoints") or "[]")
    listen = json.loads(config.get_json("listen/endpoints") or "[]")
    if "Unable to connect" in raw:
        return (
            f"cannot join the bus at {', '.join(connect)}: nothing answers there, or it refused "
            "this session (wrong or missing credentials, untrusted TLS certificate)"
        )
    if "in use" in raw.lower():
        return f"cannot listen on {', '.join(listen)}: address already in use"
    if "listen" in raw.lower() or "bind" in raw.lower():
        return f"cannot listen on {', '.join(listen)} (address not available here?)"
    where = ", ".join([*listen, *connect])
    return f"cannot open the bus session on {where}: {_zenoh_reason(raw)}"


def _zenoh_reason(raw: str) -> str:
    """Zenoh's error text without the Rust source locations (``... at /x/y.rs:62.``)."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", raw).strip() or "unknown Zenoh error"

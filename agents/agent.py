"""The agent process: one vehicle, its board link and its controller on the bus.

An agent is started by the orchestrator's launcher (``python -m hilswarm.agents.agent
--connect ENDPOINT --config JSON``) or by ``hilswarm agent`` on another machine. It

1. opens a Zenoh *client* session to the orchestrator's router (``connected``),
2. builds its vehicle, opens and configures its board, builds its controller (``configured``),
3. declares its publishers (``y``, ``u``, ``x_hat``, ``status``, ``telemetry``), subscribes to its
   neighbours' **explicit** ``y`` keys, to the tick and control keys, declares its ``set``
   queryable and its liveliness token (``armed``),
4. answers ticks (``running``) until told to stop.

Tick ``k`` (see :class:`~hilswarm.agents.bus.TickMessage`): every y_{k-1} is in, so the agent
computes ``u_k = controller(u_{k-1}, y_{k-1}, neighbours' y_{k-1})``, applies it, lets the
board/plant advance one period (``exchange``), senses ``y_k`` and publishes it — one bus round
trip per tick. Tick 0 only senses ``y_0``. ``u_k`` is the input held over ``[t_{k-1}, t_k)``
and is recorded with ``t = t_{k-1}``; ``y_k`` is recorded with ``t = t_k = k * dt``.

The vehicle's telemetry channels (``vehicle.telemetry``) go out in batches on
``agent/<name>/telemetry`` (:func:`~hilswarm.agents.bus.encode_telemetry_batch`): the rows
appended since the previous batch, every :data:`~hilswarm.agents.bus.TELEMETRY_PERIOD_S` of
wall time (checked once per tick and while idle: one clock comparison), and a last batch when
the agent goes safe or shuts down. A killed agent loses at most one period of telemetry.

Ticks run on the bus: the callback that receives the tick message, or the neighbour output
that was the last one missing, runs the tick right there (no thread hop per tick). One lock
(the *engine lock*) serialises ticks, commands and parameter changes, so each is handled
whole, between ticks. The main thread only handles rare work: parameter changes (queries),
signals, the manager's disappearance, and the periodic telemetry batch.

Which tick runs when (the tick message of :class:`~hilswarm.agents.bus.TickMessage` releases
ticks up to ``k``):

* ``lockstep`` — the agent steps through every released tick; it computes tick ``k`` as soon
  as *its own* neighbours' ``y_{k-1}`` are in (a lost neighbour, listed in ``missing``,
  counts as no data). The manager releases ticks at most ``lockstep_window`` ahead of the
  slowest agent. Since ``u_k`` depends only on the agent's own and its neighbours' outputs,
  the results are those of a swarm-wide barrier per tick, whatever the window.
* ``realtime`` — tick messages come on the wall-clock schedule and the agent runs the newest
  one; a tick message that arrives more than :data:`STALE_TICK_PERIODS` periods after its
  schedule (the agent was stalled and messages queued up) is skipped, and the next tick that
  runs reports how many were skipped and may use older neighbour outputs.
"""

from __future__ import annotations

import argparse
import logging
import math
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from types import FrameType
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.agent_config import (  # also this module's interface
    AgentConfig,
    AgentConfigError,
    AgentHardware,
    build_hardware,
)
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.lifecycle import AgentLifecycle
from hilswarm.agents.telemetry import TelemetryBatcher

logger = logging.getLogger(__name__)

__all__ = [
    "MANAGER_NAME",
    "Agent",
    "AgentConfig",
    "AgentConfigError",
    "AgentHardware",
    "StopRequestedError",
    "build_hardware",
    "main",
    "run_agent",
]

#: How long an agent waits for the router, its publishers' subscribers and the manager [s].
DEFAULT_STARTUP_TIMEOUT_S = 20.0
#: Realtime: a tick message later than this many periods after its schedule is skipped.
STALE_TICK_PERIODS = 1.5
#: Realtime: how fast the estimate of the bus delay forgets its minimum [periods per tick].
DELAY_ESTIMATE_RELAX = 0.01
#: Neighbour outputs kept per neighbour older than this agent's last tick [ticks].
NEIGHBOUR_HISTORY = 4
#: Bound on the neighbour outputs kept per neighbour (newer ones included) [ticks].
MAX_NEIGHBOUR_HISTORY = 2048
#: Vehicle telemetry channels not published: they would repeat ``/<agent>/{y,u,x_hat}``,
#: which the tick path records already.
DUPLICATE_CHANNELS = ("y", "u", "x_hat")


class StopRequestedError(HilswarmError, RuntimeError):
    """The agent was told to stop (signal, lost manager) before it was running.

    Args:
        message: what happened.
        orderly: ``True`` when the stop was asked for (a signal), ``False`` for a fault.
    """

    def __init__(self, message: str, *, orderly: bool = False) -> None:
        super().__init__(message)
        self.orderly = orderly


# ---------------------------------------------------------------------------------------------
# The agent
# ---------------------------------------------------------------------------------------------

# Main-thread queue items: (kind, payload...). Rare: never one per tick.
_SET, _MANAGER_GONE, _SIGNAL, _FAILED, _WAKE = range(5)
#: No agent missing (the common tick).
_NOBODY: frozenset[str] = frozenset()


class Agent:
    """One agent on the bus (see the module docstring).

    Args:
        config: what to build and where it sits in the graph.
        endpoints: Zenoh endpoints to connect to (the orchestrator's router or a zenohd).
        hardware_factory: builds vehicle/board/controller from the config and the bus
            endpoints (keyword ``endpoints``; tests may pass their own).
        clock: monotonic clock [s] used for tick timings.
        startup_timeout_s: bound on waiting for the bus and the manager.
    """

    def __init__(
        self,
        config: AgentConfig,
        endpoints: Sequence[str],
        *,
        hardware_factory: Callable[..., AgentHardware] = build_hardware,
        clock: Callable[[], float] = time.perf_counter,
        startup_timeout_s: float = DEFAULT_STARTUP_TIMEOUT_S,
    ) -> None:
        self.config = config
        self.endpoints = list(endpoints)
        self.keys = bus.BusKeys(config.experiment)
        self._hardware_factory = hardware_factory
        self._clock = clock
        self._startup_timeout_s = startup_timeout_s
        self._queue: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self.lifecycle = AgentLifecycle(on_transition=self._on_transition)
        self._session: zenoh.Session | None = None
        self._status_pub: zenoh.Publisher | None = None
        self._entities: list[Any] = []  # keep references: undeclared when dropped
        self.hardware: AgentHardware | None = None
        self.k = -1  # last tick answered
        self._u = np.zeros(0)
        self._y: np.ndarray | None = None
        self._neighbour_y: dict[str, dict[int, np.ndarray]] = {n: {} for n in config.neighbours}
        self._received_from: set[str] = set()
        # The engine lock serialises ticks (run by bus callbacks), commands and parameter
        # changes; it guards everything a tick reads or writes.
        self._engine_lock = threading.RLock()
        self._ticking = False  # ticks run only between arm and stop
        self._realtime = False  # set by every tick message (the manager's mode)
        self._horizon = -1  # highest tick released by the manager
        self._horizon_t = 0.0  # realtime: its experiment time [s]
        self._tick_missing: frozenset[str] = _NOBODY  # realtime: missing for the newest tick
        self._lost: frozenset[str] = _NOBODY  # lockstep: agents the manager reports lost
        self._delay_estimate = math.inf  # realtime: tick arrival - schedule, minimum [s]
        self._last_arrival = -math.inf  # realtime: arrival of the previous tick message [s]
        self._late_alone = False  # realtime: the previous tick message was late on its own
        self._stop_requested = ""
        self._manager_seen = threading.Event()
        self._queue_replay: list[tuple[Any, ...]] = []
        self._telemetry: TelemetryBatcher | None = None
        self._telemetry_pub: zenoh.Publisher | None = None
        self._telemetry_heads: dict[str, bytes] = {}
        self._telemetry_due = math.inf  # wall clock [s, self._clock] of the next batch
        self.telemetry_batches = 0

    # -- telemetry -------------------------------------------------------------------------

    def publish_telemetry(self) -> int:
        """Publish the telemetry rows appended since the previous batch; returns the row count.

        Does nothing before the publisher is declared or when nothing is new.
        """
        batcher, publisher = self._telemetry, self._telemetry_pub
        self._telemetry_due = self._clock() + bus.TELEMETRY_PERIOD_S
        if batcher is None or publisher is None:
            return 0
        rows = batcher.take()
        if not rows:
            return 0
        heads = self._telemetry_heads
        parts = []
        count = 0
        for channel, arrays in rows:
            head = heads.get(channel.name)
            if head is None:
                head = heads[channel.name] = bus.telemetry_channel_head(
                    channel.name, channel.fields
                )
            parts.append((head, arrays.k, arrays.t, arrays.values))
            count += arrays.k.shape[0]
        publisher.put(bus.encode_telemetry_batch(parts))
        self.telemetry_batches += 1
        return count

    # -- status ----------------------------------------------------------------------------

    def _on_transition(self, event: str, source: str, target: str, detail: str) -> None:
        logger.info("%s: %s -> %s (%s) %s", self.config.name, source, target, event, detail)
        if target == "safe":  # the rows up to the fault go out before the safe status
            self._publish_telemetry_safely()
        self.publish_status(
            {"kind": "transition", "event": event, "source": source, "state": target},
            detail=detail,
        )

    def publish_status(self, fields: Mapping[str, Any], *, detail: str = "") -> None:
        """Publish a status message (JSON) with the current tick and state."""
        if self._status_pub is None:
            return
        k = max(self.k, 0)
        message = {
            "agent": self.config.name,
            "state": self.lifecycle.state_id,
            "k": k,
            "t": k * self.config.dt,
            "detail": detail,
            **fields,
        }
        self._status_pub.put(bus.encode_json(message))

    # -- start-up --------------------------------------------------------------------------

    def _wait_for(self, event: threading.Event, what: str) -> None:
        """Wait (bounded) for ``event``, still honouring stop requests and the manager's loss."""
        deadline = time.monotonic() + self._startup_timeout_s
        while not event.wait(0.05):
            self._drain_startup_queue()
            if time.monotonic() > deadline:
                raise bus.BusConnectionError(
                    f"agent {self.config.name!r}: timed out after {self._startup_timeout_s} s "
                    f"waiting for {what}"
                )

    def _drain_startup_queue(self) -> None:
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item[0] in (_SIGNAL, _MANAGER_GONE):
                raise StopRequestedError(
                    f"agent {self.config.name!r}: {item[1]} during start-up",
                    orderly=item[0] == _SIGNAL,
                )
            self._queue_replay.append(item)

    def _watch_matching(self, publisher: zenoh.Publisher) -> threading.Event:
        """An event that is set exactly while ``publisher`` has matching subscribers."""
        event = threading.Event()

        def on_status(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                event.set()
            else:
                event.clear()

        self._entities.append(
            publisher.declare_matching_listener(zenoh.handlers.Callback(on_status, indirect=False))
        )
        if bus.has_subscribers(publisher):
            event.set()
        return event

    def _open_bus(self) -> zenoh.Session:
        session = bus.open_session(bus.client_config(self.endpoints))
        self._session = session
        self._status_pub = session.declare_publisher(
            self.keys.status(self.config.name), **bus.DATA_QOS
        )
        self._wait_for(
            self._watch_matching(self._status_pub),
            "the orchestrator to subscribe to the status key",
        )
        return session

    def _declare(self, session: zenoh.Session) -> None:
        keys, name, put = self.keys, self.config.name, self._queue.put
        guarded = self._guarded
        self._y_pub = session.declare_publisher(keys.y(name), **bus.TICK_PATH_QOS)
        self._u_pub = session.declare_publisher(keys.u(name), **bus.DATA_QOS)
        self._x_pub = session.declare_publisher(keys.x_hat(name), **bus.DATA_QOS)
        entities: list[Any] = [self._y_pub, self._u_pub, self._x_pub]
        telemetry = getattr(self.hardware.vehicle, "telemetry", None) if self.hardware else None
        if telemetry is not None and len(telemetry):
            self._telemetry = TelemetryBatcher(telemetry, skip=DUPLICATE_CHANNELS)
            self._telemetry_pub = session.declare_publisher(
                keys.telemetry_batches(name), **bus.DATA_QOS
            )
            entities.append(self._telemetry_pub)
            self._telemetry_due = self._clock() + bus.TELEMETRY_PERIOD_S
        for neighbour in self.config.neighbours:
            entities.append(
                session.declare_subscriber(
                    keys.y(neighbour),
                    zenoh.handlers.Callback(
                        lambda s, n=neighbour: guarded(
                            self.receive_neighbour, n, s.payload.to_bytes()
                        ),
                        indirect=False,
                    ),
                )
            )
        entities.append(
            session.declare_subscriber(
                keys.tick,
                zenoh.handlers.Callback(
                    lambda s: guarded(self.receive_tick, s.payload.to_bytes()), indirect=False
                ),
            )
        )
        entities.append(
            session.declare_subscriber(
                keys.control,
                zenoh.handlers.Callback(
                    lambda s: guarded(self.receive_control, s.payload.to_bytes()),
                    indirect=False,
                ),
            )
        )
        entities.append(
            session.declare_queryable(
                keys.set(name), zenoh.handlers.Callback(lambda q: put((_SET, q)), indirect=False)
            )
        )
        entities.append(
            session.liveliness().declare_subscriber(
                keys.alive(MANAGER_NAME),
                zenoh.handlers.Callback(self._on_manager_liveliness, indirect=False),
                history=True,
            )
        )
        self._entities.extend(entities)
        # u and x_hat travel to the manager inside the y report; their own keys are published
        # only while someone else (a tool, a dashboard) subscribes to them.
        self._extra_listeners = (
            self._watch_matching(self._u_pub),
            self._watch_matching(self._x_pub),
        )
        self._wait_for(self._watch_matching(self._y_pub), "the manager to subscribe to y")
        self._wait_for(self._manager_seen, "the instance manager's liveliness token")
        # Declared last: once the manager sees the token, every declaration above is known.
        self._entities.append(session.liveliness().declare_token(keys.alive(name)))

    def _on_manager_liveliness(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._manager_seen.set()
        else:
            self._queue.put((_MANAGER_GONE, "the instance manager disappeared"))

    # -- main loop -------------------------------------------------------------------------

    def run(self) -> int:
        """Run until stopped; returns the process exit status (0 clean stop, 1 failure)."""
        status = 1
        try:
            session = self._open_bus()
            self.lifecycle.connect()
            self.use_hardware(self._hardware_factory(self.config, endpoints=self.endpoints))
            self._attach_pose_source(session)
            self.lifecycle.configure()
            self._declare(session)
            self.lifecycle.arm(detail=f"neighbours: {', '.join(self.config.neighbours) or '-'}")
            for item in self._queue_replay:
                self._queue.put(item)
            self._queue_replay.clear()
            with self._engine_lock:
                self._ticking = True
                self._advance()  # a tick released while arming runs now
            status = self._loop()
        except StopRequestedError as exc:
            self._halt()
            self._go_safe(str(exc), fault=not exc.orderly)
            status = 0
        except HilswarmError as exc:
            self._halt()
            logger.error("agent %s failed: %s", self.config.name, exc)
            self._go_safe(f"failed: {exc}")
        except Exception as exc:  # a bug in user code must still leave the vehicle safe
            self._halt()
            logger.exception("agent %s crashed", self.config.name)
            self._go_safe(f"crashed: {type(exc).__name__}: {exc}")
        finally:
            self._shutdown()
        return status

    def _attach_pose_source(self, session: zenoh.Session) -> None:
        """A bus pose source (mocap) subscribes to its body and waits for its first pose."""
        source = getattr(self.hardware.vehicle, "pose_source", None) if self.hardware else None
        attach = getattr(source, "attach_bus", None)
        if attach is not None:
            self._entities.extend(attach(session, self.keys))
            source.wait_first()

    def _halt(self) -> None:
        """No more ticks (waits for a tick in progress to finish)."""
        with self._engine_lock:
            self._ticking = False

    def _loop(self) -> int:
        """The main thread while running: rare work only (ticks run on the bus callbacks)."""
        get = self._queue.get
        while not self._stop_requested:
            try:
                item = get(timeout=0.25)
            except queue.Empty:
                item = None
            if item is not None:
                kind = item[0]
                if kind == _SET:
                    with self._engine_lock:
                        self._on_set(item[1])
                elif kind == _FAILED:
                    raise item[1]
                elif kind in (_MANAGER_GONE, _SIGNAL):
                    with self._engine_lock:
                        self._ticking = False
                        self._go_safe(str(item[1]), fault=kind == _MANAGER_GONE)
                        self._stop_requested = str(item[1])
            if self._clock() >= self._telemetry_due:
                with self._engine_lock:
                    self.publish_telemetry()
        with self._engine_lock:  # a stop command: the orderly end
            self._ticking = False
            self._go_safe(self._stop_requested, fault=False)
        return 0

    def _guarded(self, handler: Callable[..., None], *args: Any) -> None:
        """Run a bus callback's work; a failure goes to the main thread, which stops safely."""
        try:
            handler(*args)
        except Exception as exc:  # the main thread re-raises it: safe mode, exit status 1
            with self._engine_lock:
                self._ticking = False
            self._queue.put((_FAILED, exc))

    def use_hardware(self, hardware: AgentHardware) -> None:
        """Take the built vehicle/board/controller (``run`` does this with its factory)."""
        self.hardware = hardware
        self._u = np.zeros(int(hardware.vehicle.n_inputs))

    # -- ticks -------------------------------------------------------------------------------

    def receive_neighbour(self, name: str, payload: bytes) -> None:
        """A neighbour's y message (bus callback): store it; run a tick that waited for it.

        Raises:
            bus.BusMessageError: the message does not follow the vector layout.
        """
        k, _t, values = bus.decode_vector(payload)
        values.flags.writeable = False  # shared with the controller: read-only, no copy
        with self._engine_lock:
            history = self._neighbour_y[name]
            history[k] = values
            self._received_from.add(name)
            # Keep what a tick may still need: y_{self.k} and newer (a neighbour may run up
            # to a lockstep window ahead), and a few older ones for a realtime catch-up.
            while len(history) > 1:
                oldest = min(history)
                if oldest >= self.k - NEIGHBOUR_HISTORY and len(history) <= MAX_NEIGHBOUR_HISTORY:
                    break
                del history[oldest]
            if self._ticking and self._horizon > self.k and k >= self.k:
                self._advance()

    def receive_tick(self, payload: bytes, *, arrived: float | None = None) -> None:
        """A tick message (bus callback): release ticks up to its ``k`` and run what can run.

        Args:
            payload: the encoded :class:`~hilswarm.agents.bus.TickMessage`.
            arrived: when it arrived [s, this agent's clock]; default: now.

        Raises:
            bus.BusMessageError: the message does not follow the tick layout.
        """
        tick = bus.decode_tick(payload)
        arrived = self._clock() if arrived is None else arrived
        with self._engine_lock:
            if tick.missing:
                names = self.config.agent_names
                missing = frozenset(names[i] for i in tick.missing if i < len(names))
            else:
                missing = _NOBODY
            self._realtime = tick.realtime  # the manager's mode decides how ticks run
            if self._realtime:
                if tick.k <= self._horizon:
                    return  # duplicate or out of order
                if self._is_stale(tick.t, arrived):
                    return  # it queued up while this agent was stalled: a fresher one follows
                self._horizon, self._horizon_t, self._tick_missing = tick.k, tick.t, missing
            else:
                self._lost = self._lost | missing if missing else self._lost
                self._horizon = max(self._horizon, tick.k)
            if self._ticking:
                self._advance()

    def _is_stale(self, t: float, arrived: float) -> bool:
        """Realtime: did the tick of time ``t`` [s] queue up while this agent was stalled?

        Its delay (arrival on this agent's clock minus ``t``) is compared with the smallest
        delay seen (which slowly forgets, so a slower bus is accepted). A message more than
        :data:`STALE_TICK_PERIODS` late that arrives right behind the previous one (a burst of
        queued messages) is stale. A late one on its own runs; two in a row mean the schedule
        moved (a resume) or the bus got slower, and the second becomes the new reference.
        """
        dt = self.config.dt
        delay = arrived - t
        burst = arrived - self._last_arrival < 0.5 * dt
        self._last_arrival = arrived
        if delay - self._delay_estimate > STALE_TICK_PERIODS * dt:
            if burst and self.k >= 0:
                return True
            if self._late_alone:
                self._delay_estimate = delay
            self._late_alone = True
            return False
        self._late_alone = False
        self._delay_estimate = min(delay, self._delay_estimate + DELAY_ESTIMATE_RELAX * dt)
        return False

    def receive_control(self, payload: bytes) -> None:
        """A swarm-wide command (bus callback): handled at once, between ticks."""
        with self._engine_lock:
            self._on_control(payload)
        if self._stop_requested:
            self._queue.put((_WAKE,))

    def _advance(self) -> None:
        """Run every released tick whose inputs are in (call under the engine lock)."""
        dt = self.config.dt
        while self._ticking and self.k < self._horizon:
            if self._realtime:  # the newest released tick; those in between are skipped
                k = self._horizon
                skipped = k - self.k - 1 if self.k >= 0 else 0
                missing, stale_ok = self._tick_missing, skipped > 0
            else:
                k, skipped, missing, stale_ok = self.k + 1, 0, self._lost, False
            neighbours: dict[str, np.ndarray | None] | None = None
            if k > 0 and self._y is not None and self.lifecycle.state_id in ("armed", "running"):
                neighbours = self._gather(k - 1, missing, stale_ok)
                if neighbours is None:
                    return  # a neighbour's y_{k-1} is still on its way
            self._run_tick(k, self._horizon_t if self._realtime else k * dt, skipped, neighbours)

    def _gather(
        self, k_prev: int, missing: frozenset[str], stale_ok: bool
    ) -> dict[str, np.ndarray | None] | None:
        """Neighbours' y_{k_prev}, or ``None`` while one that is not missing is not in yet."""
        result: dict[str, np.ndarray | None] = {}
        for name in self.config.neighbours:
            history = self._neighbour_y[name]
            values = history.get(k_prev)
            if values is not None:
                result[name] = values
            elif name in missing:
                result[name] = None
            elif stale_ok:
                older = [k for k in history if k < k_prev]
                result[name] = history[max(older)] if older else None
            else:
                return None
        return result

    def _run_tick(
        self, k: int, t: float, skipped: int, neighbours: dict[str, np.ndarray | None] | None
    ) -> None:
        """Tick ``k`` with its inputs in: compute, apply, sense, publish (under the lock)."""
        if self.lifecycle.state_id == "armed":
            self.lifecycle.start()
        y_payload, report, u_new, x_hat = self.tick_work(
            k, t, skipped=skipped, neighbours=neighbours
        )
        self._y_pub.put(y_payload, attachment=report)
        if u_new is not None and self._extra_listeners[0].is_set():
            self._u_pub.put(bus.encode_vector(k, t - self.config.dt, u_new))
        if x_hat is not None and x_hat.size and self._extra_listeners[1].is_set():
            self._x_pub.put(bus.encode_vector(k, t - self.config.dt, x_hat))
        if self._clock() >= self._telemetry_due:
            self.publish_telemetry()

    def tick_work(
        self,
        k: int,
        t: float,
        *,
        skipped: int = 0,
        missing: frozenset[str] = frozenset(),
        neighbours: Mapping[str, np.ndarray | None] | None = None,
    ) -> tuple[bytes, bytes, np.ndarray | None, np.ndarray | None]:
        """The agent's own work for tick ``k`` at experiment time ``t`` [s], without the bus.

        Computes ``u_k`` from ``u_{k-1}``, ``y_{k-1}`` and the neighbours' ``y_{k-1}`` (those in
        ``missing`` count as no data), applies it, exchanges with the board, senses ``y_k`` and
        encodes it. Any failure of the controller or the vehicle/board puts the agent in safe
        mode; it still senses and answers.

        Args:
            k: tick index (> the last one handled).
            t: experiment time of the tick [s].
            skipped: ticks dropped before this one because the agent fell behind.
            missing: agents whose ``y_{k-1}`` the manager reports missing.
            neighbours: the neighbours' ``y_{k-1}`` (``None`` for no data) when already
                gathered; default: taken from what was received (absent: no data).

        Returns:
            ``(y message, tick report, u_k or None, x_hat_k or None)``: the payload and
            attachment to publish on the y key, and what was computed (``None``: no controller
            step this tick).
        """
        clock = self._clock
        lifecycle = self.lifecycle
        hw = self.hardware
        vehicle = hw.vehicle
        dt = self.config.dt
        t0 = clock()
        u_new: np.ndarray | None = None
        if k > 0 and self._y is not None and lifecycle.state_id == "running":
            if neighbours is None:
                with self._engine_lock:
                    everyone = missing | frozenset(self.config.neighbours)  # absent: no data
                    neighbours = self._gather(k - 1, everyone, False)
            try:
                u_new = hw.model.step(self._u, self._y, t=t - dt, neighbours=neighbours)
                u_new.flags.writeable = False  # ours alone: the next step needs no copy of it
            except Exception as exc:  # user controller code: any failure means safe mode
                logger.exception("%s: controller failed at tick %d", self.config.name, k)
                self._go_safe(f"controller failed at tick {k}: {type(exc).__name__}: {exc}")
                u_new = None
        t1 = t_link = clock()
        retries = _link_retries(hw.board)
        try:
            if u_new is not None and lifecycle.state_id == "running":
                vehicle.apply(u_new)
                self._u = u_new
            t_link = clock()
            if k > 0:  # tick 0 senses what connect() primed: the initial state
                vehicle.exchange()
            t2 = clock()
            y = vehicle.sense(k, t)
            if type(y) is not np.ndarray or y.dtype != np.float64:
                y = np.asarray(y, dtype=np.float64)
        except Exception as exc:  # board link or user vehicle code: safe mode, keep answering
            t2 = clock()
            logger.exception("%s: vehicle/board failed at tick %d", self.config.name, k)
            self._go_safe(f"vehicle/board failed at tick {k}: {type(exc).__name__}: {exc}")
            y = np.full(int(vehicle.n_outputs), np.nan)
        t3 = clock()
        self.k = k
        self._y = y
        x_hat = hw.model.x_hat if u_new is not None else None
        retries = _link_retries(hw.board) - retries
        timing = bus.AgentTiming(t1 - t0, t_link - t1, t3 - t2, skipped, t2 - t_link, retries)
        report = bus.encode_report(timing, u_new, x_hat)
        y_payload = bus.encode_vector(k, t, y)
        if getattr(vehicle, "safe_mode", False) and lifecycle.state_id != "safe":
            reason = getattr(vehicle, "safe_mode_reason", "") or "vehicle entered safe mode"
            lifecycle.enter_safe(detail=str(reason))
        return y_payload, report, u_new, x_hat

    # -- commands --------------------------------------------------------------------------

    def _on_control(self, payload: bytes) -> None:
        try:
            command, reason = bus.decode_control(payload)
        except bus.BusMessageError as exc:
            logger.warning("%s: %s", self.config.name, exc)
            return
        state = self.lifecycle.state_id
        if command is bus.ControlCommand.ESTOP:
            self._estop(reason or "e-stop")
        elif command is bus.ControlCommand.STOP:
            self._ticking = False  # no tick after a stop command; the main thread goes safe
            self._stop_requested = reason or "stop requested"
        elif command is bus.ControlCommand.PAUSE and state == "running":
            self.lifecycle.pause(detail=reason)
        elif command is bus.ControlCommand.RESUME and state == "paused":
            self.lifecycle.resume(detail=reason)

    def _estop(self, reason: str) -> None:
        hw = self.hardware
        if hw is not None:
            try:
                hw.vehicle.enter_safe_mode(f"e-stop: {reason}")
            except HilswarmError as exc:
                logger.error("%s: enter_safe_mode failed: %s", self.config.name, exc)
            if hw.board is not None:
                try:
                    hw.board.estop()
                except HilswarmError as exc:
                    logger.error("%s: board e-stop failed: %s", self.config.name, exc)
        if self.lifecycle.state_id not in ("safe", "stopped"):
            self.lifecycle.enter_safe(detail=f"e-stop: {reason}")

    def _go_safe(self, reason: str, *, fault: bool = True) -> None:
        """Vehicle to safe mode (outputs to safe values, pushed to the board) and state safe.

        ``fault=False`` marks an orderly stop (run completed, stop or signal): the vehicle logs
        it at INFO instead of WARNING.
        """
        if self.lifecycle.state_id in ("safe", "stopped"):
            return
        hw = self.hardware
        if hw is not None:
            try:
                if not getattr(hw.vehicle, "safe_mode", False):
                    if fault:
                        hw.vehicle.enter_safe_mode(reason)
                    else:
                        hw.vehicle.enter_safe_mode(reason, fault=False)
                hw.vehicle.exchange()  # push the safe values to the board now
            except HilswarmError as exc:
                logger.error("%s: could not make outputs safe: %s", self.config.name, exc)
        self.lifecycle.enter_safe(detail=reason)

    def _publish_telemetry_safely(self) -> None:
        """The last batch on the way out: a failure is logged, never stops the shutdown."""
        try:
            self.publish_telemetry()
        except (HilswarmError, zenoh.ZError) as exc:
            logger.error("%s: last telemetry batch not published: %s", self.config.name, exc)

    def _on_set(self, query: zenoh.Query) -> None:
        """Apply a parameter change between ticks and acknowledge it (query reply + status)."""
        try:
            request = bus.decode_json(query.payload.to_bytes() if query.payload else b"{}")
            changes = request.get("params")
            if not isinstance(changes, dict) or not changes:
                raise AgentConfigError("expected {'params': {name: value, ...}}")
            if self.hardware is None:
                raise AgentConfigError("the controller is not built yet")
            self.hardware.model.set_params(**changes)
        except HilswarmError as exc:
            query.reply_err(bus.encode_json({"ok": False, "error": str(exc)}))
            self.publish_status({"kind": "set", "ok": False}, detail=f"set refused: {exc}")
        else:
            applied = {name: self.hardware.model.params[name] for name in changes}
            ack = {"ok": True, "agent": self.config.name, "k": self.k, "params": _jsonable(applied)}
            query.reply(query.key_expr, bus.encode_json(ack))
            self.publish_status({"kind": "set", "ok": True}, detail=f"set {_jsonable(applied)}")
        finally:
            query.drop()

    # -- shutdown --------------------------------------------------------------------------

    def _shutdown(self) -> None:
        self._publish_telemetry_safely()
        self._telemetry_pub = None
        if self.lifecycle.state_id == "safe":
            received = sorted(self.received_from)
            self.lifecycle.stop(detail=f"received from: {', '.join(received) or '-'}")
        hw = self.hardware
        if hw is not None and hw.board is not None:
            try:
                hw.board.close()
            except HilswarmError as exc:
                logger.error("%s: closing the board failed: %s", self.config.name, exc)
        self._entities.clear()
        self._status_pub = None
        if self._session is not None:
            self._session.close()
            self._session = None

    def request_stop(self, reason: str) -> None:
        """Ask the main loop to go safe and stop (thread- and signal-safe)."""
        self._queue.put((_SIGNAL, reason))

    @property
    def received_from(self) -> frozenset[str]:
        """Agents whose output this agent actually received (neighbour-only delivery check)."""
        with self._engine_lock:
            return frozenset(self._received_from)


#: Name of the instance manager's liveliness token (``hilswarm/<exp>/alive/_manager``).
MANAGER_NAME = "_manager"


def _link_retries(board: Any) -> int:
    """Re-sends of board requests so far (0 for links that do not count them)."""
    return int(getattr(getattr(board, "stats", None), "retries", 0) or 0)


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def run_agent(config: AgentConfig, endpoints: Sequence[str]) -> int:
    """Run one agent in this process until stopped; SIGINT/SIGTERM stop it cleanly."""
    agent = Agent(config, endpoints)

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        agent.request_stop(f"signal {signal.Signals(signum).name}")

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return agent.run()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m hilswarm.agents.agent --connect ENDPOINT --config JSON``."""
    parser = argparse.ArgumentParser(prog="python -m hilswarm.agents.agent")
    parser.add_argument("--connect", action="append", required=True, help="Zenoh endpoint")
    parser.add_argument("--config", required=True, help="AgentConfig as JSON")
    parser.add_argument("-v", "--verbose", action="count", default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s agent %(process)d %(name)s: %(message)s",
    )
    try:
        config = AgentConfig.from_json(args.config)
    except HilswarmError as exc:
        logger.error("%s", exc)
        return 2
    return run_agent(config, args.connect)


if __name__ == "__main__":
    sys.exit(main())

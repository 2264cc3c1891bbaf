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

Threads (the agent is a thin adapter between the bus and its tick engine):

* **Bus callbacks** (Zenoh's threads) only decode and hand off: a tick or neighbour message
  goes into the pure :class:`~hilswarm.agents.tick_engine.TickEngine` (which tick runs when,
  with which inputs; under a lock held only for that call) and wakes the worker. They never
  touch the board or the controller and never block, so the bus session and the liveliness
  token stay alive whatever the board does. Any malformed message on any key is dropped and
  counted (``malformed`` in the status messages), never fatal.
* **The worker thread** runs ticks (controller, apply, board exchange, sense, publish y),
  parameter changes, pause/resume and the periodic telemetry batch, in that order between
  ticks. A board link fault (stall, unplug) puts the agent in ``degraded`` while the worker
  reconnects and re-applies the configuration, for up to the link's timeout
  (``Board.link_timeout_s``); past it the agent goes safe.
* **The main thread** handles rare work: signals, stop requests, the manager's disappearance,
  status counters, and the orderly end (it stops the worker, bounded, before making the
  vehicle safe).
* **E-stop** has its own path: the control callback hands ESTOP to the board at once
  (``Board.request_estop``: a frame written beside any exchange in progress, which keeps
  waiting for its own reply), so outputs go safe even while an exchange is blocked on a
  stalled board; the vehicle-level safe mode follows on the worker.

The vehicle's telemetry channels (``vehicle.telemetry``) go out in batches on
``agent/<name>/telemetry`` (:class:`~hilswarm.agents.telemetry_feed.TelemetryFeed`): the rows
appended since the previous batch, every :data:`~hilswarm.agents.bus.TELEMETRY_PERIOD_S`, and a
last batch when the agent goes safe or shuts down. A killed agent loses at most one period of
telemetry. A board link fault is ridden out with :mod:`hilswarm.agents.link_recovery`.

Status messages (JSON on ``agent/<name>/status``, recorded on ``/<agent>/status``; the
counters in :class:`~hilswarm.agents.agent_counters.AgentCounters`) carry
``agent``, ``state``, ``k``, ``t``, ``detail``, ``kind`` and, once any is non-zero, the input
counters: ``malformed`` (messages that could not be decoded, by key: ``tick``, ``y``,
``control``, ``set``, ``mocap``: body poses of a mocap pose source), ``dropped`` (well-formed
messages rejected by the tick engine, by reason: ``tick_ahead``, ``tick_past``, ``tick_time``,
``tick_mode``, ``tick_missing``, ``y_ahead``, ``y_duplicate``, ``y_size``, ``schedule_dt``,
``schedule_time``, and ``stale`` realtime ticks skipped), ``skipped`` (ticks this agent missed
in total), ``link_faults`` (board link faults ridden out) and ``stale_samples`` (board answers
marked STALE: with an XBee gateway in broadcast mode, the robot's last samples the gateway
answered with; the mode's normal operation, not a fault). A self-clocked realtime agent (it
keeps the manager's schedule itself, see :class:`~hilswarm.agents.bus.ScheduleMessage`) adds
``inputs_missing`` ({neighbour: [tick, ...]}): the ticks since its previous status that used
no data for that neighbour (its ``y_{k-1}`` was not in at the tick's due time) although the
manager had not reported it lost. A status of kind ``inputs`` is published when these
counters change or such ticks are pending (at most once per
:data:`~hilswarm.agents.agent_counters.COUNTERS_PERIOD_S`; :mod:`.agent_counters`), and
every status (the last one of the run included) carries the ticks noted since the previous
one.
"""

from __future__ import annotations

import argparse
import functools
import logging
import math
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import FrameType
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents import bus, bus_callback
from hilswarm.agents.agent_config import (  # also this module's interface
    AgentConfig,
    AgentConfigError,
    AgentHardware,
    build_hardware,
    tick_phase_s,
)
from hilswarm.agents.agent_counters import AgentCounters
from hilswarm.agents.credentials import Credentials
from hilswarm.agents.errors import BoardError, HilswarmError
from hilswarm.agents.lifecycle import AgentLifecycle
from hilswarm.agents.link_recovery import (
    LINK_FAULTS,
    QuitRequestedError,
    link_retries,
    link_stages,
    reconnect_within,
)
from hilswarm.agents.rehearsal import rehearse
from hilswarm.agents.scheduling import use_batch_scheduling
from hilswarm.agents.telemetry_feed import DUPLICATE_CHANNELS, TelemetryFeed
from hilswarm.agents.tick_engine import (  # noqa: F401 - re-exported: the engine's constants
    MAX_NEIGHBOUR_HISTORY,
    NEIGHBOUR_HISTORY,
    STALE_TICK_PERIODS,
    Tick,
    TickEngine,
    is_warmup,
    preroll_times,
)
from hilswarm.agents.timed_queue import get_within

logger = logging.getLogger(__name__)

__all__ = [
    "MANAGER_NAME",
    "Agent",
    "AgentAlreadyRunningError",
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
#: Bound on asking the router whether this agent's liveliness token is already there [s].
ALREADY_RUNNING_CHECK_S = 2.0
#: How long a stop waits for the worker to finish its tick before aborting the board link [s].
WORKER_STOP_WAIT_S = 0.5
#: How long it then waits for the aborted worker [s]; past it the agent stops without it.
WORKER_ABORT_WAIT_S = 1.0


class AgentAlreadyRunningError(HilswarmError, RuntimeError):
    """Another process already runs this agent on the run's bus (its liveliness token is
    there): a second one would publish the same outputs and steer the same vehicle."""


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
_MANAGER_GONE, _SIGNAL, _FAILED, _WAKE = range(4)
# Worker queue items: ``None`` (ticks may be ready) or (kind, payload...).
_W_SET, _W_CONTROL, _W_ESTOP, _W_QUIT = range(4)


def estop_reason(reason: str) -> str:
    """What an e-stop is recorded and logged as: ``"e-stop: <reason>"``, or ``"e-stop"`` when
    the command gave none (or only said "e-stop" again)."""
    reason = reason.strip()
    return f"e-stop: {reason}" if reason and reason.lower() != "e-stop" else "e-stop"


class Agent:
    """One agent on the bus (see the module docstring).

    Args:
        config: what to build and where it sits in the graph.
        endpoints: Zenoh endpoints to connect to (the orchestrator's router or a zenohd).
        security: the agent's credentials for the run's router (``None``: none).
        hardware_factory: builds vehicle/board/controller from the config, the bus endpoints
            and the credentials (keywords ``endpoints``, ``security``; tests may pass their
            own).
        clock: monotonic clock [s] used for tick timings.
        startup_timeout_s: bound on waiting for the bus and the manager.
        own_process: the agent owns its process (:func:`run_agent`): a lockstep run then puts
            the process's threads under ``SCHED_BATCH`` at its first tick
            (:mod:`hilswarm.agents.scheduling`); off for an agent inside another program.
    """

    def __init__(
        self,
        config: AgentConfig,
        endpoints: Sequence[str],
        *,
        security: bus.SessionSecurity | None = None,
        hardware_factory: Callable[..., AgentHardware] = build_hardware,
        clock: Callable[[], float] = time.perf_counter,
        startup_timeout_s: float = DEFAULT_STARTUP_TIMEOUT_S,
        own_process: bool = False,
    ) -> None:
        self.config = config
        self._own_process = own_process
        self.endpoints = list(endpoints)
        self.keys = bus.BusKeys(config.experiment, config.run_id)
        self._security = security
        self._hardware_factory = hardware_factory
        self._clock = clock
        self._startup_timeout_s = startup_timeout_s
        self._queue: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        # Lifecycle transitions come from the worker (ticks, link faults), the control callback
        # (e-stop) and the main thread (the end): one at a time.
        self._state_lock = threading.RLock()
        self.lifecycle = AgentLifecycle(on_transition=self._on_transition)
        self._session: zenoh.Session | None = None
        self._status_pub: zenoh.Publisher | None = None
        self._entities: list[Any] = []  # keep references: undeclared when dropped
        self.hardware: AgentHardware | None = None
        self.k = -1  # last tick answered
        self._u = np.zeros(0)
        self._y: np.ndarray | None = None
        #: Which tick runs when, with which inputs; guarded by the engine lock, which is held
        #: only for the engine's own short calls (never around board I/O or the controller).
        self.engine = TickEngine(
            config.neighbours,
            config.agent_names,
            config.dt,
            config.lockstep_window,
            phase_s=tick_phase_s(config),
        )
        #: A mocap pose source's ``tick_due`` (told each self-clocked tick's due time, so a
        #: sense can wait for its own frame's pose), or ``None``.
        self._tick_due_hint: Callable[[float], None] | None = None
        self._engine_lock = threading.Lock()
        #: The input and fault counters of the status messages.
        self.status_counters = AgentCounters(self.engine, self._engine_lock)
        self._link_down = False  # the board link failed for good: no more exchanges
        self._work: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._wake_pending = False
        self._worker: threading.Thread | None = None
        self._quitting = threading.Event()  # set when the worker must finish
        self._stop_requested = ""
        self._manager_seen = threading.Event()
        self._queue_replay: list[tuple[Any, ...]] = []
        self._telemetry: TelemetryFeed | None = None  # the vehicle's telemetry, if it has any
        self._extra_listeners: tuple[threading.Event, threading.Event] = (
            threading.Event(),
            threading.Event(),
        )

    # -- telemetry -------------------------------------------------------------------------

    def publish_telemetry(self) -> int:
        """Publish the telemetry rows appended since the previous batch; returns the row count.

        Does nothing before the publisher is declared, after shutdown or when nothing is new.
        Called by the thread that owns the hardware (the worker while it runs, else the main
        thread).
        """
        feed = self._telemetry
        return 0 if feed is None else feed.publish(self._clock())

    @property
    def telemetry_batches(self) -> int:
        """Telemetry batches published so far."""
        feed = self._telemetry
        return 0 if feed is None else feed.batches

    @property
    def _telemetry_due(self) -> float:
        """When the next telemetry batch is due [s, the agent's clock]; ``inf``: never."""
        feed = self._telemetry
        return math.inf if feed is None else feed.due

    def _owns_hardware(self) -> bool:
        """True on the thread that may touch the vehicle, board and telemetry right now."""
        worker = self._worker
        if worker is not None and worker.is_alive():
            return threading.current_thread() is worker
        return True

    # -- status ----------------------------------------------------------------------------

    def _on_transition(self, event: str, source: str, target: str, detail: str) -> None:
        logger.info("%s: %s -> %s (%s) %s", self.config.name, source, target, event, detail)
        if target == "safe" and self._owns_hardware():  # rows up to the fault first
            self._publish_telemetry_safely()
        self.publish_status(
            {"kind": "transition", "event": event, "source": source, "state": target},
            detail=detail,
        )

    def _transition(self, event: str, detail: str) -> bool:
        """Fire lifecycle ``event`` if the current state allows it (any thread)."""
        with self._state_lock:
            if all(e.id != event for e in self.lifecycle.allowed_events):
                return False
            self.lifecycle.send(event, detail=detail)
            return True

    def counters(self) -> dict[str, Any]:
        """The input and fault counters of status messages (non-zero ones only)."""
        return self.status_counters.fields()

    @property
    def malformed(self) -> dict[str, int]:
        """Messages that could not be decoded, by key (see the module docstring)."""
        return self.status_counters.malformed

    @property
    def skipped(self) -> int:
        """Ticks this agent missed in total."""
        return self.status_counters.skipped

    @property
    def link_faults(self) -> int:
        """Board link faults ridden out (or not)."""
        return self.status_counters.link_faults

    def publish_status(self, fields: Mapping[str, Any], *, detail: str = "") -> None:
        """Publish a status message (JSON) with the current tick, state and counters."""
        if self._status_pub is None:
            return
        k = max(self.k, 0)
        message = {
            "agent": self.config.name,
            "state": self.lifecycle.state_id,
            "k": k,
            "t": k * self.config.dt,
            "detail": detail,
            **self.counters(),
            **fields,
        }
        self._status_pub.put(bus.encode_json(message))

    def _publish_changed_counters(self) -> None:
        """A status of kind ``inputs`` when the counters changed since the last one (at most
        once per :data:`~hilswarm.agents.agent_counters.COUNTERS_PERIOD_S`)."""
        if self.status_counters.changed(self._clock()):
            self.publish_status({"kind": "inputs"}, detail="input and fault counters")

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
            if self._stop_requested:
                raise StopRequestedError(
                    f"agent {self.config.name!r}: {self._stop_requested} during start-up",
                    orderly=True,
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

        self._entities.append(publisher.declare_matching_listener(bus_callback.callback(on_status)))
        if bus.has_subscribers(publisher):
            event.set()
        return event

    def _open_bus(self) -> zenoh.Session:
        session = bus.open_session(bus.client_config(self.endpoints, security=self._security))
        self._session = session
        self._refuse_if_running(session)  # before anything of this agent is on the bus
        self._status_pub = session.declare_publisher(
            self.keys.status(self.config.name), **bus.DATA_QOS
        )
        self._wait_for(
            self._watch_matching(self._status_pub),
            "the orchestrator to subscribe to the status key",
        )
        return session

    def _refuse_if_running(self, session: zenoh.Session) -> None:
        """Raise :class:`AgentAlreadyRunningError` when this agent's liveliness token is on
        the bus already: another process runs it (``hilswarm agent`` for an agent the run
        started itself, or the same remote agent started twice). Checked before this process
        declares anything or opens its board, so the running agent is left undisturbed."""
        name = self.config.name
        replies = session.liveliness().get(self.keys.alive(name), timeout=ALREADY_RUNNING_CHECK_S)
        if any(reply.ok is not None for reply in replies):
            raise AgentAlreadyRunningError(
                f"agent {name!r} is already running in {self.keys.experiment} "
                f"(run {self.keys.run_id or '-'}): another process holds its place on the bus. "
                "A run starts every agent itself except those given with --remote; "
                "start only those with `hilswarm agent`, each once"
            )

    def _declare(self, session: zenoh.Session) -> None:
        keys, name = self.keys, self.config.name
        self._y_pub = session.declare_publisher(keys.y(name), **bus.TICK_PATH_QOS)
        self._u_pub = session.declare_publisher(keys.u(name), **bus.DATA_QOS)
        self._x_pub = session.declare_publisher(keys.x_hat(name), **bus.DATA_QOS)
        entities: list[Any] = [self._y_pub, self._u_pub, self._x_pub]
        telemetry = getattr(self.hardware.vehicle, "telemetry", None) if self.hardware else None
        if telemetry is not None and len(telemetry):
            publisher = session.declare_publisher(keys.telemetry_batches(name), **bus.DATA_QOS)
            entities.append(publisher)
            self._telemetry = TelemetryFeed(
                telemetry, publisher, now=self._clock(), skip=DUPLICATE_CHANNELS
            )
        receive_neighbour, put_work = self.receive_neighbour, self._work.put
        for neighbour in self.config.neighbours:
            entities.append(
                session.declare_subscriber(
                    keys.y(neighbour),
                    bus_callback.callback(
                        lambda s, n=neighbour: receive_neighbour(n, s.payload.to_bytes())
                    ),
                )
            )
        receive_tick, receive_control = self.receive_tick, self.receive_control
        entities.append(
            session.declare_subscriber(
                keys.tick,
                bus_callback.callback(lambda s: receive_tick(s.payload.to_bytes())),
            )
        )
        entities.append(
            session.declare_subscriber(
                keys.control,
                bus_callback.callback(lambda s: receive_control(s.payload.to_bytes())),
            )
        )
        entities.append(
            session.declare_queryable(
                keys.set(name),
                bus_callback.callback(lambda q: put_work((_W_SET, q))),
            )
        )
        entities.append(
            session.liveliness().declare_subscriber(
                keys.alive(MANAGER_NAME),
                bus_callback.callback(self._on_manager_liveliness),
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

    # -- main thread -----------------------------------------------------------------------

    def run(self) -> int:
        """Run until stopped; returns the process exit status (0 clean stop, 1 failure)."""
        status = 1
        try:
            session = self._open_bus()
            self._transition("connect", "")
            self.use_hardware(
                self._hardware_factory(
                    self.config, endpoints=self.endpoints, security=self._security
                )
            )
            self._attach_pose_source(session)
            self._transition("configure", "")
            self._declare(session)
            took = rehearse(type(self), self.config)  # the tick path warm before "armed"
            if took is not None:
                logger.debug("%s: rehearsed in %.1f ms", self.config.name, took * 1e3)
            self._transition("arm", f"neighbours: {', '.join(self.config.neighbours) or '-'}")
            for item in self._queue_replay:
                self._queue.put(item)
            self._queue_replay.clear()
            if self._stop_requested:
                raise StopRequestedError(self._stop_requested, orderly=True)
            self._start_worker()
            status = self._loop()
        except StopRequestedError as exc:
            self._finish(str(exc), fault=not exc.orderly)
            status = 0
        except AgentAlreadyRunningError as exc:  # nothing of ours on the bus: nothing to undo
            logger.error("%s", exc)
            status = 2
        except HilswarmError as exc:
            logger.error("agent %s failed: %s", self.config.name, exc)
            self._finish(f"failed: {exc}", fault=True)
        except Exception as exc:  # a bug in user code must still leave the vehicle safe
            logger.exception("agent %s crashed", self.config.name)
            self._finish(f"crashed: {type(exc).__name__}: {exc}", fault=True)
        finally:
            self._shutdown()
        return status

    def _attach_pose_source(self, session: zenoh.Session) -> None:
        """A bus pose source (mocap) subscribes to its body and waits for its first pose."""
        source = getattr(self.hardware.vehicle, "pose_source", None) if self.hardware else None
        attach = getattr(source, "attach_bus", None)
        if attach is not None:
            if hasattr(source, "on_malformed"):  # undecodable poses: malformed["mocap"]
                source.on_malformed = functools.partial(self._count_malformed, "mocap")
            self._entities.extend(attach(session, self.keys))
            source.wait_first()
        self._tick_due_hint = getattr(source, "tick_due", None)

    def _start_worker(self) -> None:
        with self._engine_lock:
            self.engine.running = True
        self._worker = threading.Thread(
            target=self._work_loop, name=f"agent-{self.config.name}-worker", daemon=True
        )
        self._worker.start()
        self._wake()  # a tick released while arming runs now

    def _loop(self) -> int:
        """The main thread while running: rare work only (ticks run on the worker)."""
        events = self._queue
        while not self._stop_requested:
            try:
                item = get_within(events, 0.25)
            except queue.Empty:
                item = None
            if item is not None:
                kind = item[0]
                if kind == _FAILED:
                    raise item[1]
                if kind in (_MANAGER_GONE, _SIGNAL):
                    self._finish(str(item[1]), fault=kind == _MANAGER_GONE)
                    return 0
            self._publish_changed_counters()
        self._finish(self._stop_requested, fault=False)  # a stop command: the orderly end
        return 0

    def _finish(self, reason: str, *, fault: bool) -> None:
        """Stop ticking, stop the worker (bounded) and make the vehicle safe.

        The worker finishes the tick in progress; one blocked on a stalled board is aborted
        (the board link gives up), and one that does not return even then is left behind:
        the outputs go safe through the e-stop path and the agent stops without it.
        """
        with self._engine_lock:
            self.engine.running = False
        self._stop_requested = self._stop_requested or reason
        if not self._stop_worker():
            hw = self.hardware
            sent = hw is not None and hw.board is not None and hw.board.request_estop()
            logger.error(
                "%s: the worker did not stop (board link blocked); outputs made safe %s",
                self.config.name,
                "by e-stop" if sent else "by the board's watchdog",
            )
            self._transition("enter_safe", f"{reason} (board link blocked)")
            return
        self._go_safe(reason, fault=fault)

    def _stop_worker(self) -> bool:
        """Tell the worker to quit and wait for it (bounded); ``True`` once it has stopped."""
        worker = self._worker
        if worker is None:
            return True
        self._quitting.set()
        self._work.put((_W_QUIT,))
        worker.join(WORKER_STOP_WAIT_S)
        if worker.is_alive() and self.hardware is not None and self.hardware.board is not None:
            self.hardware.board.abort()
            worker.join(WORKER_ABORT_WAIT_S)
        return not worker.is_alive()

    def use_hardware(self, hardware: AgentHardware) -> None:
        """Take the built vehicle/board/controller (``run`` does this with its factory)."""
        self.hardware = hardware
        self.status_counters.board = hardware.board
        self._u = np.zeros(int(hardware.vehicle.n_inputs))
        add_listener = getattr(hardware.board, "add_link_listener", None)
        if add_listener is not None:
            add_listener(self._on_link_event)

    def _on_link_event(self, kind: str, detail: str) -> None:
        """A board link event, on the thread whose request met it (the worker's exchange)."""
        if kind == "disconnected" and self.lifecycle.state_id == "running":
            self.status_counters.link_faults += 1
            self._transition("degrade", f"board link lost at tick {self.k + 1}: {detail}")
        elif kind == "reconnected":
            self._transition("recover", f"board link back: {detail}")

    # -- bus callbacks: decode and hand off ------------------------------------------------

    def _count_malformed(self, key: str) -> None:
        self.status_counters.count_malformed(key)  # several bus threads may count at once

    def _wake(self) -> None:
        """Wake the worker (one token at a time: the worker takes every ready tick)."""
        if not self._wake_pending:
            self._wake_pending = True
            self._work.put(None)

    def receive_neighbour(self, name: str, payload: bytes) -> None:
        """A neighbour's y message (bus callback): into the engine; wake a tick that waits.

        A malformed message is counted (``malformed["y"]``) and dropped.
        """
        try:
            k, _t, values = bus.decode_vector(payload)
        except bus.BusMessageError:
            self._count_malformed("y")
            return
        if is_warmup(k):
            return  # the pre-roll's: the path is warm, nothing to keep
        values.flags.writeable = False  # shared with the controller: read-only, no copy
        arrived = self._clock()
        with self._engine_lock:
            ready = self.engine.on_neighbour(name, k, values, arrived)
        if ready:
            self._wake()

    def receive_tick(self, payload: bytes, *, arrived: float | None = None) -> None:
        """A tick or schedule message (bus callback): into the engine; wake the worker if a
        tick is ready (or, for a schedule, so it waits for the next tick's due time).

        Args:
            payload: the encoded :class:`~hilswarm.agents.bus.TickMessage` or
                :class:`~hilswarm.agents.bus.ScheduleMessage`; a malformed one is counted
                (``malformed["tick"]``) and dropped.
            arrived: when it arrived [s, this agent's clock]; default: now.
        """
        try:
            if bus.is_schedule(payload):
                schedule = bus.decode_schedule(payload)
                tick = None
            else:
                tick = bus.decode_tick(payload)
        except bus.BusMessageError:
            self._count_malformed("tick")
            return
        arrived = self._clock() if arrived is None else arrived
        with self._engine_lock:
            if tick is None:
                accepted = self.engine.on_schedule(
                    schedule.first,
                    schedule.last,
                    schedule.t0,
                    schedule.dt,
                    missing=schedule.missing,
                    arrived=arrived,
                )
            else:
                accepted = self.engine.on_tick(tick.k, tick.t, tick.missing, tick.realtime, arrived)
        if accepted:
            self._wake()

    def receive_control(self, payload: bytes) -> None:
        """A swarm-wide command (bus callback). ESTOP goes to the board at once (its own path);
        STOP ends ticking at once; pause and resume are handled by the worker between ticks.
        """
        try:
            command, reason = bus.decode_control(payload)
        except bus.BusMessageError:
            self._count_malformed("control")
            return
        if command is bus.ControlCommand.ESTOP:
            self._estop_now(estop_reason(reason))
        elif command is bus.ControlCommand.STOP:
            with self._engine_lock:
                self.engine.running = False  # no tick after a stop command
            self._stop_requested = reason or "stop requested"
            self._queue.put((_WAKE,))
        else:
            self._work.put((_W_CONTROL, command, reason))

    def _estop_now(self, reason: str) -> None:
        """E-stop: the board's own path now, the state at once, the vehicle on the worker.

        ``reason``: as :func:`estop_reason` words it."""
        hw = self.hardware
        if hw is not None and hw.board is not None:
            hw.board.request_estop()
        self._transition("enter_safe", reason)
        self._work.put((_W_ESTOP, reason))

    # -- the worker thread -----------------------------------------------------------------

    def _work_loop(self) -> None:
        """The worker: ticks, then commands between ticks, then the telemetry batch."""
        work, engine, lock, clock = self._work, self.engine, self._engine_lock, self._clock
        preroll: list[float] = []  # self-clocked: when the warm-up outputs are due [s]
        try:
            while True:
                with lock:
                    due = engine.next_due()  # self-clocked: the next tick's deadline
                if due is not None and engine.k < 0 and self.lifecycle.armed.is_active:
                    # Self-clocked: the schedule is in, tick 0 is due in the lead the manager
                    # gives. Leave ``armed`` now, not on tick 0: the transition and its status
                    # message cost ~0.6 ms of CPU in every agent at once (docs/running.md).
                    self._transition("start", "schedule received")
                    now = clock()
                    preroll = [t for t in preroll_times(due, self.config.dt) if t > now]
                timeout = self._telemetry_due if due is None else min(due, self._telemetry_due)
                if preroll:
                    timeout = min(timeout, preroll[0])
                timeout -= clock()
                try:
                    item = get_within(work, min(timeout, 1.0))
                except queue.Empty:
                    item = None
                self._wake_pending = False
                if item is not None:
                    if item[0] == _W_QUIT:
                        return
                    self._handle_work(item)
                if preroll and clock() >= preroll[0]:
                    self._put_warmup(-len(preroll))
                    while preroll and clock() >= preroll[0]:
                        del preroll[0]  # late ones are skipped, never sent in a burst
                self._run_ready_ticks()
                if self._clock() >= self._telemetry_due:
                    self.publish_telemetry()
        except QuitRequestedError:
            return
        except Exception as exc:  # the main thread re-raises it: safe mode, exit status 1
            with self._engine_lock:
                self.engine.running = False
            self._queue.put((_FAILED, exc))

    def _put_warmup(self, k: int) -> None:
        """Put the pre-roll's warm-up output ``k`` (< 0) on the y key
        (:func:`~hilswarm.agents.tick_engine.preroll_times`): NaN values of the vehicle's
        size and an empty report, which every receiver ignores."""
        hw = self.hardware
        if hw is None or self.engine.k >= 0 or self.lifecycle.state_id != "running":
            return
        values = np.full(int(hw.vehicle.n_outputs), np.nan)
        report = bus.encode_report(bus.AgentTiming(), None, None)
        self._y_pub.put(bus.encode_vector(k, k * self.config.dt, values), attachment=report)

    def _run_ready_ticks(self) -> None:
        """Run every tick the engine hands out (released, inputs in)."""
        engine, lock, lifecycle, clock = self.engine, self._engine_lock, self.lifecycle, self._clock
        while not self._quitting.is_set():
            gather = self._y is not None and lifecycle.state_id in ("armed", "running")
            now = clock()
            with lock:
                tick = engine.take(gather=gather, now=now)
            if tick is None:
                return
            self._run_tick(tick)

    def _use_batch_scheduling(self) -> None:
        """Lockstep: this process's threads under ``SCHED_BATCH`` (a throughput job; see
        :mod:`hilswarm.agents.scheduling`). A refusal only costs speed: logged, not fatal."""
        try:
            switched = use_batch_scheduling()
        except OSError as exc:
            logger.warning("%s: lockstep under the default CPU policy: %s", self.config.name, exc)
            return
        logger.debug("%s: %d threads under SCHED_BATCH (lockstep)", self.config.name, switched)

    def _handle_work(self, item: tuple[Any, ...]) -> None:
        kind = item[0]
        if kind == _W_SET:
            self._on_set(item[1])
        elif kind == _W_CONTROL:
            command, reason = item[1], item[2]
            if command is bus.ControlCommand.PAUSE:
                self._transition("pause", reason)
            elif command is bus.ControlCommand.RESUME:
                self._transition("resume", reason)
        elif kind == _W_ESTOP:
            self._estop(item[1])

    def _run_tick(self, tick: Tick) -> None:
        """Tick ``k`` with its inputs in: compute, apply, sense, publish (on the worker)."""
        # Ticked: the first tick starts the run (by the state's id: every tick asks, and
        # ``armed.is_active`` costs ~0.9 µs to the id's 0.05 µs).
        if self.lifecycle.state_id == "armed":
            self._transition("start", "")
            if self._own_process and self.engine.realtime is False:
                self._use_batch_scheduling()
        k, t = tick.k, tick.t
        hint = self._tick_due_hint
        if hint is not None and tick.due == tick.due:  # self-clocked (not NaN)
            hint(tick.due)
        y_payload, report, u_new, x_hat = self.tick_work(
            k, t, skipped=tick.skipped, neighbours=tick.neighbours
        )
        self._y_pub.put(y_payload, attachment=report)
        if u_new is not None and self._extra_listeners[0].is_set():
            self._u_pub.put(bus.encode_vector(k, t - self.config.dt, u_new))
        if x_hat is not None and x_hat.size and self._extra_listeners[1].is_set():
            self._x_pub.put(bus.encode_vector(k, t - self.config.dt, x_hat))

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
        encodes it. A board link fault is ridden out (``degraded``, reconnect, same tick again)
        up to the link's timeout; any other failure of the controller or the vehicle/board, or
        a link that does not come back, puts the agent in safe mode; it still senses and
        answers.

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
                    engine = self.engine
                    engine.k = max(engine.k, k)  # called directly (tests, benchmarks)
                    everyone = missing | frozenset(self.config.neighbours)  # absent: no data
                    neighbours = engine.gather(k - 1, everyone, False)
            try:
                u_new = hw.model.step(self._u, self._y, t=t - dt, neighbours=neighbours)
                u_new.flags.writeable = False  # ours alone: the next step needs no copy of it
            except Exception as exc:  # user controller code: any failure means safe mode
                logger.exception("%s: controller failed at tick %d", self.config.name, k)
                self._go_safe(f"controller failed at tick {k}: {type(exc).__name__}: {exc}")
                u_new = None
        t1 = t_link = clock()
        retries = link_retries(hw.board)
        try:
            if u_new is not None and lifecycle.state_id == "running":
                vehicle.apply(u_new)
                self._u = u_new
            t_link = clock()
            if k > 0 and not self._link_down:  # tick 0 senses what connect() primed
                try:
                    vehicle.exchange()
                except LINK_FAULTS as exc:
                    self._ride_out_link_fault(exc, k)
                    vehicle.exchange()
            t2 = clock()
            y = vehicle.sense(k, t)
            if type(y) is not np.ndarray or y.dtype != np.float64:
                y = np.asarray(y, dtype=np.float64)
        except QuitRequestedError:
            raise
        except Exception as exc:  # board link or user vehicle code: safe mode, keep answering
            t2 = clock()
            if isinstance(exc, LINK_FAULTS):
                logger.error("%s: board link failed at tick %d: %s", self.config.name, k, exc)
                self._link_down = True
            else:
                logger.exception("%s: vehicle/board failed at tick %d", self.config.name, k)
            self._go_safe(f"vehicle/board failed at tick {k}: {type(exc).__name__}: {exc}")
            y = np.full(int(vehicle.n_outputs), np.nan)
        t3 = clock()
        self.k = k
        self._y = y
        if skipped:
            self.status_counters.skipped += skipped
        x_hat = hw.model.x_hat if u_new is not None else None
        retries = link_retries(hw.board) - retries
        stages = link_stages(hw.board, k > 0)  # the XBee gateway's part of link_s, if any
        timing = bus.AgentTiming(
            t1 - t0, t_link - t1, t3 - t2, skipped, t2 - t_link, retries, *stages
        )
        report = bus.encode_report(timing, u_new, x_hat)
        y_payload = bus.encode_vector(k, t, y)
        if getattr(vehicle, "safe_mode", False) and lifecycle.state_id != "safe":
            reason = getattr(vehicle, "safe_mode_reason", "") or "vehicle entered safe mode"
            self._transition("enter_safe", str(reason))
        return y_payload, report, u_new, x_hat

    def _ride_out_link_fault(self, fault: BoardError, k: int) -> None:
        """The board link failed at tick ``k``: ``degraded``, reconnect until the link's timeout.

        Returns once the link is back and configured (``running`` again; the caller repeats
        the exchange). Past the timeout it raises the last error (the caller goes safe).
        """
        board = self.hardware.board if self.hardware is not None else None
        timeout = float(getattr(board, "link_timeout_s", 0.0) or 0.0)
        state = self.lifecycle.state_id
        if board is None or timeout <= 0 or self._quitting.is_set() or state == "safe":
            raise fault
        start = self._clock()
        if state != "degraded":  # (a lost port made it degraded already)
            self.status_counters.link_faults += 1
            self._transition("degrade", f"board link fault at tick {k}: {fault}")
        attempts = reconnect_within(board, timeout, fault, self._quitting, self._clock)
        self._transition(
            "recover",
            f"board link back after {self._clock() - start:.2f} s ({attempts} attempts); "
            "configuration re-applied",
        )

    # -- commands --------------------------------------------------------------------------

    def _estop(self, reason: str) -> None:
        """The vehicle side of an e-stop (on the worker; the board got it on its own path)."""
        hw = self.hardware
        if hw is not None:
            try:
                hw.vehicle.enter_safe_mode(reason)
            except HilswarmError as exc:
                logger.error("%s: enter_safe_mode failed: %s", self.config.name, exc)
            if hw.board is not None:
                try:
                    hw.board.estop()
                except HilswarmError as exc:
                    logger.error("%s: board e-stop failed: %s", self.config.name, exc)
        self._transition("enter_safe", reason)

    def _go_safe(self, reason: str, *, fault: bool = True) -> None:
        """Vehicle to safe mode (outputs to safe values, pushed to the board) and state safe.

        ``fault=False`` marks an orderly stop (run completed, stop or signal): the vehicle logs
        it at INFO instead of WARNING. Called by the thread that owns the hardware.
        """
        if self.lifecycle.state_id in ("safe", "stopped"):
            return
        hw = self.hardware
        if hw is not None:
            if self._link_down and hw.board is not None:
                hw.board.abort()  # no request may wait on the dead link; its watchdog acts
            try:
                if not getattr(hw.vehicle, "safe_mode", False):
                    if fault:
                        hw.vehicle.enter_safe_mode(reason)
                    else:
                        hw.vehicle.enter_safe_mode(reason, fault=False)
                if not self._link_down:
                    hw.vehicle.exchange()  # push the safe values to the board now
            except HilswarmError as exc:
                logger.error("%s: could not make outputs safe: %s", self.config.name, exc)
        self._transition("enter_safe", reason)

    def _publish_telemetry_safely(self) -> None:
        """The last batch on the way out: a failure is logged, never stops the shutdown."""
        try:
            self.publish_telemetry()
        except (HilswarmError, zenoh.ZError) as exc:
            logger.error("%s: last telemetry batch not published: %s", self.config.name, exc)

    def _on_set(self, query: zenoh.Query) -> None:
        """Apply a parameter change between ticks and acknowledge it (query reply + status)."""
        try:
            try:
                request = bus.decode_json(query.payload.to_bytes() if query.payload else b"{}")
            except bus.BusMessageError:
                self._count_malformed("set")
                raise
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
        worker_done = self._stop_worker()
        if worker_done:
            self._publish_telemetry_safely()
        if self._telemetry is not None:
            self._telemetry.close()
        if self.lifecycle.state_id == "safe":
            received = sorted(self.received_from)
            self._transition("stop", f"received from: {', '.join(received) or '-'}")
        hw = self.hardware
        if worker_done and hw is not None and hw.board is not None:
            try:
                hw.board.close()
            except HilswarmError as exc:
                logger.error("%s: closing the board failed: %s", self.config.name, exc)
        if self._session is not None and not bus.flush_barrier(
            self._session, self.keys.flush(self.config.name)
        ):
            logger.warning(
                "%s: the bus did not confirm the last status before the session closed",
                self.config.name,
            )
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
            return frozenset(self.engine.received_from)


#: Name of the instance manager's liveliness token (``hilswarm/<exp>/alive/_manager``).
MANAGER_NAME = "_manager"


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


def run_agent(
    config: AgentConfig, endpoints: Sequence[str], security: bus.SessionSecurity | None = None
) -> int:
    """Run one agent in this process until stopped; SIGINT/SIGTERM stop it cleanly."""
    agent = Agent(config, endpoints, security=security, own_process=True)

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        agent.request_stop(f"signal {signal.Signals(signum).name}")

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return agent.run()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m hilswarm.agents.agent [--connect ENDPOINT] [--credentials FILE] --config JSON``.

    The endpoints default to those of the credentials file.
    """
    parser = argparse.ArgumentParser(prog="python -m hilswarm.agents.agent")
    parser.add_argument("--connect", action="append", default=[], help="Zenoh endpoint")
    parser.add_argument("--credentials", type=Path, help="the agent's credentials file (0600)")
    parser.add_argument("--config", required=True, help="AgentConfig as JSON")
    parser.add_argument("-v", "--verbose", action="count", default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s agent %(process)d %(name)s: %(message)s",
    )
    try:
        config = AgentConfig.from_json(args.config)
        credentials = Credentials.read(args.credentials) if args.credentials else None
    except HilswarmError as exc:
        logger.error("%s", exc)
        return 2
    endpoints = args.connect or (list(credentials.endpoints) if credentials else [])
    if not endpoints:
        logger.error("no bus endpoint: give --connect or --credentials")
        return 2
    return run_agent(config, endpoints, credentials.security() if credentials else None)


if __name__ == "__main__":
    sys.exit(main())

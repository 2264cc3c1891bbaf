"""The instance manager: schedules the ticks of every agent and accounts for each of them.

The manager owns the bus of an experiment on this machine: it opens a Zenoh *router* session
listening on loopback (or joins a ``zenohd`` router with ``--connect``), declares its
liveliness token ``hilswarm/<exp>/alive/_manager``, waits until every agent's liveliness token
is up (agents declare it after all their publishers and subscribers, so then every
subscription is known), and then sends ticks:

* ``lockstep`` — tick k+1 is sent as soon as every y_k is in: simulated time runs as fast as
  the agents answer; results are reproducible.
* ``realtime`` — tick k is sent at ``T0 + k * dt`` on the monotonic clock (drift free). Agents
  whose y_k is not in when tick k+1 is due are counted *late* for that tick (per agent) and
  listed as missing in tick k+1, so their neighbours see ``None``; late answers are recorded
  and counted, never silently absorbed.

Every tick is accounted on ``/orchestrator/ticks``: scheduled and send times, completion, late
and missing agents, and each agent's answer latency and sense/compute/actuate times.

Faults: an agent whose liveliness token disappears (killed, or hung past the 1 s lease) or
that does not answer within ``answer_timeout_s`` is *lost*. With ``on_agent_loss = "stop"``
every agent goes to safe mode and the run stops; with ``"continue"`` the agent is marked lost
and listed as missing in every later tick. A stop request (Ctrl-C, ``hilswarm stop``, the end
of the experiment) sends every agent to safe mode and then waits for them to stop.
"""

from __future__ import annotations

import logging
import math
import queue
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.agent import MANAGER_NAME
from hilswarm.orchestrator.experiment import Experiment
from hilswarm.orchestrator.recorder import Recorder
from hilswarm.orchestrator.status_display import StatusDisplay, StatusSnapshot

logger = logging.getLogger(__name__)

#: Default bound on waiting for every agent's liveliness token [s].
DEFAULT_START_TIMEOUT_S = 60.0
#: Default bound on waiting for one tick's answers in lockstep mode [s].
DEFAULT_ANSWER_TIMEOUT_S = 5.0
#: Default bound on waiting for agents to stop after the stop command [s].
DEFAULT_STOP_TIMEOUT_S = 5.0

# Queue item kinds (small ints: compared on every message).
_Y, _ALIVE, _GONE, _CONTROL, _STOP = range(5)


class ManagerError(Exception):
    """Base of the manager's own errors (the orchestrator reports them and exits 1)."""


@dataclass
class RunSummary:
    """What happened in one run.

    Attributes:
        experiment: experiment name.
        mode: ``lockstep`` or ``realtime``.
        ticks: ticks completed (every live agent answered).
        planned_ticks: ticks the experiment asked for.
        wall_s: wall-clock length of the ticking phase [s].
        stop_reason: why the run ended (``"completed"``, ``"interrupted"``, ...).
        lost: agents lost (killed, hung), in order of loss.
        late: late answers per agent (realtime).
        late_ticks: ticks not complete by the next tick's deadline (realtime).
        completion_s: per tick, completion time after its scheduled time [s].
        failed: True when the run could not do what was asked (lost agent with policy stop,
            start-up failure).
    """

    experiment: str
    mode: str
    ticks: int = 0
    planned_ticks: int = 0
    wall_s: float = 0.0
    stop_reason: str = ""
    lost: list[str] = field(default_factory=list)
    late: dict[str, int] = field(default_factory=dict)
    late_ticks: int = 0
    completion_s: list[float] = field(default_factory=list)
    failed: bool = False

    @property
    def speed(self) -> float:
        """Experiment time per wall-clock time (lockstep speed-up; ~1 in realtime)."""
        return 0.0 if self.wall_s <= 0 else self.ticks * self._dt / self.wall_s

    _dt: float = 0.0

    def completion_percentiles(self) -> tuple[float, float]:
        """(p50, p99) of tick completion times [s] (NaN when no tick completed)."""
        if not self.completion_s:
            return math.nan, math.nan
        values = np.asarray(self.completion_s)
        return float(np.percentile(values, 50)), float(np.percentile(values, 99))

    def text(self) -> str:
        """A few human lines."""
        p50, p99 = self.completion_percentiles()
        lines = [
            f"experiment {self.experiment!r} ({self.mode}): {self.ticks}/{self.planned_ticks} "
            f"ticks in {self.wall_s:.2f} s wall clock ({self.speed:.1f}x real time); "
            f"stopped: {self.stop_reason}",
            f"tick completion p50 {p50 * 1e3:.2f} ms, p99 {p99 * 1e3:.2f} ms; "
            f"late ticks {self.late_ticks}",
        ]
        late = {name: n for name, n in self.late.items() if n}
        if late:
            lines.append("late answers: " + ", ".join(f"{n}={c}" for n, c in late.items()))
        if self.lost:
            lines.append("lost agents: " + ", ".join(self.lost))
        return "\n".join(lines)


class _RecordPump:
    """Writes to the recorder on its own thread, so recording never delays a tick."""

    def __init__(self, recorder: Recorder | None, keys: bus.BusKeys, dt: float) -> None:
        self.recorder = recorder
        self.keys = keys
        self.dt = dt
        self.queue: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self.agent_states: dict[str, str] = {}
        self.stopped_agents: set[str] = set()
        self._thread = threading.Thread(target=self._run, name="hilswarm-recorder", daemon=True)
        self.errors = 0

    def start(self) -> None:
        self._thread.start()

    def on_sample(self, sample: zenoh.Sample, log_time_ns: int) -> None:
        """Bus callback (u, x_hat, status, telemetry): enqueue only."""
        self.queue.put((str(sample.key_expr), sample.payload.to_bytes(), log_time_ns))

    def _run(self) -> None:
        get = self.queue.get
        while True:
            item = get()
            if item is None:
                return
            try:
                self._write(*item)
            except Exception:  # a bad message must not stop the recording of the others
                self.errors += 1
                logger.exception("cannot record %s", item[0])

    def _write(self, key: str, payload: Any, log_time_ns: int) -> None:
        recorder = self.recorder
        if key == "#ticks":
            if recorder is not None:
                k, t, timings = payload
                recorder.write_ticks(k=k, t=t, log_time_ns=log_time_ns, timings=timings)
            return
        if key == "#y":
            if recorder is not None:
                name, y, report = payload
                k, t, values = bus.decode_vector(y)
                recorder.write_vector(
                    f"/{name}/y", k=k, t=t, values=values, log_time_ns=log_time_ns
                )
                if report.u.size:
                    t_u = t - self.dt
                    recorder.write_vector(
                        f"/{name}/u", k=k, t=t_u, values=report.u, log_time_ns=log_time_ns
                    )
                    if report.x_hat.size:
                        recorder.write_vector(
                            f"/{name}/x_hat",
                            k=k,
                            t=t_u,
                            values=report.x_hat,
                            log_time_ns=log_time_ns,
                        )
            return
        if key == "#status":
            name, state, k, t, detail = payload
            if recorder is not None:
                recorder.write_status(
                    name, state=state, k=k, t=t, log_time_ns=log_time_ns, detail=detail
                )
            return
        name, leaf = self.keys.parse_agent_key(key)
        if leaf == "status":
            message = bus.decode_json(payload)
            state = str(message.get("state", ""))
            self.agent_states[name] = state
            if state == "stopped":
                self.stopped_agents.add(name)
            if recorder is not None:
                detail = str(message.get("detail", ""))
                if message.get("kind") == "set":
                    detail = f"{detail} (ok={message.get('ok')})"
                recorder.write_status(
                    name,
                    state=state,
                    k=int(message.get("k", 0)),
                    t=float(message.get("t", 0.0)),
                    log_time_ns=log_time_ns,
                    detail=detail,
                )
            return
        if recorder is None:
            return
        k, t, values = bus.decode_vector(payload)
        recorder.write_vector(f"/{name}/{leaf}", k=k, t=t, values=values, log_time_ns=log_time_ns)

    def put_outputs(self, name: str, y: bytes, report: bus.TickReport, log_time_ns: int) -> None:
        """Record an agent's y_k and the u_k, x_hat_k of its report."""
        if self.recorder is not None:
            self.queue.put(("#y", (name, y, report), log_time_ns))

    def put_ticks(self, k: int, t: float, timings: dict[str, Any], log_time_ns: int) -> None:
        self.queue.put(("#ticks", (k, t, timings), log_time_ns))

    def put_status(
        self, name: str, state: str, *, k: int, detail: str, log_ns: int, dt: float
    ) -> None:
        self.queue.put(("#status", (name, state, k, k * dt, detail), log_ns))

    def close(self, timeout_s: float = 30.0) -> None:
        if self._thread.is_alive():
            self.queue.put(None)
            self._thread.join(timeout_s)


_K = struct.Struct("<q")


class _TickState:
    """Answers to the tick in flight (arrays indexed like the experiment's agents)."""

    def __init__(self, n: int) -> None:
        self.k = 0
        self.scheduled = 0.0
        self.sent = 0.0
        self.last_progress = 0.0
        self.expected = n
        self.count = 0
        self.arrived = np.zeros(n, dtype=bool)
        self.answer_s = np.full(n, np.nan)
        self.timing = np.full((n, 3), np.nan)  # sense, compute, actuate [s]
        self.skipped = np.zeros(n, dtype=np.int64)

    def begin(self, k: int, scheduled: float, sent: float) -> None:
        """Tick ``k`` scheduled at ``scheduled`` was sent at ``sent`` [s, manager clock]."""
        self.k, self.scheduled, self.sent, self.last_progress = k, scheduled, sent, sent
        self.count = 0
        self.arrived[:] = False
        self.answer_s[:] = np.nan
        self.timing[:] = np.nan
        self.skipped[:] = 0

    def answer(self, i: int, received: float, timing: bus.AgentTiming, *, counted: bool) -> None:
        """Agent ``i``'s y_k arrived at ``received`` [s, manager clock]."""
        self.arrived[i] = True
        self.answer_s[i] = received - self.sent
        self.timing[i] = (timing.sense_s, timing.compute_s, timing.actuate_s)
        self.skipped[i] = timing.skipped
        if counted:
            self.count += 1
            self.last_progress = received

    def unanswered(self, lost: set[int]) -> list[int]:
        """Agents (not lost) whose y_k is not in."""
        return [i for i in np.flatnonzero(~self.arrived).tolist() if i not in lost]

    def recount(self, n: int, lost: set[int]) -> None:
        """Recompute what is expected after agents were lost."""
        self.expected = n - len(lost)
        self.count = sum(1 for i in np.flatnonzero(self.arrived).tolist() if i not in lost)


class InstanceManager:
    """Schedules ticks for the agents of ``experiment`` and records the run.

    Args:
        experiment: the loaded experiment (its ``mode`` and ``n_ticks`` are used).
        recorder: where to record (``None``: nothing is recorded).
        listen: endpoints of the embedded router session (``tcp/127.0.0.1:<port>``);
            ignored when ``connect`` is given.
        connect: endpoints of an existing Zenoh router to join as a client.
        clock: monotonic clock [s] for scheduling and accounting.
        wall_clock_ns: wall clock [ns, Unix epoch] for MCAP log times.
        answer_timeout_s: lockstep: an agent that does not answer a tick within this is lost.
        stop_timeout_s: bound on waiting for agents to stop.
        display: live status display (``None``: none).
        record_ticks: write ``/orchestrator/ticks`` (one message per tick).
    """

    def __init__(
        self,
        experiment: Experiment,
        *,
        recorder: Recorder | None,
        listen: Sequence[str] = (),
        connect: Sequence[str] = (),
        clock: Callable[[], float] = time.perf_counter,
        wall_clock_ns: Callable[[], int] = time.time_ns,
        answer_timeout_s: float = DEFAULT_ANSWER_TIMEOUT_S,
        stop_timeout_s: float = DEFAULT_STOP_TIMEOUT_S,
        display: StatusDisplay | None = None,
        record_ticks: bool = True,
    ) -> None:
        if not listen and not connect:
            raise ManagerError("the instance manager needs endpoints to listen on or connect to")
        self.experiment = experiment
        self.keys = bus.BusKeys(experiment.name)
        self.names: tuple[str, ...] = experiment.agent_names
        self.n = len(self.names)
        self.dt = experiment.dt
        self.mode = experiment.mode
        self._listen = list(listen)
        self._connect = list(connect)
        self._clock = clock
        self._wall_ns = wall_clock_ns
        self.answer_timeout_s = answer_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self._display = display
        self._record_ticks = record_ticks
        self._queue: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self._pump = _RecordPump(recorder, self.keys, experiment.dt)
        self._session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self.alive: set[str] = set()
        self.lost: set[int] = set()
        self._stop_reason = ""
        self._paused = False
        self._reanchor = False
        self._estop_tick: int | None = None
        self.summary = RunSummary(experiment=experiment.name, mode=self.mode)
        self.summary._dt = self.dt
        self.summary.late = dict.fromkeys(self.names, 0)
        self.summary.planned_ticks = experiment.n_ticks
        self._clock_origin = clock()

    # -- bus ---------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the bus session and declare everything; start the recorder thread."""
        if self._connect:
            config = bus.client_config(self._connect)
        else:
            config = bus.listen_config(self._listen)
        session = bus.open_session(config)
        self._session = session
        keys, put, clock = self.keys, self._queue.put, self._clock
        self._tick_pub = session.declare_publisher(keys.tick, **bus.TICK_PATH_QOS)
        self._control_pub = session.declare_publisher(keys.control, **bus.TICK_PATH_QOS)
        self._status_pub = session.declare_publisher(keys.manager_status, **bus.DATA_QOS)
        entities: list[Any] = [self._tick_pub, self._control_pub, self._status_pub]
        for i, name in enumerate(self.names):
            entities.append(
                session.declare_subscriber(
                    keys.y(name),
                    zenoh.handlers.Callback(
                        lambda s, i=i: put(
                            (
                                _Y,
                                i,
                                s.payload.to_bytes(),
                                s.attachment.to_bytes() if s.attachment else b"",
                                clock(),
                            )
                        ),
                        indirect=False,
                    ),
                )
            )
        pump, wall_ns = self._pump, self._wall_ns
        # u and x_hat arrive inside the agents' y reports; status and telemetry on their keys.
        for leaf in ("status", "telemetry/**"):
            entities.append(
                session.declare_subscriber(
                    f"{keys.prefix}/agent/*/{leaf}",
                    zenoh.handlers.Callback(lambda s: pump.on_sample(s, wall_ns()), indirect=False),
                )
            )
        entities.append(
            session.declare_subscriber(
                keys.control,
                zenoh.handlers.Callback(
                    lambda s: put((_CONTROL, s.payload.to_bytes())), indirect=False
                ),
            )
        )
        entities.append(
            session.liveliness().declare_subscriber(
                keys.all_alive,
                zenoh.handlers.Callback(self._on_liveliness, indirect=False),
                history=True,
            )
        )
        entities.append(session.liveliness().declare_token(keys.alive(MANAGER_NAME)))
        self._entities = entities
        self._pump.start()
        self._publish_state("waiting", "waiting for agents")

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        try:
            name = self.keys.parse_alive_key(str(sample.key_expr))
        except bus.BusKeyError:
            return
        if name == MANAGER_NAME or name not in self.names:
            return
        kind = _ALIVE if sample.kind == zenoh.SampleKind.PUT else _GONE
        self._queue.put((kind, name, self._clock()))

    def _publish_state(self, state: str, detail: str = "") -> None:
        if self._session is not None:
            self._status_pub.put(bus.encode_json({"state": state, "detail": detail}))

    def request_stop(self, reason: str) -> None:
        """Ask the run to stop (thread-safe, signal-safe): agents to safe, then stopped."""
        self._queue.put((_STOP, reason))

    def estop(self, reason: str = "e-stop") -> None:
        """Swarm-wide e-stop: every agent's outputs to safe values now, then the run stops."""
        self._control_pub.put(bus.encode_control(bus.ControlCommand.ESTOP, reason=reason))

    # -- start-up ----------------------------------------------------------------------------

    def wait_for_agents(
        self, timeout_s: float = DEFAULT_START_TIMEOUT_S, check: Callable[[], None] | None = None
    ) -> None:
        """Block until every agent's liveliness token is up.

        Args:
            timeout_s: bound [s].
            check: called regularly; raises to abort (e.g. an agent process exited).

        Raises:
            ManagerError: timeout, or a stop request arrived first.
        """
        deadline = self._clock() + timeout_s
        while len(self.alive) < self.n:
            remaining = deadline - self._clock()
            if remaining <= 0:
                waiting = [n for n in self.names if n not in self.alive]
                raise ManagerError(
                    f"timed out after {timeout_s} s waiting for agents: {', '.join(waiting)}"
                )
            if check is not None:
                check()
            try:
                item = self._queue.get(timeout=min(remaining, 0.1))
            except queue.Empty:
                continue
            kind = item[0]
            if kind == _ALIVE:
                self.alive.add(item[1])
                if self._display is not None:
                    self._display.log(f"agent {item[1]} ready ({len(self.alive)}/{self.n})")
            elif kind == _GONE:
                self.alive.discard(item[1])
            elif kind == _STOP:
                raise ManagerError(f"stopped before the run began: {item[1]}")
            elif kind == _CONTROL:
                command, reason = bus.decode_control(item[1])
                if command in (bus.ControlCommand.STOP, bus.ControlCommand.ESTOP):
                    raise ManagerError(f"{command.value} before the run began: {reason}")

    # -- ticking -----------------------------------------------------------------------------

    def run(self) -> RunSummary:
        """Send every tick of the experiment, then stop the agents. Returns the summary."""
        n_ticks = self.experiment.n_ticks
        realtime = self.mode == "realtime"
        clock, get, dt = self._clock, self._queue.get, self.dt
        summary = self.summary
        tick = _TickState(self.n)
        tick.expected = self.n - len(self.lost)
        self._publish_state("running")
        start = clock()
        t0 = start + (min(0.05, 5 * dt) if realtime else 0.0)
        if realtime:
            self._wait_until(t0)
        tick.begin(0, t0, self._send_tick(0, ()))
        next_display = start + 0.5
        while not self._stop_reason:
            now = clock()
            if self._reanchor:  # realtime resume: tick k+1 is due one period from now
                self._reanchor = False
                t0 = now - tick.k * dt
            due = t0 + (tick.k + 1) * dt if realtime else math.inf
            wait_until = now + 0.1 if self._paused or not realtime else due
            if now >= next_display:
                self._show(tick.k, start, now)
                next_display = now + 0.5
            try:
                item = get(timeout=max(0.0, wait_until - now))
            except queue.Empty:
                item = None
            if item is not None:
                self._handle(item, tick)
                if self._stop_reason:
                    break
            now = clock()
            complete = tick.count >= tick.expected
            if self._paused:
                continue
            if not realtime and complete:
                self._account(tick, tick.last_progress if tick.expected else now, ())
                summary.ticks += 1
                if tick.k + 1 >= n_ticks:
                    self._stop_reason = "completed"
                    break
                scheduled = clock()
                tick.begin(tick.k + 1, scheduled, self._send_tick(tick.k + 1, sorted(self.lost)))
            elif realtime and now >= due:
                late = [] if complete else tick.unanswered(self.lost)
                self._account(tick, tick.last_progress if complete else math.nan, late)
                for j in late:
                    summary.late[self.names[j]] += 1
                if late:
                    summary.late_ticks += 1
                else:
                    summary.ticks += 1
                if tick.k + 1 >= n_ticks:
                    self._stop_reason = "completed"
                    break
                k = tick.k + 1
                tick.begin(k, t0 + k * dt, self._send_tick(k, sorted(set(late) | self.lost)))
            elif not realtime and now - tick.last_progress > self.answer_timeout_s:
                for j in tick.unanswered(self.lost):
                    self._on_agent_gone(
                        self.names[j], tick.k, f"no answer within {self.answer_timeout_s} s"
                    )
                tick.recount(self.n, self.lost)
                tick.last_progress = now
        summary.wall_s = clock() - start
        summary.stop_reason = self._stop_reason
        self._show(tick.k, start, clock())
        self._stop_agents()
        return summary

    def _handle(self, item: tuple[Any, ...], tick: _TickState) -> None:
        """One queue item while ticking."""
        kind = item[0]
        if kind == _Y:
            _, i, payload, attachment, received = item
            report = bus.decode_report(attachment)
            self._pump.put_outputs(self.names[i], payload, report, self._wall_ns())
            k_y = _K.unpack_from(payload)[0]
            if k_y == tick.k and not tick.arrived[i]:
                tick.answer(i, received, report.timing, counted=i not in self.lost)
            elif k_y < tick.k:
                logger.debug("late answer of %s for tick %d", self.names[i], k_y)
        elif kind == _GONE:
            self._on_agent_gone(item[1], tick.k, "liveliness token lost (killed or hung)")
            tick.recount(self.n, self.lost)
        elif kind == _ALIVE:
            self.alive.add(item[1])
        elif kind == _CONTROL:
            self._on_control(item[1], tick.k)
        elif kind == _STOP:
            self._stop_reason = str(item[1])

    def _wait_until(self, when: float) -> None:
        """Block until ``when`` on the manager clock, still handling stop requests."""
        while True:
            remaining = when - self._clock()
            if remaining <= 0:
                return
            try:
                item = self._queue.get(timeout=remaining)
            except queue.Empty:
                return
            if item[0] == _STOP:
                self._stop_reason = str(item[1])
                return
            if item[0] == _ALIVE:
                self.alive.add(item[1])

    def _send_tick(self, k: int, missing: Sequence[int]) -> float:
        sent = self._clock()
        self._tick_pub.put(bus.encode_tick(bus.TickMessage(k, k * self.dt, tuple(missing))))
        return sent

    def _account(self, tick: _TickState, done: float, late: Sequence[int]) -> None:
        """Record the timing account of ``tick`` (times on the manager clock [s])."""
        if not math.isnan(done):
            self.summary.completion_s.append(done - tick.scheduled)
        if not self._record_ticks or self._pump.recorder is None:
            return
        names = self.names
        agents = {}
        for i in np.flatnonzero(tick.arrived):
            agents[names[i]] = {
                "answer_s": float(tick.answer_s[i]),
                "sense_s": float(tick.timing[i, 0]),
                "compute_s": float(tick.timing[i, 1]),
                "actuate_s": float(tick.timing[i, 2]),
                "skipped": int(tick.skipped[i]),
            }
        timings = {
            "scheduled_s": tick.scheduled - self._clock_origin,
            "send_delay_s": tick.sent - tick.scheduled,
            "completion_s": None if math.isnan(done) else done - tick.scheduled,
            "late": [names[i] for i in late],
            "missing": [names[i] for i in sorted(self.lost)],
            "agents": agents,
        }
        self._pump.put_ticks(tick.k, tick.k * self.dt, timings, self._wall_ns())

    def _on_control(self, payload: bytes, k: int) -> None:
        try:
            command, reason = bus.decode_control(payload)
        except bus.BusMessageError as exc:
            logger.warning("%s", exc)
            return
        if command is bus.ControlCommand.STOP:
            self._stop_reason = f"stop requested{': ' + reason if reason else ''}"
        elif command is bus.ControlCommand.ESTOP:
            self._estop_tick = k
            self._pump.put_status(
                "orchestrator", "estop", k=k, detail=reason, log_ns=self._wall_ns(), dt=self.dt
            )
            self._stop_reason = f"e-stop at tick {k}{': ' + reason if reason else ''}"
        elif command is bus.ControlCommand.PAUSE:
            self._paused = True
            self._publish_state("paused", reason)
        elif command is bus.ControlCommand.RESUME:
            self._paused = False
            self._reanchor = True
            self._publish_state("running", reason)

    def _on_agent_gone(self, name: str, k: int, reason: str) -> None:
        self.alive.discard(name)
        i = self.names.index(name)
        if i in self.lost:
            return
        self.lost.add(i)
        self.summary.lost.append(name)
        logger.warning("agent %s lost at tick %d: %s", name, k, reason)
        if self._display is not None:
            self._display.log(f"agent {name} lost at tick {k}: {reason}")
        self._pump.put_status(name, "lost", k=k, detail=reason, log_ns=self._wall_ns(), dt=self.dt)
        if self.experiment.on_agent_loss == "stop":
            self.summary.failed = True
            self._stop_reason = f"agent {name} lost ({reason}); on_agent_loss = stop"
        elif len(self.lost) == self.n:
            self.summary.failed = True
            self._stop_reason = "every agent is lost"

    # -- stopping ----------------------------------------------------------------------------

    def _stop_agents(self) -> None:
        """Every agent to safe mode and stopped; wait (bounded) for their tokens to go."""
        self._publish_state("stopping", self._stop_reason)
        self._control_pub.put(bus.encode_control(bus.ControlCommand.STOP, reason=self._stop_reason))
        deadline = self._clock() + self.stop_timeout_s
        while self.alive:
            remaining = deadline - self._clock()
            if remaining <= 0:
                logger.warning(
                    "agents still up %s s after the stop command: %s",
                    self.stop_timeout_s,
                    ", ".join(sorted(self.alive)),
                )
                break
            try:
                item = self._queue.get(timeout=remaining)
            except queue.Empty:
                break
            if item[0] == _GONE:
                self.alive.discard(item[1])
            elif item[0] == _Y:
                report = bus.decode_report(item[3])
                self._pump.put_outputs(self.names[item[1]], item[2], report, self._wall_ns())

    def _show(self, k: int, start: float, now: float) -> None:
        if self._display is None:
            return
        elapsed = max(now - start, 1e-9)
        self._display.update(
            StatusSnapshot(
                experiment=self.experiment.name,
                mode=self.mode,
                k=k,
                n_ticks=self.experiment.n_ticks,
                tick_rate_hz=k / elapsed,
                late_ticks=self.summary.late_ticks,
                states=dict(self._pump.agent_states),
                lost=[self.names[i] for i in sorted(self.lost)],
                paused=self._paused,
            )
        )

    def close(self) -> None:
        """Stop recording (after draining) and close the bus session. Idempotent."""
        if self._session is not None:
            try:
                self._publish_state("stopped", self._stop_reason)
            finally:
                self._entities.clear()
                self._session.close()
                self._session = None
        self._pump.close()

    @property
    def estop_tick(self) -> int | None:
        """Tick at which an e-stop was received, if any."""
        return self._estop_tick

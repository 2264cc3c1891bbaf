"""The instance manager: schedules the ticks of every agent and accounts for each of them.

The manager owns the bus of an experiment on this machine: it opens a Zenoh *router* session
listening on loopback, on a free port it reads back (or joins a ``zenohd`` router with
``--connect``), with the run's authentication and access control when given, declares its
liveliness token ``hilswarm/<exp>/<run_id>/alive/_manager``, waits until every agent's
liveliness token is up (agents declare it after all their publishers and subscribers, so then every
subscription is known), and then sends ticks:

* ``lockstep`` — simulated time runs as fast as the agents answer; results are reproducible.
  Ticks are *released* up to ``lockstep_window`` ahead of the oldest tick whose answers are
  not all in (a tick message k releases every tick up to k), in steps of half a window; an
  agent computes tick k as soon as its own neighbours' y_{k-1} are in. Its input depends on
  nothing else, so the numbers are those of a swarm-wide barrier per tick (window 1).
* ``realtime`` — tick k is sent at ``T0 + k * dt`` on the monotonic clock (drift free). Agents
  whose y_k is not in when tick k+1 is due are counted *late* for that tick (per agent) and
  listed as missing in tick k+1, so their neighbours see ``None``; late answers are recorded
  and counted, never silently absorbed. With ``[mocap]`` (``tick_lock``, the default) the
  ticks are released in step with the camera frames instead: tick k a small lag after the
  first frame at or after ``T0 + k * dt``, falling back to the free grid at once when frames
  stop (:mod:`hilswarm.orchestrator.frame_lock`).
* ``realtime``, **self-clocked** (``realtime_clock = "shared"``, the default; only when every
  agent runs on this host and no XBee gateway follows the ticks): instead of one tick message
  per period the manager sends a *schedule* (:class:`~hilswarm.agents.bus.ScheduleMessage`: T0 on
  CLOCK_MONOTONIC, dt, first and last tick) at the start, on every change (a pause ends it
  after the next tick, a resume re-anchors it, a lost agent is announced, the frame lock moves
  the due time of the next tick: sent once that tick's senses are over,
  :meth:`~hilswarm.orchestrator.frame_schedule.FrameSchedule.quiet_send_time`) and every
  :data:`SCHEDULE_REPEAT_S`; each agent wakes itself at ``T0 + k * dt``. The manager still
  closes tick k when tick k+1 is due and accounts it exactly as above (late: y_k not in).

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
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents import bus, bus_callback
from hilswarm.agents.agent import MANAGER_NAME
from hilswarm.agents.tick_engine import is_warmup, start_lead
from hilswarm.agents.timed_queue import get_within
from hilswarm.orchestrator.experiment import Experiment, self_clocked
from hilswarm.orchestrator.frame_schedule import FRAME_ACQUIRE_WAIT_S, FrameSchedule
from hilswarm.orchestrator.machine_cpu import read_cpu_times
from hilswarm.orchestrator.record_feed import RecordFeed
from hilswarm.orchestrator.record_stream import ORCHESTRATOR, RecordSink
from hilswarm.orchestrator.recorder import Recorder
from hilswarm.orchestrator.run_summary import AgentEvent, RunSummary
from hilswarm.orchestrator.run_tally import RunTally
from hilswarm.orchestrator.status_display import StatusDisplay, StatusSnapshot
from hilswarm.orchestrator.stream_recorder import StreamRecorder
from hilswarm.orchestrator.tick_window import TickAccount, TickWindow

logger = logging.getLogger(__name__)

#: Default bound on waiting for every agent's liveliness token [s].
DEFAULT_START_TIMEOUT_S = 60.0
#: Default bound on waiting for one tick's answers in lockstep mode [s].
DEFAULT_ANSWER_TIMEOUT_S = 5.0
#: Default bound on waiting for agents to stop after the stop command [s].
DEFAULT_STOP_TIMEOUT_S = 5.0
#: Late ticks above this fraction of the planned ticks degrade the outcome (exit status 3)
#: when the experiment does not set ``max_late_fraction``.
DEFAULT_MAX_LATE_FRACTION = 0.01
#: Default period of handing records to the recorder [s].
DEFAULT_FLUSH_PERIOD_S = 0.02
#: Self-clocked realtime: the schedule is repeated this often [s] (a forged or lost schedule
#: holds at most this long).
SCHEDULE_REPEAT_S = 1.0
#: Self-clocked realtime: the frame lock moving the next tick's due time by more than this [s]
#: sends a new schedule.
SCHEDULE_MOVE_S = 20e-6

#: At the stop, how long an agent's last status (``stopped``, with its final counters) may
#: still take to arrive after its liveliness token went [s]: the token's end travels as a
#: declaration, ahead of data, and may overtake the agent's last messages.
STOP_STATUS_GRACE_S = 0.5

# Event kinds of the ticking thread's queue (rare: not one per message).
_ALIVE, _GONE, _CONTROL, _STOP, _SAFE, _COMPLETE, _STOPPED = range(7)
_K = struct.Struct("<q")


class ManagerError(Exception):
    """Base of the manager's own errors (the orchestrator reports them and exits 1)."""


class InstanceManager:
    """Schedules ticks for the agents of ``experiment`` and records the run.

    Per tick the manager's own work is small and allocation-light: each agent's ``y`` is
    accounted in the bus callback that receives it (its tick index read from the first 8
    bytes; nothing else decoded), the tick's account is kept in preallocated arrays, and what
    is recorded is kept as it came and goes on the MCAP record stream, in batches
    (:mod:`hilswarm.orchestrator.record_feed`), to ``recorder`` (usually the recorder
    process, see :mod:`hilswarm.orchestrator.recorder_process`), which does the decoding and
    JSON encoding on its own core. The due times of realtime ticks come from
    :mod:`hilswarm.orchestrator.frame_schedule` (free, or in step with the mocap frames), the
    counting of ticks and the agents' reports go to :mod:`hilswarm.orchestrator.run_tally`.

    Args:
        experiment: the loaded experiment (its ``mode`` and ``n_ticks`` are used).
        recorder: where the record stream goes (a :class:`RecordSink`, or a
            :class:`~hilswarm.orchestrator.recorder.Recorder` written in this process);
            ``None``: nothing is recorded.
        listen: endpoints of the embedded router session (``tcp/127.0.0.1:0``: a free port;
            :attr:`endpoints` holds the bound ones after :meth:`open`); ignored when
            ``connect`` is given.
        connect: endpoints of an existing Zenoh router to join as a client.
        run_id: the run's id (bus key prefix ``hilswarm/<exp>/<run_id>``).
        security: the router's authentication, TLS and access control (``None``: none).
        clock: monotonic clock [s] for scheduling and accounting.
        wall_clock_ns: wall clock [ns, Unix epoch] for MCAP log times.
        answer_timeout_s: lockstep: an agent that does not answer a tick within this is lost.
        stop_timeout_s: bound on waiting for agents to stop.
        display: live status display (``None``: none).
        record_ticks: write ``/orchestrator/ticks`` (one message per tick).
        flush_period_s: records are handed to ``recorder`` at most this long after they came
            [s] (a killed orchestrator loses at most this much). In realtime runs a batch goes
            when a tick completes, from half a period before it is due: between the swarm's
            ticks, not at a due time, where the recorder's work would compete with theirs.
        describe_process: says what an agent's process is doing (exited, killed, still
            running) when its liveliness token disappears, for the loss report.
        remote: agents that join from other hosts (``hilswarm run --remote``): a realtime run
            with any keeps tick messages (no self-clocked schedule).
    """

    def __init__(
        self,
        experiment: Experiment,
        *,
        recorder: RecordSink | Recorder | None,
        listen: Sequence[str] = (),
        connect: Sequence[str] = (),
        run_id: str = "",
        security: bus.SessionSecurity | None = None,
        clock: Callable[[], float] = time.perf_counter,
        wall_clock_ns: Callable[[], int] = time.time_ns,
        answer_timeout_s: float = DEFAULT_ANSWER_TIMEOUT_S,
        stop_timeout_s: float = DEFAULT_STOP_TIMEOUT_S,
        display: StatusDisplay | None = None,
        record_ticks: bool = True,
        flush_period_s: float = DEFAULT_FLUSH_PERIOD_S,
        describe_process: Callable[[str], str] | None = None,
        remote: Sequence[str] = (),
    ) -> None:
        if not listen and not connect:
            raise ManagerError("the instance manager needs endpoints to listen on or connect to")
        self.experiment = experiment
        self.keys = bus.BusKeys(experiment.name, run_id)
        self._security = security
        self.names: tuple[str, ...] = experiment.agent_names
        self._index = {name: i for i, name in enumerate(self.names)}
        self.n = len(self.names)
        self.dt = experiment.dt
        self.mode = experiment.mode
        self._realtime = experiment.mode == "realtime"
        #: Self-clocked realtime (see the module docstring): agents keep the schedule.
        self.self_clocked = self_clocked(
            experiment.mode,
            getattr(experiment, "realtime_clock", "shared"),
            getattr(experiment, "gateway", None),
            remote=bool(remote),
        )
        if clock is not time.perf_counter and clock is not time.monotonic:
            self.self_clocked = False  # the schedule must be on CLOCK_MONOTONIC
        # Self-clocked: the schedule in force (first, last tick; T0 [s, manager clock]).
        self._schedule = (0, experiment.n_ticks - 1, 0.0)
        self._schedule_sent = -math.inf  # when it was last sent [s]
        self._schedule_at: float | None = None  # when the schedule in force goes out, if held
        self._halt_after: int | None = None  # a pause ends the schedule after this tick
        self._listen = list(listen)
        self._connect = list(connect)
        #: Endpoints of the bus (after :meth:`open`: the bound ones when listening).
        self.endpoints: list[str] = list(connect) or list(listen)
        self._clock = clock
        self._wall_ns = wall_clock_ns
        self.answer_timeout_s = answer_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self._display = display
        self._describe_process = describe_process
        # Shared with the bus callbacks (Zenoh threads): guarded by _lock.
        self._lock = threading.Lock()
        # realtime: one tick in flight; self-clocked: also the next one, opened in advance
        self.window = 1 if self._realtime else experiment.lockstep_window
        if self.self_clocked:
            self.window = 2
        self._step_k = 0  # self-clocked: the tick whose due time is the next step
        self._tick = TickWindow(self.n, self.window)
        if isinstance(recorder, Recorder):
            recorder = StreamRecorder(recorder, experiment)
        # The record stream: the bus callbacks keep messages in ``_records`` under _lock; the
        # feed hands them to the sink in batches.
        self._feed: RecordFeed | None = None
        if recorder is not None:
            self._feed = RecordFeed(
                recorder,
                self.names,
                lock=self._lock,
                tick_base=lambda: self._tick.base,
                clock=clock,
                wall_clock_ns=wall_clock_ns,
                flush_period_s=flush_period_s,
            )
        self._records = self._feed.writer if self._feed is not None else None
        self._record_ticks = record_ticks and recorder is not None
        self._flush_period_s = flush_period_s
        self.agent_states: dict[str, str] = {}
        # Rare events for the ticking thread: liveliness, control, stop, safe, lockstep done.
        self._events: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self._session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self.alive: set[str] = set()
        self.lost: set[int] = set()
        self._stop_reason = ""
        self._stopping = False
        self._paused = False
        self._reanchor = False
        self._estop_tick: int | None = None
        self.summary = RunSummary(experiment=experiment.name, mode=self.mode)
        self.summary.dt_s = self.dt
        self.summary.late = dict.fromkeys(self.names, 0)
        self.summary.planned_ticks = experiment.n_ticks
        # read defensively: the key comes with the experiment schema
        self.summary.max_late_fraction = float(
            getattr(experiment, "max_late_fraction", DEFAULT_MAX_LATE_FRACTION)
        )
        self._tally = RunTally(
            self.summary,
            self.names,
            experiment.n_ticks,
            experiment.rate_hz,
            say=display.log if display is not None else None,
            cpu_times=read_cpu_times if self._realtime else None,
        )
        self._clock_origin = clock()
        # Realtime due times, in step with the mocap frames with ``[mocap] tick_lock``.
        self._frames = FrameSchedule(
            self.dt,
            getattr(experiment, "mocap", None),
            realtime=self._realtime,
            self_clocked=self.self_clocked,
        )

    # -- bus ---------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the bus session and declare everything."""
        if self._connect:
            config = bus.client_config(self._connect, security=self._security)
        else:
            config = bus.listen_config(self._listen, security=self._security)
        session = bus.open_session(config)
        self._session = session
        if not self._connect:
            try:
                self.endpoints = bus.bound_endpoints(session)
            except bus.BusConnectionError:
                session.close()
                self._session = None
                raise
        keys = self.keys
        self._tick_pub = session.declare_publisher(keys.tick, **bus.TICK_PATH_QOS)
        self._control_pub = session.declare_publisher(keys.control, **bus.TICK_PATH_QOS)
        self._status_pub = session.declare_publisher(keys.manager_status, **bus.DATA_QOS)
        entities: list[Any] = [self._tick_pub, self._control_pub, self._status_pub]
        for i, name in enumerate(self.names):
            entities.append(
                session.declare_subscriber(
                    keys.y(name),
                    bus_callback.callback(self._y_callback(i)),
                )
            )
        # u and x_hat arrive inside the agents' y reports; status and telemetry on their keys
        # (telemetry batches on agent/<name>/telemetry, single vectors one level below).
        # Explicit keys per agent, never agent/*/...: the router's access control forwards an
        # agent only subscriptions inside its own keys, which its publishers need to match.
        for name in self.names:
            for key, callback in (
                (keys.status(name), self._on_status),
                (f"{keys.agent(name, 'telemetry')}/*", self._on_vector),
                (keys.telemetry_batches(name), self._on_telemetry),
            ):
                entities.append(session.declare_subscriber(key, bus_callback.callback(callback)))
        if self._frames.locking:
            entities.append(
                session.declare_subscriber(
                    keys.mocap_clock,
                    bus_callback.callback(self._on_frame_clock),
                )
            )
        entities.append(
            session.declare_subscriber(
                keys.manager_request,
                bus_callback.callback(self._on_request),
            )
        )
        for leaf in ("status", "stats"):  # explicit keys: see above
            entities.append(
                session.declare_subscriber(
                    keys.gateway(leaf),
                    bus_callback.callback(self._on_gateway),
                )
            )
        entities.append(
            session.liveliness().declare_subscriber(
                keys.all_alive,
                bus_callback.callback(self._on_liveliness),
                history=True,
            )
        )
        entities.append(session.liveliness().declare_token(keys.alive(MANAGER_NAME)))
        self._entities = entities
        self._publish_state("waiting", "waiting for agents")

    def _y_callback(self, i: int) -> Callable[[zenoh.Sample], None]:
        """The callback of agent ``i``'s y key (runs on a Zenoh thread: keep it short)."""
        clock, wall_ns, lock, tick = self._clock, self._wall_ns, self._lock, self._tick
        records, ledger, feed = self._records, self._record_ticks, self._feed
        record = feed is not None
        lockstep = not self._realtime
        put, unpack_k, header = self._events.put, _K.unpack_from, _K.size
        window, arrived, answered_at, count = (
            tick.window,
            tick.arrived,
            tick.answered_at,
            tick.count,
        )

        def on_y(sample: zenoh.Sample) -> None:
            received = clock()
            payload = sample.payload.to_bytes()
            if len(payload) < header:
                logger.warning("agent %s sent a y of %d bytes", self.names[i], len(payload))
                return
            k = unpack_k(payload)[0]
            if is_warmup(k):
                return  # a pre-roll warm-up (tick_engine.preroll_times): not recorded
            with lock:
                if records is not None:
                    attachment = sample.attachment
                    records.y(
                        i,
                        wall_ns(),
                        payload,
                        attachment.to_bytes() if attachment is not None else b"",
                    )
                if k < tick.base or k > tick.released:
                    # a stray one, or a late answer: recorded, and in the ledger when its
                    # tick closed without it
                    late = tick.late_answer(k, i, received) if ledger else None
                    if late is not None and records is not None:
                        records.late(i, k, wall_ns(), late)
                    return
                slot = k % window
                if arrived[slot, i]:
                    return  # a duplicate
                arrived[slot, i] = True
                answered_at[slot, i] = received
                if tick.lost[i]:
                    return
                count[slot] += 1
                if k == tick.base:
                    tick.last_progress = received
                # Lockstep: the oldest tick is complete, release more. Realtime, recording:
                # the swarm is idle until its next tick, the time to hand the records over.
                done = count[slot] >= tick.expected and (
                    k == tick.base if lockstep else record and received >= feed.flush_from
                )
            if done:
                put((_COMPLETE, k))

        return on_y

    def _on_frame_clock(self, sample: zenoh.Sample) -> None:
        """A mocap frame's clock (100-240 Hz, a Zenoh thread): one update of the frame lock."""
        self._frames.on_frame(sample.payload.to_bytes(), self._clock())

    def _due(self, k: int) -> float:
        """Realtime: the due time of tick ``k`` [s, manager clock], locked or free."""
        return self._frames.due(k, self._clock())

    def _note_frame_lock(self, k: int, now: float, *, final: bool = False) -> None:
        """Record the frame lock's state (``frame_lock`` on ``/orchestrator/status``) when it
        changes, every so often while it holds, and at the end (``final``)."""
        detail = self._frames.report(k, now, final=final)
        if detail is not None:
            self._record_event(ORCHESTRATOR, "frame_lock", k=k, detail=detail)

    def _on_status(self, sample: zenoh.Sample) -> None:
        """An agent's status message (rare): its state for the display and the policies."""
        payload = sample.payload.to_bytes()
        try:
            name, _ = self.keys.parse_agent_key(str(sample.key_expr))
            i = self._index[name]
            message = bus.decode_json(payload)
        except (bus.BusKeyError, bus.BusMessageError, KeyError) as exc:
            logger.warning("status message not understood: %s", exc)
            return
        state = str(message.get("state", ""))
        with self._lock:
            if self._records is not None:
                self._records.status(i, self._wall_ns(), payload)
            if "degraded" in (state, self.agent_states.get(name)):
                # A board link fault: the agent's ticks wait for its link, it is not hung.
                self._tick.last_progress = self._clock()
            self.agent_states[name] = state
            self._tally.note_status(name, state, message, stopping=self._stopping)
        if state == "stopped":
            self._events.put((_STOPPED, name))
        elif state == "safe":
            agent_k = message.get("k")
            agent_k = agent_k if isinstance(agent_k, int) else -1
            self._events.put((_SAFE, name, str(message.get("detail", "")), agent_k))

    def _on_vector(self, sample: zenoh.Sample) -> None:
        """A vector on another agent key (telemetry): recorded as it came."""
        records = self._records
        if records is None:
            return
        try:
            name, leaf = self.keys.parse_agent_key(str(sample.key_expr))
            i = self._index[name]
        except (bus.BusKeyError, KeyError) as exc:
            logger.warning("vector message not understood: %s", exc)
            return
        payload = sample.payload.to_bytes()
        with self._lock:
            records.vector(i, self._wall_ns(), leaf, payload)

    def _on_telemetry(self, sample: zenoh.Sample) -> None:
        """An agent's telemetry batch (every ~0.25 s): kept as it came, decoded by the recorder."""
        records = self._records
        if records is None:
            return
        try:
            name, _ = self.keys.parse_agent_key(str(sample.key_expr))
            i = self._index[name]
        except (bus.BusKeyError, KeyError) as exc:
            logger.warning("telemetry batch not understood: %s", exc)
            return
        payload = sample.payload.to_bytes()
        with self._lock:
            records.telemetry(i, self._wall_ns(), payload)

    def _on_request(self, sample: zenoh.Sample) -> None:
        """An operator's command (``hilswarm stop``): forwarded on ``control`` at once, so an
        e-stop reaches the agents without waiting for the ticking thread; then handled there.
        Only the manager puts on ``control`` (the router's access control enforces it)."""
        try:
            command, reason = bus.decode_control(sample.payload.to_bytes())
        except bus.BusMessageError as exc:
            logger.warning("operator request not understood: %s", exc)
            return
        payload = bus.encode_control(command, reason=reason)
        if command in (bus.ControlCommand.STOP, bus.ControlCommand.ESTOP):
            with self._lock:  # the agents' safe states from here on are the (e-)stop's
                self._stopping = True
        self._events.put((_CONTROL, payload))  # first: the manager knows before any agent
        self._control_pub.put(payload)

    def _on_gateway(self, sample: zenoh.Sample) -> None:
        """The XBee gateway's status and per-tick figures (JSON): recorded as they came."""
        records = self._records
        if records is None:
            return
        leaf = str(sample.key_expr).rsplit("/", 1)[-1]
        payload = sample.payload.to_bytes()
        with self._lock:
            records.gateway(self._wall_ns(), leaf, payload)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        try:
            name = self.keys.parse_alive_key(str(sample.key_expr))
        except bus.BusKeyError:
            return
        if name == MANAGER_NAME or name not in self._index:
            return
        kind = _ALIVE if sample.kind == zenoh.SampleKind.PUT else _GONE
        self._events.put((kind, name, self._clock()))

    def _publish_state(self, state: str, detail: str = "") -> None:
        if self._session is not None:
            self._status_pub.put(bus.encode_json({"state": state, "detail": detail}))

    def _record_event(self, agent: str, state: str, *, k: int, detail: str) -> None:
        if self._feed is not None:
            self._feed.event(agent, state, k=k, t=k * self.dt, detail=detail)

    def _flush_records(self, now: float | None = None) -> None:
        """Hand the records gathered so far to the sink (one batch); the next is due one flush
        period from ``now`` [s, manager clock; default: the clock now]."""
        if self._feed is not None:
            self._feed.flush(now, dt=self.dt)

    def request_stop(self, reason: str) -> None:
        """Ask the run to stop (thread-safe, signal-safe): agents to safe, then stopped."""
        self._events.put((_STOP, reason))

    def estop(self, reason: str = "e-stop") -> None:
        """Swarm-wide e-stop: every agent's outputs to safe values now, then the run stops."""
        with self._lock:  # the agents' safe states from here on are the e-stop's, not faults
            self._stopping = True
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
            self._flush_records()
            try:
                item = get_within(self._events, min(remaining, 0.1))
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
        realtime = self._realtime
        clock, events, dt = self._clock, self._events, self.dt
        tick, feed = self._tick, self._feed
        with self._lock:
            tick.recount()
        if realtime and not self._frames.wait_acquired(FRAME_ACQUIRE_WAIT_S):
            logger.warning(
                "no mocap frames within %g s: the first ticks run on the free clock",
                FRAME_ACQUIRE_WAIT_S,
            )
        self._publish_state("running")
        start = clock()
        clocked = self.self_clocked
        # The lead before tick 0; self-clocked agents put their warm-up outputs in it too.
        t0 = start + (start_lead(dt, self_clocked=clocked) if realtime else 0.0)
        if realtime:
            self._frames.start(t0)  # tick k due at t0 + k dt, or in step with the mocap frames
            t0 = self._due(0)
            if clocked:  # the agents wake themselves at t0 + k * dt from now on
                with self._lock:  # open tick 0 before an agent can answer it
                    tick.release(0, t0, t0)
                self._send_schedule(0, self.experiment.n_ticks - 1, t0, record=True)
            self._wait_until(t0)
        if not self._stop_reason:
            if clocked:
                self._clocked_step()
            elif realtime:
                self._release(0, t0)
                self._frames.released()
                self._note_frame_lock(0, clock())
            else:
                self._release_window()
        next_display = start + 0.5
        shown_paused = self._paused  # a pause or resume is shown at once (and in `ps`)
        while not self._stop_reason:
            now = clock()
            if self._reanchor:  # realtime resume: tick k+1 is due one period from now
                self._reanchor = False
                if clocked:
                    self._reanchor_clocked(now)
                else:
                    self._reanchor_free(now)
            if clocked:  # the schedule in force
                due = self._schedule[2] + self._step_k * dt
            else:
                due = self._due(tick.k + 1) if realtime else math.inf
            stepping = self._clocked_stepping() if clocked else not self._paused
            if clocked and now - self._schedule_sent >= SCHEDULE_REPEAT_S:
                self._send_schedule(*self._schedule)
            if not stepping:
                wait_until = now + 0.1
            elif realtime:
                wait_until = due
                if self._schedule_at is not None:
                    wait_until = min(wait_until, self._schedule_at)
            else:
                wait_until = min(now + 0.1, tick.last_progress + self.answer_timeout_s)
            if now >= next_display or self._paused != shown_paused:
                self._show(tick.base - 1, start, now)
                next_display = now + 0.5
                shown_paused = self._paused
            if feed is not None and now >= feed.next_flush:  # no tick completed to carry it
                self._flush_records(now)
            try:
                item = get_within(events, wait_until - clock())
            except queue.Empty:
                item = None
            if item is not None:
                self._handle(item)
                if self._stop_reason:
                    break
            if realtime:
                if clocked:
                    if self._schedule_at is not None and clock() >= self._schedule_at:
                        self._send_schedule(*self._schedule)
                    if self._clocked_stepping() and clock() >= due:
                        self._clocked_step()
                elif not self._paused and clock() >= due:
                    self._realtime_step(due)
            else:
                self._lockstep_step()
        if realtime:  # the lock's totals at the end
            self._note_frame_lock(tick.k, clock(), final=True)
        summary = self.summary
        summary.wall_s = clock() - start
        summary.stop_reason = self._stop_reason
        summary.completion_s = self._tally.completion_s()
        self._show(tick.base - 1, start, clock())
        self._stop_agents(max(tick.base - 1, 0))
        return summary

    def _realtime_step(self, scheduled: float) -> None:
        """Close the tick in flight (late agents counted) and send the next one, due now
        (``scheduled`` [s, manager clock])."""
        tick, n_ticks = self._tick, self.experiment.n_ticks
        with self._lock:
            complete = tick.base_complete()
            late = [] if complete else tick.unanswered()
            account = self._close_base(late, complete)
            k = tick.released + 1
            if k < n_ticks:
                missing = sorted(set(late) | self.lost)
                tick.release(k, scheduled, self._clock())
        if k < n_ticks:
            self._send_tick(k, missing)
            self._frames.released()
            self._note_frame_lock(k, self._clock())
        self._count(account, late)
        if k >= n_ticks:
            self._stop_reason = "completed"

    def _reanchor_free(self, now: float) -> None:
        """Ticked resume: tick k+1 is due one period from ``now`` (or at the frame then)."""
        self._frames.reanchor(now, self._tick.k)

    def _clocked_stepping(self) -> bool:
        """Self-clocked: does the ticking thread step? Not while paused, except that a pause
        takes effect once the tick after it is closed."""
        halt_after = self._halt_after
        return not self._paused or (halt_after is not None and self._tick.base <= halt_after)

    def _clocked_step(self) -> None:
        """Self-clocked: tick ``j = _step_k`` is due now (the agents start it themselves).

        Closes the ticks before ``j`` (late agents counted) and opens ``j`` and ``j + 1``
        (an agent's answer may come before this thread gets here: its tick is open already).
        When the frame lock moves the due time of ``j + 1`` off the schedule in force, a new
        schedule is in force at once and goes out once tick ``j``'s senses are over (it
        reaches the agents most of a period before that tick).
        """
        tick, n_ticks, dt = self._tick, self.experiment.n_ticks, self.dt
        j = self._step_k
        _, last, anchor = self._schedule
        last = min(n_ticks - 1, last)
        due_j = anchor + j * dt
        if self._frames.locking:
            self._frames.released()
            self._note_frame_lock(j, self._clock())
            if j + 1 <= last:
                moved = self._due(j + 1) - (j + 1) * dt  # the anchor the lock asks for
                if abs(moved - anchor) > SCHEDULE_MOVE_S:
                    anchor = moved
                    at = self._frames.quiet_send_time(due_j, anchor + (j + 1) * dt)
                    self._send_schedule(j + 1, self._schedule[1], anchor, at=at)
        closed: list[tuple[TickAccount, list[int]]] = []
        with self._lock:
            while tick.base < j and tick.base <= tick.released:
                # Late: not in when the next tick was due, which the agents started on their
                # own clocks, whenever this thread gets here (a busy machine delays it).
                late = tick.late_at(self._next_due(tick))
                closed.append((self._close_base(late, tick.base_complete()), late))
            if j <= last and tick.released < j:
                tick.release(j, due_j, due_j)  # no message: sent = scheduled
            if j + 1 <= last:
                due = anchor + (j + 1) * dt
                if tick.released < j + 1:
                    tick.release(j + 1, due, due)
                else:  # opened in advance already: re-timed
                    slot = (j + 1) % tick.window
                    tick.scheduled[slot] = tick.sent[slot] = due
        self._step_k = j + 1
        for account, late in closed:
            self._count(account, late)
        if tick.base >= n_ticks:
            self._stop_reason = "completed"

    def _next_due(self, tick: TickWindow) -> float:
        """Self-clocked: when the tick after the oldest open one was due [s, manager clock]
        (its own due time once opened, re-timed by the frame lock; else one period on)."""
        following = tick.base + 1
        if following <= tick.released:
            return float(tick.scheduled[following % tick.window])
        return float(tick.scheduled[tick.base % tick.window]) + self.dt

    def _reanchor_clocked(self, now: float) -> None:
        """Self-clocked resume: the tick after the last one started is due one period from
        ``now`` (or at the frame then); the new schedule goes out."""
        tick = self._tick
        with self._lock:
            started = min(self._step_k - 1, tick.released)
            tick.released = started  # a tick opened in advance is opened again, re-timed
        self._frames.reanchor(now, started)
        t0 = self._due(started + 1) - (started + 1) * self.dt
        if started + 1 < self.experiment.n_ticks:
            # Open the resumed tick now: an agent may answer it before this thread's step at
            # its due time (an answer to a tick not open yet is not counted: it would be late).
            due = t0 + (started + 1) * self.dt
            with self._lock:
                tick.release(started + 1, due, due)
        self._halt_after = None
        self._step_k = started + 1
        self._send_schedule(started + 1, self.experiment.n_ticks - 1, t0, record=True)

    def _count(self, account: TickAccount, late: list[int]) -> None:
        """Account a closed tick and count it (late or on time)."""
        self._account(account)
        self._tally.count(account.k, late)

    def _lockstep_step(self) -> None:
        """Close every completed tick, release more, and find agents that stopped answering."""
        tick = self._tick
        accounts = []
        with self._lock:
            while tick.base_complete():
                accounts.append(self._close_base([], True))
        for account in accounts:
            self._account(account)
        self.summary.ticks += len(accounts)
        if tick.base >= self.experiment.n_ticks:
            self._stop_reason = "completed"
            return
        if not self._paused:
            self._release_window()
        now = self._clock()
        waiting = tick.base <= tick.released and not self._paused  # an open tick to answer
        if waiting and not accounts and now - tick.last_progress > self.answer_timeout_s:
            with self._lock:  # a degraded agent waits for its board link: not lost
                if "degraded" in self.agent_states.values():
                    return
            for j in tick.unanswered():
                self._on_agent_gone(
                    self.names[j], tick.base, f"no answer within {self.answer_timeout_s} s"
                )
            with self._lock:
                tick.last_progress = now

    def _release_window(self) -> None:
        """Lockstep: release ticks up to ``lockstep_window`` ahead of the oldest open one.

        Releases in steps of half a window (one tick message covers several ticks), or at
        once when nothing is in flight.
        """
        tick = self._tick
        target = min(tick.base - 1 + self.window, self.experiment.n_ticks - 1)
        if target <= tick.released:
            return
        idle = tick.base > tick.released
        if idle or target - tick.released >= max(1, self.window // 2):
            self._release(target, self._clock())

    def _release(self, k: int, scheduled: float) -> None:
        """Open ticks up to ``k`` (scheduled at ``scheduled`` [s]) and send tick ``k``."""
        tick = self._tick
        with self._lock:
            now = self._clock()
            for j in range(tick.released + 1, k + 1):
                tick.release(j, scheduled, now)
        self._send_tick(k, sorted(self.lost))

    def _close_base(self, late: list[int], complete: bool) -> TickAccount:
        """The account of the oldest open tick, which is closed (call under the lock)."""
        tick = self._tick
        slot = tick.base % tick.window
        answered = tick.answered_at[slot]
        done = math.nan
        if complete:
            counted = answered[~tick.lost]
            done = float(np.nanmax(counted)) if np.isfinite(counted).any() else self._clock()
        sent = float(tick.sent[slot])
        answers = answered - sent if self._record_ticks else None
        account = TickAccount(tick.base, float(tick.scheduled[slot]), sent, done, late, answers)
        tick.close_base()
        return account

    def _account(self, account: TickAccount) -> None:
        """Record the timing account of a tick (times on the manager clock [s])."""
        k, scheduled = account.k, account.scheduled
        completion = account.done - scheduled
        self._tally.completed(k, completion)
        if account.answers is None:
            return
        records = self._records
        if records is None:
            return
        with self._lock:
            records.tick(
                k,
                self._wall_ns(),
                scheduled_s=scheduled - self._clock_origin,
                send_delay_s=account.sent - scheduled,
                completion_s=completion,
                late=account.late,
                missing=sorted(self.lost),
                answer_s=account.answers,
            )

    def _handle(self, item: tuple[Any, ...]) -> None:
        """One event while ticking."""
        kind = item[0]
        k = self._tick.base
        if kind == _COMPLETE and self._realtime:
            # A realtime tick is complete: hand the records over now, while the swarm waits
            # for its next tick, rather than at a due time, when the recorder's work would
            # compete with every agent's.
            self._flush_records(self._clock())
            return
        if kind in (_COMPLETE, _STOPPED):
            return  # the loop closes the tick; stopped agents matter only at the stop
        if kind == _GONE:
            reason = "liveliness token lost (killed or hung)"
            process = self._describe_process(item[1]) if self._describe_process else ""
            self._on_agent_gone(item[1], k, f"{reason}; {process}" if process else reason)
        elif kind == _ALIVE:
            self.alive.add(item[1])
        elif kind == _CONTROL:
            self._on_control(item[1], k)
        elif kind == _STOP:
            self._stop_reason = str(item[1])
        elif kind == _SAFE:
            self._on_agent_safe(item[1], item[2], k, first_tick=item[3] == 0)

    def _wait_until(self, when: float) -> None:
        """Block until ``when`` on the manager clock, still handling stop requests."""
        while True:
            remaining = when - self._clock()
            if remaining <= 0:
                return
            try:
                item = get_within(self._events, remaining)
            except queue.Empty:
                return
            if item[0] == _STOP:
                self._stop_reason = str(item[1])
                return
            if item[0] == _ALIVE:
                self.alive.add(item[1])

    def _send_schedule(
        self, first: int, last: int, t0: float, *, record: bool = False, at: float | None = None
    ) -> None:
        """Self-clocked: send (and keep) the schedule: ticks ``first..last`` due at
        ``t0 + k * dt`` [s, CLOCK_MONOTONIC], with the lost agents. ``record``: also as a
        ``schedule`` event on ``/orchestrator/status`` (the start, a pause, a resume, a loss;
        not the repeats and the frame lock's moves). ``at``: in force now, but sent only then
        [s, manager clock] (the ticking thread sends it; any schedule sent before that
        carries it)."""
        self._schedule = (first, last, t0)
        if at is not None and at > self._clock():
            self._schedule_at = at
            return
        self._schedule_at = None
        missing = tuple(sorted(self.lost))
        message = bus.ScheduleMessage(first, last, t0, self.dt, missing)
        self._tick_pub.put(bus.encode_schedule(message))
        self._schedule_sent = self._clock()
        if record:
            lost = ", ".join(self.names[i] for i in missing) or "none"
            detail = (
                f"self-clocked: ticks {first}..{last} due at T0 + k dt, T0 "
                f"{t0 - self._clock_origin:.6f} s (the manager's clock origin); lost: {lost}"
            )
            self._record_event(ORCHESTRATOR, "schedule", k=first, detail=detail)

    def _send_tick(self, k: int, missing: Sequence[int]) -> None:
        message = bus.TickMessage(k, k * self.dt, tuple(missing), realtime=self._realtime)
        self._tick_pub.put(bus.encode_tick(message))

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
            self.summary.estop_tick = k
            self._record_event(ORCHESTRATOR, "estop", k=k, detail=reason)
            self._stop_reason = f"e-stop at tick {k}{': ' + reason if reason else ''}"
        elif command is bus.ControlCommand.PAUSE and not self._paused:
            self._paused = True
            if self.self_clocked:  # the agents stop after the next tick (no race with it)
                self._halt_after = self._step_k
                first, _, t0 = self._schedule
                self._send_schedule(first, max(first, self._halt_after), t0, record=True)
            self._record_event(ORCHESTRATOR, "paused", k=k, detail=reason)
            self._publish_state("paused", reason)
        elif command is bus.ControlCommand.RESUME and self._paused:
            self._paused = False
            self._reanchor = True
            self._record_event(ORCHESTRATOR, "running", k=k, detail=reason)
            self._publish_state("running", reason)

    def _on_agent_safe(self, name: str, detail: str, k: int, *, first_tick: bool = False) -> None:
        """An agent reported state ``safe`` while ticking: apply ``on_agent_safe``.

        An agent safe from its first tick (no pose, a fault at start) fails the run whatever
        the policy: it never did what the experiment asks.
        """
        if first_tick and not self._stop_reason and not self.summary.failed:
            self.summary.failed = True
            logger.warning("agent %s was safe from its first tick: %s", name, detail)
            if self._display is not None:
                self._display.log(f"agent {name} was safe from its first tick: {detail}")
        if self.experiment.on_agent_safe != "stop" or self._stop_reason:
            return
        self.summary.failed = True
        self._stop_reason = f"agent {name} entered safe mode ({detail}); on_agent_safe = stop"
        if self._display is not None:
            self._display.log(f"agent {name} entered safe mode at tick {k}: {detail}")

    def _on_agent_gone(self, name: str, k: int, reason: str) -> None:
        self.alive.discard(name)
        i = self._index[name]
        if i in self.lost:
            return
        self.lost.add(i)
        with self._lock:
            self._tick.lost[i] = True
            self._tick.recount()
        if not self._realtime and self._tick.released >= 0 and not self._stop_reason:
            # Tell the neighbours now: they may be waiting for this agent's output.
            self._send_tick(self._tick.released, sorted(self.lost))
        elif self.self_clocked and not self._stop_reason:
            self._send_schedule(*self._schedule, record=True)  # the same, with the lost agent
        self.summary.lost.append(name)
        self.summary.lost_at[name] = AgentEvent(k, reason)
        logger.warning("agent %s lost at tick %d: %s", name, k, reason)
        if self._display is not None:
            self._display.log(f"agent {name} lost at tick {k}: {reason}")
        self._record_event(name, "lost", k=k, detail=reason)
        if self.experiment.on_agent_loss == "stop":
            self.summary.failed = True
            self._stop_reason = f"agent {name} lost ({reason}); on_agent_loss = stop"
        elif len(self.lost) == self.n:
            self.summary.failed = True
            self._stop_reason = "every agent is lost"

    # -- stopping ----------------------------------------------------------------------------

    def _stop_agents(self, k: int) -> None:
        """Every agent to safe mode and stopped; wait (bounded) for their tokens to go and for
        their last status (``stopped``, with the final counters: at most
        :data:`STOP_STATUS_GRACE_S` after the last token went)."""
        with self._lock:
            self._stopping = True  # safe states from here on are the stop's, not faults
            stopping = set(self.alive)
            stopped = {name for name in stopping if self.agent_states.get(name) == "stopped"}
        self._publish_state("stopping", self._stop_reason)
        self._record_event(ORCHESTRATOR, "stopping", k=k, detail=self._stop_reason)
        self._control_pub.put(bus.encode_control(bus.ControlCommand.STOP, reason=self._stop_reason))
        clock = self._clock
        deadline = clock() + self.stop_timeout_s
        grace_end = math.inf  # set when the last token went
        while self.alive or not stopping <= stopped:
            self._flush_records()
            if not self.alive and grace_end == math.inf:
                grace_end = clock() + STOP_STATUS_GRACE_S
            remaining = (deadline if self.alive else grace_end) - clock()
            if remaining <= 0:
                if self.alive:
                    logger.warning(
                        "agents still up %s s after the stop command: %s",
                        self.stop_timeout_s,
                        ", ".join(sorted(self.alive)),
                    )
                break
            try:
                item = get_within(self._events, min(remaining, self._flush_period_s * 5))
            except queue.Empty:
                continue
            if item[0] == _GONE:
                self.alive.discard(item[1])
            elif item[0] == _STOPPED:
                stopped.add(item[1])
        self._flush_records()

    def states_now(self) -> dict[str, str]:
        """Each agent's lifecycle state as it last reported it (a copy; any thread)."""
        with self._lock:
            return dict(self.agent_states)

    def _show(self, k: int, start: float, now: float) -> None:
        if self._display is None:
            return
        elapsed = max(now - start, 1e-9)
        states = self.states_now()
        self._display.update(
            StatusSnapshot(
                experiment=self.experiment.name,
                mode=self.mode,
                k=k,
                n_ticks=self.experiment.n_ticks,
                tick_rate_hz=k / elapsed,
                late_ticks=self.summary.late_ticks,
                states=states,
                lost=[self.names[i] for i in sorted(self.lost)],
                paused=self._paused,
            )
        )

    def close(self) -> None:
        """Close the bus session, then hand the last records to the sink. Idempotent."""
        if self._session is not None:
            try:
                self._publish_state("stopped", self._stop_reason)
            finally:
                self._entities.clear()
                self._session.close()
                self._session = None
        self._flush_records()
        if self._feed is not None:
            self._feed.hand_over(final=True)

    @property
    def estop_tick(self) -> int | None:
        """Tick at which an e-stop was received, if any."""
        return self._estop_tick

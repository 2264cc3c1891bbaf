"""Baseline for the swarm benchmark: the bus alone, with the runtime's process layout.

One router session (like the orchestrator's embedded bus, same configuration and QoS) and N
client *processes* (like agents). Each client subscribes to the tick key and to its two ring
neighbours' outputs; on a tick it answers at once, from the bus callback, with a y message of
the agents' size (3 values + a report attachment). No vehicle, no controller, no recording:
what is left is the cost of Zenoh with one Python process per agent on this machine, which
bounds what the full runtime can reach here.

    python benchmarks/bare_bus.py --agents 32 --rate 100 --seconds 5     # realtime
    python benchmarks/bare_bus.py --agents 8 --rate 100 --lockstep       # round trips
    python benchmarks/bare_bus.py --short                                 # CI-sized (< 15 s)
    python benchmarks/bare_bus.py --agents 32 --rate 100 --self-clocked   # no tick messages
    python benchmarks/bare_bus.py --agents 8 --rate 100 --lockstep --window 8
    python benchmarks/bare_bus.py --agents 8 --rate 100 --lockstep --tick-work frisbee

Realtime: tick k is sent at ``T0 + k dt``; a tick is late when some answer is not in when the
next one is due (as in the runtime). Lockstep: tick k+1 is sent from the callback of the last
answer of tick k (one round trip per tick, a barrier: the slowest form of lockstep). In
lockstep the clients run under ``SCHED_BATCH``, as the runtime's lockstep agents do
(:mod:`hilswarm.agents.scheduling`).

Two leaner patterns bound what any design on this bus could reach, not just the runtime's:

* ``--self-clocked`` (realtime): no tick messages at all. The router sends T0 once; every
  client then answers tick k at ``T0 + k dt`` of its own monotonic clock (the machine's clock,
  shared by every process here). Only the messages no design can do without are left: each
  y to the two neighbours and to the manager.
* ``--window W`` (lockstep): clients run tick k as soon as their neighbours' y_{k-1} are in,
  up to a horizon the router moves W ticks ahead of the slowest completed tick, one message
  per half window (as ``hilswarm run`` with ``lockstep_window = W``).

``--tick-work CASE`` (any pattern) makes it the *work floor* of a fleet: each client also runs
an agent's own tick work (``Agent.tick_work`` of a ``benchmarks/agent_tick.py`` case: the
Frisbee on ``sim://`` with its waypoint controller, the integrator with consensus, or the
spring-mass-damper) before it answers (in its bus callback, or on its clock thread when
self-clocked), with the newest outputs it heard from its neighbours (its tick path rehearsed
first, as an agent's is). No worker thread, tick engine, manager accounting or recording: what
the bus and that work cost together on this machine, a floor for any runtime doing the work
(``swarm_ticks.py --work-floor``).

``--spin-us US`` (any pattern) has each client burn ``US`` µs of its own thread's CPU time
before each answer: work of a known cost, hot (a tight loop that touches no data and evicts
nothing), so the speed it leaves bounds from above what any real work of that CPU cost could
leave. ``benchmarks/work_budget.py`` sweeps it: how much work per tick a client can do and
keep a given share of the bare bus's lockstep speed.
"""

from __future__ import annotations

import argparse
import functools
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass

import numpy as np
import zenoh
from cpu_sampler import CpuSampler
from hilswarm.agents import bus, bus_callback
from hilswarm.agents.scheduling import use_batch_scheduling

_Y_VALUES = np.array([0.5, -0.25, 1.0])
_REPORT = bus.encode_report(bus.AgentTiming(), np.zeros(2), np.zeros(2))


@dataclass
class BareResult:
    """Figures of one bare-bus run."""

    n: int
    rate_hz: float
    mode: str
    ticks: int
    late_ticks: int
    completion_s: np.ndarray  # per complete tick [s]
    wall_s: float
    startup_s: float = float("nan")  # first client started to every client alive [s]
    client_cpu_s: float = float("nan")  # one client process's CPU per tick [s] (mean)
    cpu_busy: float = float("nan")  # the machine's CPUs busy during the ticks [0, 1]

    @property
    def late_fraction(self) -> float:
        return self.late_ticks / max(1, self.ticks)

    @property
    def speed(self) -> float:
        """Lockstep: experiment time per wall time."""
        return self.ticks / self.rate_hz / self.wall_s if self.wall_s > 0 else 0.0

    def percentiles_ms(self) -> tuple[float, float]:
        """(p50, p99) completion [ms]; late ticks count as infinite."""
        values = np.concatenate([self.completion_s, np.full(self.late_ticks, np.inf)])
        if not values.size:
            return float("nan"), float("nan")
        p50, p99 = np.percentile(values, [50, 99], method="inverted_cdf")
        return float(p50) * 1e3, float(p99) * 1e3


def _ring_neighbours(index: int, n: int) -> list[int]:
    """Indices of client ``index``'s two ring neighbours (fewer for n < 3)."""
    steps = (1, n - 1) if n > 2 else (1,) if n == 2 else ()
    return [(index + step) % n for step in steps]


#: The self-clocked start message: T0 [s, time.monotonic] and the tick period [s].
_START = struct.Struct("<dd")

#: ``--tick-work`` choices: the cases of ``benchmarks/agent_tick.py``.
TICK_WORK_CASES = ("frisbee", "consensus", "smd")


def spin(seconds: float) -> None:
    """Burn ``seconds`` [s] of this thread's CPU time (``time.thread_time``) in a tight loop:
    work of a known CPU cost that neither waits nor touches data (``--spin-us``). Time the
    thread spends preempted does not count."""
    clock = time.thread_time
    end = clock() + seconds
    while clock() < end:
        pass


class TickWork:
    """One agent's own tick work (``Agent.tick_work``: controller, vehicle, board, sensing,
    encoding) run by a bare client before each answer, for ``--tick-work``.

    The agent is one of ``benchmarks/agent_tick.py``'s cases, built as an agent process builds
    it and never on a bus; the neighbours' outputs it steps with are the newest ones this
    client heard (no data until the first). Its tick path is rehearsed first, as an agent's is
    before it arms. What a bare bus with this work measures is what the bus and the fleet's
    own work cost together, without a worker thread, tick engine, manager accounting or
    recording.
    """

    def __init__(self, case_name: str, ring_neighbours: list[int]) -> None:
        from agent_tick import cases, offline_agent  # noqa: PLC0415 - an agent's imports, if asked
        from hilswarm.agents.agent import Agent  # noqa: PLC0415
        from hilswarm.agents.rehearsal import rehearse  # noqa: PLC0415

        case = {case.name: case for case in cases()}[case_name]
        self._agent = offline_agent(case.config)
        rehearse(Agent, case.config)  # the tick path warm, as an agent's before it arms
        names = list(case.config.neighbours)
        #: ring index -> the case's neighbour name (the case has at most two)
        self.names = dict(zip(ring_neighbours, names, strict=False))
        self.neighbours: dict[str, np.ndarray | None] = dict.fromkeys(names)

    def heard(self, j: int, values: np.ndarray) -> None:
        """Ring neighbour ``j``'s newest output (its values as decoded)."""
        name = self.names.get(j)
        if name is not None:
            self.neighbours[name] = values

    def tick(self, k: int, t: float) -> tuple[bytes, bytes]:
        """Tick ``k`` at experiment time ``t`` [s]: the y message and its report."""
        y_payload, report, _u, _x = self._agent.tick_work(k, t, neighbours=self.neighbours)
        return y_payload, report


def client(
    index: int, n: int, endpoint: str, pattern: str, tick_work: str = "", *, spin_s: float = 0.0
) -> None:
    """One client process; ``pattern``: ``tick`` (realtime), ``barrier`` (lockstep, answering
    each tick as ``tick`` does), ``clock`` or ``window`` (see the module doc); ``tick_work``: a
    :class:`TickWork` case run before each answer (empty: none); ``spin_s``: CPU time [s]
    burnt before each answer (:func:`spin`; 0: none)."""
    keys = bus.BusKeys("bare")
    if pattern in ("barrier", "window"):  # lockstep: batch work, as the runtime's agents
        use_batch_scheduling()
    session = bus.open_session(bus.client_config([endpoint]))
    name = f"r{index}"
    publisher = session.declare_publisher(keys.y(name), **bus.TICK_PATH_QOS)
    neighbours = _ring_neighbours(index, n)
    work = TickWork(tick_work, neighbours) if tick_work else None
    lock = threading.Lock()
    # window pattern: the newest y_k heard per neighbour, our next tick, the released horizon
    heard = dict.fromkeys(neighbours, -1)
    progress = {"next": 0, "horizon": -1}
    stop = threading.Event()

    def answer(k: int, t: float) -> None:
        if spin_s > 0:
            spin(spin_s)
        if work is None:
            publisher.put(bus.encode_vector(k, t, _Y_VALUES), attachment=_REPORT)
            return
        y_payload, report = work.tick(k, t)
        publisher.put(y_payload, attachment=report)

    def advance() -> None:  # window pattern, under the lock
        while progress["next"] <= progress["horizon"] and all(
            heard[j] >= progress["next"] - 1 for j in neighbours
        ):
            answer(progress["next"], 0.0)
            progress["next"] += 1

    def on_neighbour(j: int, sample: zenoh.Sample) -> None:
        k, _t, values = bus.decode_vector(sample.payload.to_bytes())
        if work is not None:
            values.flags.writeable = False  # as an agent hands it to its controller
            work.heard(j, values)
        if pattern == "window":
            with lock:
                heard[j] = max(heard[j], k)
                advance()

    def on_tick(sample: zenoh.Sample) -> None:
        tick = bus.decode_tick(sample.payload.to_bytes())
        if pattern in ("tick", "barrier"):
            answer(tick.k, tick.t)
            return
        with lock:
            progress["horizon"] = max(progress["horizon"], tick.k)
            advance()

    def run_clock(t0: float, period: float) -> None:
        k = 0
        while not stop.is_set():
            due = t0 + k * period
            remaining = due - time.monotonic()
            if remaining > 0 and stop.wait(remaining):
                return
            answer(k, k * period)
            k += 1

    clocks: list[threading.Thread] = []

    def on_start(sample: zenoh.Sample) -> None:
        t0, period = _START.unpack(sample.payload.to_bytes())
        clocks.append(threading.Thread(target=run_clock, args=(t0, period), daemon=True))
        clocks[-1].start()

    entities = [
        session.declare_subscriber(
            keys.y(f"r{j}"),
            bus_callback.callback(functools.partial(on_neighbour, j)),
        )
        for j in neighbours
    ]
    if pattern == "clock":
        entities.append(session.declare_subscriber(keys.control, bus_callback.callback(on_start)))
    else:
        entities.append(session.declare_subscriber(keys.tick, bus_callback.callback(on_tick)))
    entities.append(session.liveliness().declare_token(keys.alive(name)))
    sys.stdin.read()  # the parent closes stdin to stop us
    stop.set()
    for clock in clocks:  # its last put must not meet a closed session
        clock.join(10)
    entities.clear()
    session.close()


def run_bare(
    *,
    n: int,
    rate_hz: float,
    seconds: float,
    lockstep: bool,
    self_clocked: bool = False,
    window: int = 0,
    unix: bool = False,
    tick_work: str = "",
    spin_us: float = 0.0,
) -> BareResult:
    """Start the router and ``n`` client processes, tick, and return the figures.

    ``self_clocked`` (realtime only): clients keep the schedule themselves. ``window`` > 0
    (lockstep only): free-running clients within a released horizon instead of a barrier.
    ``tick_work``: each client runs that case's agent tick work before each answer
    (:class:`TickWork`; empty: none, the plain bare bus). ``spin_us``: each client burns that
    much of its CPU time [µs] before each answer (:func:`spin`; 0: none).
    """
    if tick_work and tick_work not in TICK_WORK_CASES:
        raise ValueError(f"tick_work {tick_work!r}: expected one of {TICK_WORK_CASES}")
    if not spin_us >= 0:
        raise ValueError(f"spin_us {spin_us!r}: expected a CPU time >= 0 [µs]")
    if self_clocked and lockstep:
        raise ValueError("self_clocked is a realtime pattern; window is the lockstep one")
    if window and not lockstep:
        raise ValueError("window is a lockstep pattern")
    keys = bus.BusKeys("bare")
    folder = tempfile.TemporaryDirectory(prefix="hilswarm-bare-")
    listen = f"unixsock-stream/{folder.name}/bus.sock" if unix else bus.loopback_endpoint(0)
    session = bus.open_session(bus.listen_config([listen]))
    endpoint = listen if unix else bus.bound_endpoints(session)[0]  # the port it bound
    lock = threading.Lock()
    period = 1.0 / rate_hz
    n_ticks = max(1, round(seconds * rate_hz))
    state = {"k": -1, "count": 0, "scheduled": 0.0, "t0": 0.0, "complete": -1, "horizon": -1}
    counts: dict[int, int] = {}  # self-clocked and window: answers per tick
    completion: list[float] = []
    done = threading.Event()
    tick_pub = session.declare_publisher(keys.tick, **bus.TICK_PATH_QOS)
    start_pub = session.declare_publisher(keys.control, **bus.TICK_PATH_QOS)

    def send(k: int, scheduled: float) -> None:
        state["k"], state["count"], state["scheduled"] = k, 0, scheduled
        tick_pub.put(bus.encode_tick(bus.TickMessage(k, k / rate_hz)))

    def release(horizon: int) -> None:  # window pattern, under the lock
        state["horizon"] = horizon
        tick_pub.put(bus.encode_tick(bus.TickMessage(horizon, horizon / rate_hz)))

    def on_y_counted(k: int) -> None:  # self-clocked and window patterns, under the lock
        if k >= n_ticks:
            return
        counts[k] = counts.get(k, 0) + 1
        if self_clocked:
            if counts[k] == n:
                completion.append(time.monotonic() - (state["t0"] + k * period))
                del counts[k]
            return
        while counts.get(state["complete"] + 1, 0) == n:
            del counts[state["complete"] + 1]
            state["complete"] += 1
        if state["complete"] >= n_ticks - 1:
            done.set()
        elif state["complete"] + window >= state["horizon"] + max(1, window // 2):
            release(min(n_ticks - 1, state["complete"] + window))

    def on_y(sample: zenoh.Sample) -> None:
        k = int.from_bytes(sample.payload.to_bytes()[:8], "little", signed=True)
        with lock:
            if self_clocked or window:
                on_y_counted(k)
                return
            if k != state["k"]:
                return
            state["count"] += 1
            if state["count"] < n:
                return
            now = time.perf_counter()
            completion.append(now - state["scheduled"])
            if lockstep:
                if k + 1 < n_ticks:
                    send(k + 1, now)
                else:
                    done.set()

    alive: set[str] = set()
    all_alive = threading.Event()

    def on_alive(sample: zenoh.Sample) -> None:
        alive.add(str(sample.key_expr))
        if len(alive) >= n:
            all_alive.set()

    entities = [
        session.declare_subscriber(keys.all_outputs, bus_callback.callback(on_y)),
        session.liveliness().declare_subscriber(
            keys.all_alive, bus_callback.callback(on_alive), history=True
        ),
    ]
    pattern = "clock" if self_clocked else "window" if window else "barrier" if lockstep else "tick"
    started = time.perf_counter()
    command = [sys.executable, os.path.abspath(__file__)]
    if tick_work:
        command += ["--tick-work", tick_work]
    if spin_us:
        command += ["--spin-us", repr(float(spin_us))]
    clients = [
        subprocess.Popen(
            [*command, "--client", str(i), str(n), endpoint, pattern], stdin=subprocess.PIPE
        )
        for i in range(n)
    ]
    late = 0
    try:
        if not all_alive.wait(120):
            raise RuntimeError(f"only {len(alive)} of {n} bare clients came up")
        startup = time.perf_counter() - started
        time.sleep(0.5)  # let every subscription reach the router
        sampler = CpuSampler([process.pid for process in clients]).start()
        start = time.perf_counter()
        if lockstep:
            with lock:
                if window:
                    release(min(n_ticks - 1, window - 1))
                else:
                    send(0, start)
            done.wait(max(60.0, 20 * seconds))
        elif self_clocked:
            state["t0"] = time.monotonic() + 0.1
            start_pub.put(_START.pack(state["t0"], period))
            time.sleep(0.1 + seconds + 2 * period)
        else:
            for k in range(n_ticks):
                due = start + k * period
                while (remaining := due - time.perf_counter()) > 0:
                    time.sleep(min(remaining, 0.002) if remaining > 0.0005 else 0)
                with lock:
                    if state["k"] >= 0 and state["count"] < n:
                        late += 1
                    send(k, due)
            time.sleep(2 * period)
        wall = time.perf_counter() - start
        sampler.stop()
        client_cpu = sampler.total_s() / n / n_ticks
        cpu_busy = sampler.machine_busy()
    finally:
        for process in clients:
            if process.stdin is not None:
                process.stdin.close()
        for process in clients:
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
        entities.clear()
        session.close()
        folder.cleanup()
    with lock:
        times = np.array(completion)
    if self_clocked:  # a tick is late when its last answer came after the next one was due
        times = times[times <= period]
        late = n_ticks - times.size
    return BareResult(
        n, rate_hz, "lockstep" if lockstep else "realtime", n_ticks, late, times, wall, startup,
        client_cpu, cpu_busy,
    )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--client", nargs=4, metavar=("INDEX", "N", "ENDPOINT", "PATTERN"), help=argparse.SUPPRESS
    )
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--rate", type=float, default=100.0, help="tick rate [Hz]")
    parser.add_argument("--seconds", type=float, default=5.0, help="realtime run length [s]")
    parser.add_argument("--lockstep", action="store_true", help="round trips as fast as possible")
    parser.add_argument(
        "--self-clocked", action="store_true", help="realtime without tick messages"
    )
    parser.add_argument(
        "--window", type=int, default=0, help="lockstep: free running within W released ticks"
    )
    parser.add_argument(
        "--unix", action="store_true", help="unix-socket transport instead of TCP on loopback"
    )
    parser.add_argument(
        "--tick-work",
        choices=TICK_WORK_CASES,
        default="",
        help="each client also runs this agent_tick.py case's tick work before each answer "
        "(rehearsed first): what the bus and that work cost together, a floor for a runtime",
    )
    parser.add_argument(
        "--spin-us",
        type=float,
        default=0.0,
        metavar="US",
        help="each client also burns US µs of its CPU time before each answer (hot work of a "
        "known cost; benchmarks/work_budget.py sweeps it)",
    )
    parser.add_argument(
        "--short", action="store_true", help="CI-sized: each pattern, 8 clients at 50 Hz"
    )
    args = parser.parse_args(argv)
    if args.client:
        index, n, endpoint, pattern = args.client
        client(int(index), int(n), endpoint, pattern, args.tick_work, spin_s=args.spin_us * 1e-6)
        return 0
    if not args.spin_us >= 0:
        parser.error(f"--spin-us {args.spin_us}: expected a CPU time >= 0 [µs]")
    if args.self_clocked and args.lockstep:
        parser.error("--self-clocked is a realtime pattern (use --window with --lockstep)")
    if args.window and not args.lockstep:
        parser.error("--window needs --lockstep")
    if args.window < 0:
        parser.error(f"--window {args.window}: expected a number of ticks >= 1")
    if args.short:  # every pattern, CI-sized: 8 clients at 50 Hz
        runs = [
            dict(lockstep=False, self_clocked=False, window=0, seconds=2.0),
            dict(lockstep=False, self_clocked=True, window=0, seconds=2.0),
            dict(lockstep=True, self_clocked=False, window=8, seconds=2.0),
        ]
        n, rate = 8, 50.0
    else:
        runs = [
            dict(lockstep=args.lockstep, self_clocked=args.self_clocked, window=args.window,
                 seconds=args.seconds)
        ]  # fmt: skip
        n, rate = args.agents, args.rate
    for options in runs:
        result = run_bare(n=n, rate_hz=rate, unix=args.unix, tick_work=args.tick_work,
                          spin_us=args.spin_us, **options)  # fmt: skip
        print(describe(result, self_clocked=bool(options["self_clocked"]),
                       window=int(options["window"]), tick_work=args.tick_work,
                       spin_us=args.spin_us))  # fmt: skip
    return 0


def describe(
    result: BareResult,
    *,
    self_clocked: bool,
    window: int,
    tick_work: str = "",
    spin_us: float = 0.0,
) -> str:
    """One line of figures for a run: its timing, one client's CPU per tick, the machine's
    CPUs busy while it ticked and the 1-minute load at its end."""
    p50, p99 = result.percentiles_ms()
    what = f"bare bus + {tick_work} tick work" if tick_work else "bare bus"
    if spin_us:
        what += f" + {spin_us:g} µs spin"
    head = f"{result.n} clients at {result.rate_hz:g} Hz"
    cpu = (f"; client {result.client_cpu_s * 1e3:.3f} ms of CPU per tick, "
           f"{100 * result.cpu_busy:.0f} % busy, load {os.getloadavg()[0]:.2f}")  # fmt: skip
    if result.mode == "lockstep":
        if window:
            return (f"{what}, lockstep window {window}, {head}: {result.speed:.1f}x real time"
                    + cpu)  # fmt: skip
        return (f"{what}, lockstep barrier, {head}: {result.speed:.1f}x real time "
                f"(round trip p50 {p50:.2f} ms)" + cpu)  # fmt: skip
    how = "self-clocked" if self_clocked else "ticked"
    return (f"{what}, realtime {how}, {head}: p50 {p50:.2f} ms, p99 {p99:.2f} ms, "
            f"late {100 * result.late_fraction:.2f} %" + cpu)  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())

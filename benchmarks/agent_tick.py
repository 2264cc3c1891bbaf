"""Agent tick benchmark: the agent's own per-tick work, in one process, without the bus.

What one agent does for every tick besides talking to Zenoh: take in its neighbours' outputs
(decode), decode the tick, run its controller (``ControlModel.step``), apply ``u`` to the
vehicle, exchange with the board (a ``sim://`` board advancing the pin-level plant), sense
``y`` and encode ``y`` and the tick report. It is measured through the agent's own methods
(:meth:`Agent.receive_neighbour`, :meth:`Agent.tick_work`) on hardware built exactly as an
agent process builds it (:func:`build_hardware`), for three cases:

* ``frisbee``   — FrisbeeBot on ``sim://`` with the waypoint controller (2 ring neighbours);
* ``consensus`` — SimulatedVehicle (2-D integrator) with linear consensus (2 neighbours);
* ``smd``       — SimulatedVehicle (spring-mass-damper) with state feedback (no neighbours).

Each figure is also given as a multiple of two baselines measured in the same process: a bare
numpy matrix-vector step of the controller's size (``K @ y``, 2 x 4) and a bare Zenoh put of an
agent's y message (with its report attachment) from a client session to a loopback router
that has a subscriber for it.

    python benchmarks/agent_tick.py                 # 20000 ticks per case
    python benchmarks/agent_tick.py --short         # CI-sized (< 20 s)
    python benchmarks/agent_tick.py --profile frisbee   # cProfile of one case
    python benchmarks/agent_tick.py --idle-ms 0     # hot ticks only
    python benchmarks/agent_tick.py --idle-kind spin    # wait in a busy loop, not asleep

The CPU per tick is measured twice: back to back (hot: the figure of the table's first
column, the agent's own work at its cheapest) and, for fewer ticks, each after ``--idle-ms``
of sleep (default 10 ms, one period at 100 Hz): what a realtime agent pays, its tick starting
with cold caches after the wait. ``x hot`` is the ratio of the two, taken in the same run. On
the 2-core development machine (a virtual machine) a Frisbee tick after 10 ms idle costs
~3-4x a hot one (docs/agent_tick.md).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import platform
import pstats
import statistics
import struct
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from hilswarm.agents import bus, bus_callback
from hilswarm.agents.agent import Agent, AgentConfig, build_hardware

#: Control period of every case [s] (100 Hz, the benchmark target rate).
DT = 0.01
#: Waypoints of the Frisbee case [m, world frame]: a 1 m square, driven eight times (~30000
#: ticks at 100 Hz), so the robot keeps pivoting and driving and never holds still.
SQUARE = [[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]] * 8


@dataclass(frozen=True)
class Case:
    """One benchmark case: an agent configuration and the outputs its neighbours send."""

    name: str
    title: str
    config: AgentConfig


def cases() -> list[Case]:
    """The three cases of the module docstring."""
    ring = ("a0", "a1", "a2")
    return [
        Case(
            "frisbee",
            "Frisbee on sim:// + waypoint",
            AgentConfig(
                experiment="bench",
                name="a0",
                agent_names=ring,
                neighbours=("a1", "a2"),
                vehicle="frisbee",
                link="sim://",
                controller="waypoint",
                dt=DT,
                params={"waypoints": SQUARE},
                initial_state=(0.0, 0.0, 0.0),
            ),
        ),
        Case(
            "consensus",
            "integrator + consensus",
            AgentConfig(
                experiment="bench",
                name="a0",
                agent_names=ring,
                neighbours=("a1", "a2"),
                vehicle="simulated",
                link=None,
                controller="consensus",
                dt=DT,
                vehicle_params={"plant": "integrator", "plant_params": {"n_dims": 2}},
                initial_state=(1.0, 0.0),
            ),
        ),
        Case(
            "smd",
            "spring-mass-damper + state feedback",
            AgentConfig(
                experiment="bench",
                name="a0",
                agent_names=("a0",),
                neighbours=(),
                vehicle="simulated",
                link=None,
                controller="state_feedback",
                dt=DT,
                vehicle_params={"plant": "spring_mass_damper"},
                params={"K": [[3.01, 4.0, 0.0, 0.0], [0.0, 0.0, 3.01, 4.0]]},
                initial_state=(4.0, 0.0, -4.0, 0.0),
            ),
        ),
    ]


def offline_agent(config: AgentConfig) -> Agent:
    """An agent with its hardware built and its lifecycle at ``running``, never on a bus."""
    agent = Agent(config, ["tcp/127.0.0.1:9"])  # never connected: no session is opened
    agent.use_hardware(build_hardware(config))
    for event in ("connect", "configure", "arm", "start"):
        agent.lifecycle.send(event)
    return agent


#: How a wait before a measured tick is named in the output, per ``--idle-kind``: (the text,
#: the column's head).
WAIT_WORDS = {"sleep": ("idle", "after idle"), "spin": ("spinning", "after spin")}


def pause(idle_s: float, kind: str = "sleep") -> None:
    """Wait ``idle_s`` [s] between two measured steps (not counted).

    ``"sleep"``: the thread sleeps and the CPU may idle, as a realtime agent waits for its
    next tick. ``"spin"``: the thread stays busy in a tight loop on the monotonic clock (the
    CPU never idles and nothing else of this process runs): whatever the tick then pays more
    than hot is not the CPU's idle state.
    """
    if kind == "spin":
        end = time.monotonic() + idle_s
        while time.monotonic() < end:
            pass
    else:
        time.sleep(idle_s)


def tick_loop(case: Case) -> Callable[..., float]:
    """A function running ``n`` more ticks of ``case``; returns CPU seconds per tick.

    With ``idle_s`` > 0 the thread waits that long before each tick (not counted; ``kind``,
    see :func:`pause`): a realtime agent waits for its next tick like that, and its tick
    starts with cold caches.
    """
    agent = offline_agent(case.config)
    n_out = int(agent.hardware.vehicle.n_outputs)
    neighbour_y = {
        name: np.linspace(0.1, 0.3, n_out) + i for i, name in enumerate(case.config.neighbours)
    }
    state = {"k": 0}
    clock = time.thread_time  # CPU time of this thread: what the agent pays, load or not

    def run(n: int, idle_s: float = 0.0, kind: str = "sleep") -> float:
        k0 = state["k"]
        # What the manager and the neighbours send is encoded by them, not timed here.
        messages = [
            (
                [
                    (name, bus.encode_vector(k - 1, (k - 1) * DT, values))
                    for name, values in neighbour_y.items()
                ]
                if k > 0  # neighbours' y_{k-1} arrive before tick k
                else [],
                bus.encode_tick(bus.TickMessage(k, k * DT)),
            )
            for k in range(k0, k0 + n)
        ]
        receive, work, decode_tick = agent.receive_neighbour, agent.tick_work, bus.decode_tick
        spent = 0.0
        start = clock()
        for outputs, tick_payload in messages:
            if idle_s:  # the condition measured: the thread waits between ticks
                spent += clock() - start
                pause(idle_s, kind)
                start = clock()
            for name, payload in outputs:
                receive(name, payload)
            tick = decode_tick(tick_payload)
            work(tick.k, tick.t)
        spent += clock() - start
        state["k"] = k0 + n
        return spent / n

    return run


def measure(run: Callable[..., float], ticks: int, repeats: int) -> float:
    """Median over ``repeats`` batches of ``ticks // repeats`` ticks [CPU s per tick]."""
    batch = max(1, ticks // repeats)
    run(min(batch, 200))  # warm-up: first ticks, lazy imports, caches
    return statistics.median(run(batch) for _ in range(repeats))


def numpy_baseline(repeats: int) -> float:
    """CPU seconds per bare ``K @ y`` (2 x 4 gain, the state-feedback size)."""
    gain = np.array([[3.01, 4.0, 0.0, 0.0], [0.0, 0.0, 3.01, 4.0]])
    y = np.array([4.0, 0.0, -4.0, 0.0])
    n = 20000
    best = []
    for _ in range(repeats):
        start = time.thread_time()
        for _ in range(n):
            gain @ y
        best.append((time.thread_time() - start) / n)
    return statistics.median(best)


_HEADER = struct.Struct("<qd")


def _numpy_steps(gain: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Six small numpy steps of the kind a tick takes (matvec, asarray, flags, encode,
    decode, clip)."""
    u = gain @ y
    values = np.asarray(u, dtype=np.float64)
    u.flags.writeable = False
    payload = _HEADER.pack(1, DT) + values.tobytes()
    decoded = np.frombuffer(payload, dtype="<f8", offset=_HEADER.size).copy()
    return np.clip(decoded, -1.0, 1.0)


def _python_steps(gain: list[list[float]], y: list[float]) -> list[float]:
    """The same steps on Python floats (struct for the encoding)."""
    u = [sum(g * v for g, v in zip(row, y, strict=True)) for row in gain]
    payload = _HEADER.pack(1, DT) + struct.pack(f"<{len(u)}d", *u)
    decoded = struct.unpack_from(f"<{len(u)}d", payload, _HEADER.size)
    return [min(max(v, -1.0), 1.0) for v in decoded]


def steps_after_idle(idle_s: float, n: int, kind: str = "sleep") -> dict[str, tuple[float, float]]:
    """Median CPU seconds of :func:`_numpy_steps` and :func:`_python_steps`, ``(hot, after
    idle_s of waiting)`` each (``kind``: see :func:`pause`): what the wait costs numpy code
    against plain Python."""
    gain = [[3.01, 4.0, 0.0, 0.0], [0.0, 0.0, 3.01, 4.0]]
    y = [4.0, 0.0, -4.0, 0.0]
    cases = {
        "numpy": (_numpy_steps, (np.array(gain), np.array(y))),
        "python": (_python_steps, (gain, y)),
    }
    clock = time.thread_time
    figures = {}
    for name, (steps, args) in cases.items():
        hot, cold = [], []
        for _ in range(max(n, 200)):
            start = clock()
            steps(*args)
            hot.append(clock() - start)
        for _ in range(n):
            pause(idle_s, kind)
            start = clock()
            steps(*args)
            cold.append(clock() - start)
        figures[name] = (statistics.median(hot), statistics.median(cold))
    return figures


def zenoh_baseline(n: int) -> tuple[float, float] | None:
    """Bare Zenoh put of a y message with its report, client -> loopback router.

    Returns ``(CPU seconds of the calling thread, wall seconds)`` per put, or ``None`` when
    no loopback session can be opened.
    """
    keys = bus.BusKeys("bench")
    try:
        router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
        endpoint = bus.bound_endpoints(router)[0]  # the free port it bound
    except bus.BusConnectionError as exc:
        print(f"(no Zenoh baseline: {exc})", file=sys.stderr)
        return None
    received = [0]
    try:
        subscriber = router.declare_subscriber(
            keys.y("a0"),
            bus_callback.callback(lambda _s: received.__setitem__(0, received[0] + 1)),
        )
        client = bus.open_session(bus.client_config([endpoint]))
        try:
            publisher = client.declare_publisher(keys.y("a0"), **bus.TICK_PATH_QOS)
            deadline = time.monotonic() + 5.0
            while not bus.has_subscribers(publisher) and time.monotonic() < deadline:
                time.sleep(0.01)
            payload = bus.encode_vector(1, DT, np.zeros(3))
            report = bus.encode_report(bus.AgentTiming(), np.zeros(2), np.zeros(5))
            for _ in range(200):  # warm-up
                publisher.put(payload, attachment=report)
            start, start_cpu = time.perf_counter(), time.thread_time()
            for _ in range(n):
                publisher.put(payload, attachment=report)
            per_put = ((time.thread_time() - start_cpu) / n, (time.perf_counter() - start) / n)
            publisher.undeclare()
        finally:
            client.close()
        subscriber.undeclare()
    finally:
        router.close()
    return per_put


def profile(case: Case, ticks: int) -> None:
    """Print the cProfile of ``ticks`` ticks of ``case`` (after a warm-up)."""
    run = tick_loop(case)
    run(200)
    profiler = cProfile.Profile()
    profiler.runcall(run, ticks)
    pstats.Stats(profiler).sort_stats("tottime").print_stats(25)


def main(argv: list[str] | None = None) -> int:
    """Command line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--short", action="store_true", help="CI-sized run (< 20 s)")
    parser.add_argument("--ticks", type=int, default=None, help="ticks per case")
    parser.add_argument("--cases", nargs="*", default=None, help="frisbee consensus smd")
    parser.add_argument("--profile", metavar="CASE", help="cProfile one case instead")
    parser.add_argument("--no-zenoh", action="store_true", help="skip the Zenoh put baseline")
    parser.add_argument(
        "--idle-ms",
        type=float,
        default=DT * 1e3,
        help="also measure ticks that each follow this long idle [ms] (default: one period "
        "at 100 Hz, as a realtime agent; 0: skip)",
    )
    parser.add_argument(
        "--idle-kind",
        choices=tuple(WAIT_WORDS),
        default="sleep",
        help="how the thread waits before each of those ticks: sleeping (default, as a realtime "
        "agent) or spinning in a busy loop (the CPU never idles)",
    )
    args = parser.parse_args(argv)
    if args.idle_ms < 0 or args.idle_ms > 1000:
        parser.error(f"--idle-ms {args.idle_ms}: expected 0..1000 ms")
    ticks = args.ticks or (3000 if args.short else 20000)
    idle_ticks = min(ticks, 100 if args.short else 500)  # each one costs the idle time
    repeats = 5 if args.short else 9
    chosen = [c for c in cases() if args.cases is None or c.name in args.cases]
    if args.profile:
        by_name = {c.name: c for c in cases()}
        if args.profile not in by_name:
            parser.error(f"--profile: unknown case {args.profile!r} ({', '.join(by_name)})")
        profile(by_name[args.profile], ticks)
        return 0

    matvec = numpy_baseline(repeats)
    put = None if args.no_zenoh else zenoh_baseline(2000 if args.short else 20000)
    print(
        f"python {platform.python_version()} ({os.path.realpath(sys.executable)}), "
        f"numpy {np.__version__}"
    )
    print(f"baselines: numpy K @ y (2x4) {matvec * 1e6:.2f} us CPU", end="")
    if put:
        print(
            f"; Zenoh put client -> loopback router {put[0] * 1e6:.1f} us CPU "
            f"({put[1] * 1e6:.1f} us wall)"
        )
        put_cpu = put[0]
    else:
        print()
        put_cpu = None
    waited, column = WAIT_WORDS[args.idle_kind]
    if args.idle_ms:
        steps = steps_after_idle(args.idle_ms / 1e3, idle_ticks, args.idle_kind)
        print(
            f"after {args.idle_ms:g} ms {waited}: six small numpy steps "
            f"{steps['numpy'][0] * 1e6:.1f} -> {steps['numpy'][1] * 1e6:.1f} us CPU; the same in "
            f"plain Python {steps['python'][0] * 1e6:.1f} -> {steps['python'][1] * 1e6:.1f} us"
        )
    idle_head = f" {column:>11} {'x hot':>6}" if args.idle_ms else ""
    idle_note = f"; {idle_ticks} ticks after {args.idle_ms:g} ms {waited} each)"
    print(
        f"{'case':<11} {'CPU/tick':>11} {'x matvec':>9} {'x put':>7}{idle_head}"
        f"   ({ticks} ticks, dt {DT} s" + (idle_note if args.idle_ms else ")")
    )
    for case in chosen:
        run = tick_loop(case)
        per_tick = measure(run, ticks, repeats)
        ratio_put = f"{per_tick / put_cpu:7.1f}" if put_cpu else "      -"
        idle = ""
        if args.idle_ms:
            cold = run(idle_ticks, args.idle_ms / 1e3, args.idle_kind)
            idle = f" {cold * 1e6:8.1f} us {cold / per_tick:6.1f}"
        print(
            f"{case.name:<11} {per_tick * 1e6:8.1f} us {per_tick / matvec:9.0f} {ratio_put}"
            f"{idle}   {case.title}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

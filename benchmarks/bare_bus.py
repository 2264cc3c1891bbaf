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

Realtime: tick k is sent at ``T0 + k dt``; a tick is late when some answer is not in when the
next one is due (as in the runtime). Lockstep: tick k+1 is sent from the callback of the last
answer of tick k (one round trip per tick, a barrier: the slowest form of lockstep).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import zenoh
from hilswarm.agents import bus

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


def client(index: int, n: int, endpoint: str) -> None:
    """One client process: answer every tick from the tick callback."""
    keys = bus.BusKeys("bare")
    session = bus.open_session(bus.client_config([endpoint]))
    name = f"r{index}"
    publisher = session.declare_publisher(keys.y(name), **bus.TICK_PATH_QOS)
    received = [0]

    def on_neighbour(sample: zenoh.Sample) -> None:
        bus.decode_vector(sample.payload.to_bytes())
        received[0] += 1

    def on_tick(sample: zenoh.Sample) -> None:
        tick = bus.decode_tick(sample.payload.to_bytes())
        publisher.put(bus.encode_vector(tick.k, tick.t, _Y_VALUES), attachment=_REPORT)

    entities = [
        session.declare_subscriber(
            keys.y(f"r{(index + step) % n}"),
            zenoh.handlers.Callback(on_neighbour, indirect=False),
        )
        for step in ((1, n - 1) if n > 2 else (1,) if n == 2 else ())
    ]
    entities.append(
        session.declare_subscriber(keys.tick, zenoh.handlers.Callback(on_tick, indirect=False))
    )
    entities.append(session.liveliness().declare_token(keys.alive(name)))
    sys.stdin.read()  # the parent closes stdin to stop us
    entities.clear()
    session.close()


def run_bare(*, n: int, rate_hz: float, seconds: float, lockstep: bool, port: int) -> BareResult:
    """Start the router and ``n`` client processes, tick, and return the figures."""
    keys = bus.BusKeys("bare")
    endpoint = bus.loopback_endpoint(port)
    session = bus.open_session(bus.listen_config([endpoint]))
    lock = threading.Lock()
    state = {"k": -1, "count": 0, "scheduled": 0.0}
    completion: list[float] = []
    done = threading.Event()
    n_ticks = max(1, round(seconds * rate_hz))
    tick_pub = session.declare_publisher(keys.tick, **bus.TICK_PATH_QOS)

    def send(k: int, scheduled: float) -> None:
        state["k"], state["count"], state["scheduled"] = k, 0, scheduled
        tick_pub.put(bus.encode_tick(bus.TickMessage(k, k / rate_hz)))

    def on_y(sample: zenoh.Sample) -> None:
        k = int.from_bytes(sample.payload.to_bytes()[:8], "little", signed=True)
        with lock:
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
        session.declare_subscriber(keys.all_outputs, zenoh.handlers.Callback(on_y, indirect=False)),
        session.liveliness().declare_subscriber(
            keys.all_alive, zenoh.handlers.Callback(on_alive, indirect=False), history=True
        ),
    ]
    command = [sys.executable, os.path.abspath(__file__), "--client"]
    clients = [
        subprocess.Popen([*command, str(i), str(n), endpoint], stdin=subprocess.PIPE)
        for i in range(n)
    ]
    late = 0
    try:
        if not all_alive.wait(120):
            raise RuntimeError(f"only {len(alive)} of {n} bare clients came up")
        time.sleep(0.5)  # let every subscription reach the router
        start = time.perf_counter()
        if lockstep:
            with lock:
                send(0, start)
            done.wait(max(60.0, 20 * seconds))
        else:
            period = 1.0 / rate_hz
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
    with lock:
        times = np.array(completion)
    return BareResult(
        n, rate_hz, "lockstep" if lockstep else "realtime", n_ticks, late, times, wall
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--client", nargs=3, metavar=("INDEX", "N", "ENDPOINT"), help=argparse.SUPPRESS
    )
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--rate", type=float, default=100.0, help="tick rate [Hz]")
    parser.add_argument("--seconds", type=float, default=5.0, help="realtime run length [s]")
    parser.add_argument("--lockstep", action="store_true", help="round trips as fast as possible")
    parser.add_argument("--port", type=int, default=17650)
    parser.add_argument("--short", action="store_true", help="CI-sized: 8 clients, 50 Hz, 2 s")
    args = parser.parse_args(argv)
    if args.client:
        client(int(args.client[0]), int(args.client[1]), args.client[2])
        return 0
    if args.short:
        args.agents, args.rate, args.seconds = 8, 50.0, 2.0
    result = run_bare(
        n=args.agents, rate_hz=args.rate, seconds=args.seconds, lockstep=args.lockstep,
        port=args.port,
    )  # fmt: skip
    p50, p99 = result.percentiles_ms()
    if args.lockstep:
        print(f"bare bus, lockstep barrier, {result.n} clients at {result.rate_hz:g} Hz: "
              f"{result.speed:.1f}x real time (round trip p50 {p50:.2f} ms)")  # fmt: skip
    else:
        late = 100 * result.late_fraction
        print(f"bare bus, realtime, {result.n} clients at {result.rate_hz:g} Hz: "
              f"p50 {p50:.2f} ms, p99 {p99:.2f} ms, late {late:.2f} %")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Agent hop benchmark: what running ticks on the agent's worker thread costs per tick.

An agent's bus callbacks only decode a tick message and hand it to the tick engine; the worker
thread runs the tick (controller, board exchange, sense) and publishes ``y``. Before, the tick
ran inside the bus callback. This benchmark runs the same agent both ways, in one process,
paired batch by batch (so machine load hits both alike):

* ``callback`` — the calling thread (standing for Zenoh's callback thread) decodes the tick,
  takes it from the engine and runs it itself: the old path;
* ``worker``   — the calling thread decodes the tick and hands it to the engine; the agent's
  worker thread runs it: the new path (one thread hop per tick).

Either way the calling thread waits for ``y`` before sending the next tick (lockstep, window
1), so the figure is the round trip per tick. ``y`` goes to an in-process sink instead of a
Zenoh publisher (a Zenoh put costs the same on either thread; ``benchmarks/agent_tick.py``
measures it). Reported: wall time and process CPU time per tick, median of the batches, and
the worker/callback ratio of each.

    python benchmarks/agent_hop.py            # 20000 ticks per path
    python benchmarks/agent_hop.py --short    # CI-sized (a few seconds)
"""

from __future__ import annotations

import argparse
import os
import queue
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

from hilswarm.agents import bus
from hilswarm.agents.agent import Agent

sys.path.insert(0, str(Path(__file__).resolve().parent))
from agent_tick import DT, cases, offline_agent


class _Sink:
    """Stands for the y publisher: hands each y payload back to the calling thread."""

    def __init__(self) -> None:
        self.done: queue.SimpleQueue[bytes] = queue.SimpleQueue()

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self.done.put(payload)


def prepared(case_name: str) -> tuple[Agent, _Sink]:
    """An offline agent of ``case_name`` whose y goes to a sink."""
    case = {c.name: c for c in cases()}[case_name]
    agent = offline_agent(case.config)
    sink = _Sink()
    agent._y_pub = sink
    agent.engine.running = True
    return agent, sink


def messages(agent: Agent, k0: int, n: int) -> list[tuple[list[tuple[str, bytes]], bytes]]:
    """Per tick: the neighbours' y_{k-1} (they arrive first) and the tick message."""
    neighbours = agent.config.neighbours
    values = [0.1 * (i + 1) for i in range(int(agent.hardware.vehicle.n_outputs))]
    return [
        (
            [(name, bus.encode_vector(k - 1, (k - 1) * DT, values)) for name in neighbours]
            if k > 0
            else [],
            bus.encode_tick(bus.TickMessage(k, k * DT)),
        )
        for k in range(k0, k0 + n)
    ]


def timed(
    inputs: list[tuple[list[tuple[str, bytes]], bytes]],
    neighbour: Callable[[str, bytes], None],
    tick: Callable[[bytes], None],
    done: Callable[[], bytes],
) -> tuple[float, float]:
    """Deliver ``inputs`` tick by tick, waiting for each y; returns (wall s, CPU s) per tick."""
    wall, cpu = time.perf_counter(), time.process_time()
    for outputs, payload in inputs:
        for name, y in outputs:
            neighbour(name, y)
        tick(payload)
        done()
    n = len(inputs)
    return (time.perf_counter() - wall) / n, (time.process_time() - cpu) / n


def run_callback(agent: Agent, sink: _Sink, k0: int, n: int) -> tuple[float, float]:
    """``n`` ticks run on the calling thread (the old path: the tick in the callback)."""
    engine, lock = agent.engine, agent._engine_lock

    def neighbour(name: str, y: bytes) -> None:
        k, _t, values = bus.decode_vector(y)
        with lock:
            engine.on_neighbour(name, k, values)

    def tick(payload: bytes) -> None:
        message = bus.decode_tick(payload)
        with lock:
            engine.on_tick(message.k, message.t, message.missing, message.realtime, 0.0)
            ready = engine.take(gather=True)
        agent._run_tick(ready)

    return timed(messages(agent, k0, n), neighbour, tick, sink.done.get)


def run_worker(agent: Agent, sink: _Sink, k0: int, n: int) -> tuple[float, float]:
    """``n`` ticks handed to the agent's worker thread (the new path)."""
    receive = agent.receive_tick
    return timed(
        messages(agent, k0, n),
        agent.receive_neighbour,
        lambda payload: receive(payload, arrived=0.0),
        sink.done.get,
    )


def main(argv: list[str] | None = None) -> int:
    """Command line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--short", action="store_true", help="CI-sized run")
    parser.add_argument("--ticks", type=int, default=None, help="ticks per path")
    parser.add_argument("--case", default="smd", help="agent case of agent_tick.py")
    args = parser.parse_args(argv)
    ticks = args.ticks or (2000 if args.short else 20000)
    batches = 5 if args.short else 10
    batch = max(1, ticks // batches)
    old, old_sink = prepared(args.case)
    new, new_sink = prepared(args.case)
    new._start_worker()
    k = 0
    figures: dict[str, list[tuple[float, float]]] = {"callback": [], "worker": []}
    try:
        run_callback(old, old_sink, k, 200)  # warm-up
        run_worker(new, new_sink, k, 200)
        k = 200
        for _ in range(batches):  # paired: each batch runs both paths back to back
            figures["callback"].append(run_callback(old, old_sink, k, batch))
            figures["worker"].append(run_worker(new, new_sink, k, batch))
            k += batch
    finally:
        new._stop_worker()
    med = {
        path: (statistics.median(w for w, _ in f), statistics.median(c for _, c in f))
        for path, f in figures.items()
    }
    load = os.getloadavg()
    print(f"agent hop, case {args.case}, {batches} x {batch} ticks per path, load {load[0]:.2f}")
    for path, (wall, cpu) in med.items():
        print(f"  {path:8s} {wall * 1e6:8.1f} us wall/tick  {cpu * 1e6:8.1f} us CPU/tick")
    (old_wall, old_cpu), (new_wall, new_cpu) = med["callback"], med["worker"]
    print(
        f"  worker/callback: wall x{new_wall / old_wall:.2f} "
        f"({(new_wall - old_wall) * 1e6:+.1f} us), CPU x{new_cpu / old_cpu:.2f} "
        f"({(new_cpu - old_cpu) * 1e6:+.1f} us)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

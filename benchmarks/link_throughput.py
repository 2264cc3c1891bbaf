"""Link throughput: ticks per second of a thesis Blimpduino-like tick over each transport.

The tick writes 6 digital outputs, 2 PWM duties and 1 servo pulse and reads 1 analog input, in
one checked round trip (docs/protocol.md). Transports measured:

* ``simavr paced``   — the real firmware in simavr, simulated time paced to the wall clock, UART
  at 115200 baud: what a real Uno on a USB serial link does. Compared with the wire-time bound
  ``baud / 10 / (request + reply bytes)``; target >= 90 %.
* ``simavr unpaced`` — the same, simulated time as fast as the host allows (functional tests).
* ``pty+SimBoard`` / ``socket+SimBoard`` — SerialBoard -> WireServer -> SimBoard (no UART time).

Each simavr line is followed by the CPU use of the harness process and of this (host) process
[% of one core] over the run (a paced harness must not starve the host on a 2-core machine).

The paced figure depends on the machine's load (the host and the harness must both be scheduled
within microseconds every tick): the load average is printed first, ``--repeat N`` measures the
paced transport N times and prints the spread, and the last line splits the best paced tick into
its wire time and the rest (firmware turnaround, host turnaround, scheduling), against the
budget the 90 % target leaves.

    python benchmarks/link_throughput.py [--short] [--seconds S] [--repeat N]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

from hilswarm.agents.errors import SimulatorError
from hilswarm.agents.link.board import PinConfig, PinMode
from hilswarm.agents.link.serial_board import SerialBoard
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.link.simavr import SimavrBoard
from hilswarm.agents.link.wire_server import PtyWireServer, SocketWireServer

BAUD = 115200
BITS_PER_BYTE = 10  # 8N1
#: Request + reply bytes of the Blimpduino-like tick (19 + 13, docs/protocol.md).
PER_TICK_BYTES = 32
DOUT = (2, 4, 7, 8, 12, 13)
CONFIG = [
    *(PinConfig(p, PinMode.DIGITAL_OUT) for p in DOUT),
    PinConfig(5, PinMode.PWM),
    PinConfig(6, PinMode.PWM),
    PinConfig(9, PinMode.SERVO, 1500),
    PinConfig(14, PinMode.ANALOG_IN),
]
READS = [14]


def tick_writes(k: int) -> dict[int, int]:
    """Writes of tick ``k``: every value changes from tick to tick."""
    writes = {pin: (k + i) % 2 for i, pin in enumerate(DOUT)}
    writes |= {5: (k * 7) % 254 + 1, 6: (k * 13) % 254 + 1, 9: 1000 + (k * 11) % 1000}
    return writes


def run(
    serial_board: SerialBoard,
    exchange: Callable[[dict[int, int], list[int]], object],
    seconds: float,
) -> tuple[float, float, float]:
    """Tick for ``seconds``; return (ticks/s, request bytes/tick, reply bytes/tick)."""
    for k in range(20):  # warm up
        exchange(tick_writes(k), READS)
    sent0, received0 = serial_board.stats.bytes_sent, serial_board.stats.bytes_received
    ticks = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        exchange(tick_writes(ticks), READS)
        ticks += 1
    elapsed = time.perf_counter() - start
    sent = (serial_board.stats.bytes_sent - sent0) / ticks
    received = (serial_board.stats.bytes_received - received0) / ticks
    return ticks / elapsed, sent, received


def report(name: str, rate: float, sent: float, received: float, *, bound: bool) -> float:
    """Print one line; return the fraction of the wire-time bound."""
    per_tick = sent + received
    wire_bound = BAUD / BITS_PER_BYTE / per_tick
    fraction = rate / wire_bound
    note = (
        f"{100 * fraction:5.1f} % of the {wire_bound:.0f} ticks/s wire bound"
        if bound
        else "(no UART timing)"
    )
    print(
        f"{name:<16} {rate:8.0f} ticks/s  {sent:4.1f} B out + {received:4.1f} B in "
        f"= {per_tick:4.1f} B/tick  {note}"
    )
    return fraction


def cpu_seconds(pid: int) -> float:
    """CPU time [s] (user + system) process ``pid`` has used so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def bench_simavr(paced: bool, seconds: float) -> float | None:
    """Measure the real firmware in simavr; None if it is not built."""
    try:
        board = SimavrBoard("uno", paced=paced, url=f"simavr://uno?paced={int(paced)}")
    except SimulatorError as exc:
        print(f"simavr {'paced' if paced else 'unpaced'}: skipped: {exc}")
        return None
    with board:
        board.configure(CONFIG, watchdog_s=0.5)
        board.set_analog_input(14, 2.5)
        serial_board = board.serial
        if serial_board is None:
            raise SimulatorError("simavr board has no serial link after open()")
        process = board.harness.process
        if process is None:
            raise SimulatorError("simavr board has no harness process after open()")
        harness0, host0, wall0 = cpu_seconds(process.pid), time.process_time(), time.monotonic()
        rate, sent, received = run(serial_board, board.exchange, seconds)
        wall = time.monotonic() - wall0
        harness_cpu = (cpu_seconds(process.pid) - harness0) / wall
        host_cpu = (time.process_time() - host0) / wall
    fraction = report(
        f"simavr {'paced' if paced else 'unpaced'}", rate, sent, received, bound=paced
    )
    print(
        f"{'':<16} CPU: harness {100 * harness_cpu:3.0f} %, host (this process) "
        f"{100 * host_cpu:3.0f} % of one core"
    )
    return fraction


def bench_loopback(kind: str, seconds: float) -> None:
    """Measure SerialBoard -> WireServer -> SimBoard over a pty or a loopback socket."""
    sim = SimBoard("uno", dt=0.01)
    sim.set_analog_input(14, 2.5)
    server: AbstractContextManager[PtyWireServer | SocketWireServer] = (
        PtyWireServer(sim) if kind == "pty" else SocketWireServer(sim)
    )
    with server as running, SerialBoard(running.url) as board:
        board.configure(CONFIG, watchdog_s=0)
        rate, sent, received = run(board, board.exchange, seconds)
    report(f"{kind}+SimBoard", rate, sent, received, bound=False)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the figures (speed never fails the run: noisy machines)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--short", action="store_true", help="a few seconds per transport")
    parser.add_argument("--seconds", type=float, default=None, help="seconds per transport")
    parser.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="measure the paced simavr transport this many times (spread)",
    )
    args = parser.parse_args(argv)
    seconds = args.seconds if args.seconds is not None else (3.0 if args.short else 15.0)
    print(
        f"Blimpduino-like tick (6 digital out, 2 PWM, 1 servo, 1 analog in), {seconds:.0f} s "
        f"per transport, {BAUD} baud 8N1"
    )
    print(
        "load average (1, 5, 15 min): {:.2f} {:.2f} {:.2f} on {} CPUs".format(
            *os.getloadavg(), os.cpu_count()
        )
    )
    fractions = [
        f
        for f in (bench_simavr(paced=True, seconds=seconds) for _ in range(max(1, args.repeat)))
        if f is not None
    ]
    bench_simavr(paced=False, seconds=seconds)
    bench_loopback("pty", seconds)
    bench_loopback("socket", seconds)
    if fractions:
        if len(fractions) > 1:
            print(
                f"paced simavr over {len(fractions)} runs: min {100 * min(fractions):.1f} %, "
                f"median {100 * statistics.median(fractions):.1f} %, max "
                f"{100 * max(fractions):.1f} % of the wire bound"
            )
        fraction = max(fractions)
        wire_us = PER_TICK_BYTES * BITS_PER_BYTE / BAUD * 1e6
        tick_us = wire_us / fraction
        budget_us = wire_us / 0.9 - wire_us
        print(
            f"best paced tick: {tick_us:.0f} us = wire {wire_us:.0f} us + the rest "
            f"{tick_us - wire_us:.0f} us (the 90 % target leaves {budget_us:.0f} us for "
            "firmware, host and scheduling)"
        )
        verdict = "meets" if fraction >= 0.9 else "MISSES"
        best = f" (best of {len(fractions)} runs)" if len(fractions) > 1 else ""
        print(
            f"paced simavr: {100 * fraction:.1f} % of the wire bound{best}, {verdict} the "
            ">= 90 % target"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""E-stop latency with an exchange blocked on a stalled board: the real firmware in simavr.

The board is the hilswarm firmware in the AVR simulator (``simavr://uno``, paced: real UART
timing). Each trial drives two PWM pins and a digital output, makes the board stop answering
(the harness' ``mute 1``: the firmware still receives and executes every request, its replies
are lost), starts an exchange on another thread (it hangs, re-sending, for
(retries + 1) x timeout), then e-stops and reads the pins back from the simulator until every
output is at its safe value:

* ``own path`` — ``Board.request_estop()`` from the e-stop thread while the exchange hangs
  (what the agent does now);
* ``behind the exchange`` — the old path: the e-stop waits until the hanging exchange gives
  up, then ``Board.estop()``.

Reported per path: the time from the e-stop to safe pins [ms], as seen by polling the
simulator's pin state (wall clock, an upper bound), and in simulated time (the firmware's own
clock at the first safe readout minus at the e-stop). The target (issue 10) is <= 20 ms and
<= 1 tick: the last line is the verdict on the own path's worst trial (the larger of its wall
and simulated latency) against both bounds, ``MET`` or ``MISSED``, with the figures and the
1-minute load average (a loaded machine slows the paced simulator and the polling).

    python benchmarks/estop_latency.py              # 20 trials per path
    python benchmarks/estop_latency.py --short      # CI-sized (3 trials per path)
    python benchmarks/estop_latency.py --rate-hz 50 # the tick bound of a 50 Hz experiment
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import threading
import time

from hilswarm.agents.errors import BoardError, SimulatorError
from hilswarm.agents.link.board import PinConfig, PinMode
from hilswarm.agents.link.simavr import SimavrBoard

PINS = [
    PinConfig(5, PinMode.PWM, 0),
    PinConfig(6, PinMode.PWM, 0),
    PinConfig(13, PinMode.DIGITAL_OUT, 0),
]
DRIVE = {5: 200, 6: 120, 13: 1}
#: The target: e-stop to safe outputs within this [s] ...
TARGET_S = 0.020
#: ... and within one tick at this rate [Hz] (the example experiments' rate) unless given.
DEFAULT_RATE_HZ = 20.0


def safe_now(board: SimavrBoard) -> tuple[bool, int]:
    """(every output at its safe value, simulated time [us]) from one state readout."""
    state = board.harness.state()
    outputs = board.read_outputs_from(state)
    return all(outputs.get(p.pin) == 0 for p in PINS), int(state["t_us"])


def trial(board: SimavrBoard, own_path: bool) -> tuple[float, float]:
    """One e-stop; returns (wall latency [s], simulated latency [s])."""
    board.configure(PINS, watchdog_s=0)  # clears the previous e-stop
    board.exchange(DRIVE, [])
    board.harness.command("mute 1")
    serial = board.serial
    retries = serial.stats.retries

    def hang() -> None:
        with contextlib.suppress(BoardError):  # it times out: that is the point
            board.exchange(DRIVE, [])

    worker = threading.Thread(target=hang)
    worker.start()
    deadline = time.monotonic() + 10
    while serial.stats.retries == retries and time.monotonic() < deadline:
        time.sleep(0.001)  # until the exchange is re-sending: it hangs
    _, t0_us = safe_now(board)
    start = time.perf_counter()
    if own_path:
        board.request_estop()
    else:
        worker.join()  # the old path: behind the hanging exchange
        board.harness.command("mute 0")
        board.estop()
    while True:
        done, t_us = safe_now(board)
        if done:
            break
    wall = time.perf_counter() - start
    board.harness.command("mute 0")
    worker.join()
    return wall, (t_us - t0_us) / 1e6


def verdict(figures: list[tuple[float, float]], rate_hz: float, load: float) -> str:
    """The verdict line on the own path's trials ``(wall [s], simulated [s])``: ``MET`` when
    the worst of them is within :data:`TARGET_S` and one tick at ``rate_hz`` [Hz]."""
    worst_s = max(max(wall, sim) for wall, sim in figures)
    tick_s = 1.0 / rate_hz
    met = worst_s <= TARGET_S and worst_s <= tick_s
    wall_ms = [wall * 1e3 for wall, _ in figures]
    return (
        f"verdict: {'MET' if met else 'MISSED'}: e-stop to safe outputs, exchange blocked, "
        f"worst {worst_s * 1e3:.2f} ms (wall median {statistics.median(wall_ms):.2f} ms, "
        f"max {max(wall_ms):.2f} ms; {len(figures)} trials) against <= {TARGET_S * 1e3:.0f} ms "
        f"and <= 1 tick ({tick_s * 1e3:.0f} ms at {rate_hz:g} Hz); load {load:.2f} (1 min)"
    )


def main(argv: list[str] | None = None) -> int:
    """Command line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--short", action="store_true", help="CI-sized run")
    parser.add_argument("--trials", type=int, default=None, help="trials per path")
    parser.add_argument(
        "--rate-hz",
        type=float,
        default=DEFAULT_RATE_HZ,
        help="tick rate of the 1-tick bound of the verdict [Hz]",
    )
    args = parser.parse_args(argv)
    if args.rate_hz <= 0:
        parser.error("--rate-hz must be positive")
    trials = args.trials or (3 if args.short else 20)
    try:
        board = SimavrBoard("uno", paced=True, timeout_s=0.1, retries=2)
        board.open()
    except SimulatorError as exc:
        print(f"no simulator: {exc}", file=sys.stderr)
        return 2
    results: dict[str, list[tuple[float, float]]] = {"own path": [], "behind the exchange": []}
    try:
        for _ in range(trials):  # paired: both paths per round
            results["own path"].append(trial(board, own_path=True))
            results["behind the exchange"].append(trial(board, own_path=False))
    finally:
        board.close()
    load = os.getloadavg()[0]
    print(f"e-stop latency, simavr uno paced, exchange hanging (3 x 0.1 s), load {load:.2f}")
    for path, figures in results.items():
        wall = [w * 1e3 for w, _ in figures]
        sim = [s * 1e3 for _, s in figures]
        print(
            f"  {path:20s} wall median {statistics.median(wall):7.2f} ms, max {max(wall):7.2f} ms;"
            f" simulated median {statistics.median(sim):7.2f} ms, max {max(sim):7.2f} ms"
        )
    print(verdict(results["own path"], args.rate_hz, load))
    return 0


if __name__ == "__main__":
    sys.exit(main())

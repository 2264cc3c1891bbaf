"""Work budget: how much CPU work per tick an agent may do and keep the lockstep target.

The lockstep target asks the runtime for at least 75 % of the bare bus's speed (8 agents at
100 Hz; docs/running.md, "Performance"). The bare bus does no work at all, and every agent
tick does some: the vehicle's, the controller's and the runtime's own. This benchmark measures
how much a tick may hold. It runs the bare bus in the runtime's lockstep pattern (window 8,
``benchmarks/bare_bus.py``) with each client burning a known CPU time before each answer
(``bare_bus.py --spin-us``: a tight loop on ``time.thread_time``, hot, touching no data) for a
sweep of times, every round framed by two runs with none, and prints each level's speed as a
share of the bare bus's in its round. The largest work that keeps the share (interpolated
between the levels, median over the rounds) is the *budget*: all an agent's tick may cost
above a bare client, vehicle, controller and runtime together. It is generous: the spin is
hot, and real work of the same CPU time also finds caches cold and evicts the other
processes' (docs/agent_tick.md), so it leaves less.

Beside it, in the same run, the Frisbee fleet's own tick work (``benchmarks/agent_tick.py``'s
case: ``Agent.tick_work`` with its neighbours' messages, hot, in this process, CPU time per
tick): what that fleet needs per tick at the very least, before any runtime; and the other
two cases' (the integrator fleet's consensus, the spring-mass-damper).

    python benchmarks/work_budget.py             # 0-80 µs, 2 rounds, 20 s of experiment each
    python benchmarks/work_budget.py --short     # CI-sized: one round, 20 and 60 µs (< 40 s)
    python benchmarks/work_budget.py --spins 0 20 40 --rounds 3 --settle-load 0.9

Every run prints one JSON line, and the end one summary line; the keys are stable
(docs/running.md, "Benchmark JSON lines"):

    {"kind": "work_budget", "round", "spin_us", "speed", "share", "client_cpu_ms",
     "cpu_busy", "load_1min"}
    {"kind": "work_budget_summary", "fraction", "budget_us", "frisbee_hot_us",
     "bare_speed", "load_1min", "cases_hot_us"}

``share`` is the run's speed over the mean speed of its round's runs with no spin (about 1
for those); ``budget_us`` is the largest spin measured when every level keeps the fraction (a
lower bound then: the closing line says so); ``frisbee_hot_us`` the Frisbee's tick work [µs
of CPU per tick, hot], measured first, and ``load_1min`` the load then; ``bare_speed`` the
median speed with no spin (x real time); ``cases_hot_us`` every ``agent_tick.py`` case's hot
tick work by name (``frisbee``, ``consensus``: the integrator fleet, ``smd``) [µs].
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from dataclasses import dataclass

from bare_bus import BareResult, run_bare
from hilswarm.agents.agent_config import DEFAULT_LOCKSTEP_WINDOW as WINDOW
from swarm_ticks import LOCKSTEP_FRACTION, add_settle_option, settle


@dataclass(frozen=True)
class Level:
    """One bare-bus run with ``spin_us`` µs of work per client tick."""

    round: int
    spin_us: float
    result: BareResult
    load_1min: float


def round_shares(runs: list[Level]) -> list[float]:
    """Each run's share of the bare bus's speed: its speed over the mean speed of the runs with
    no spin among ``runs`` (one round)."""
    zero = [level.result.speed for level in runs if level.spin_us == 0]
    if not zero:
        rounds = ", ".join(str(r) for r in sorted({level.round for level in runs}))
        raise ValueError(f"round {rounds} has no run without spin to compare with")
    base = statistics.fmean(zero)
    return [level.result.speed / base for level in runs]


def shares(levels: list[Level]) -> dict[float, float]:
    """Median share of the bare bus's speed at each spin [µs] over the rounds
    (:func:`round_shares` of each)."""
    by_spin: dict[float, list[float]] = {}
    for round_ in sorted({level.round for level in levels}):
        runs = [level for level in levels if level.round == round_]
        for level, share in zip(runs, round_shares(runs), strict=True):
            by_spin.setdefault(level.spin_us, []).append(share)
    return {spin: statistics.median(values) for spin, values in sorted(by_spin.items())}


def budget(share_at: dict[float, float], fraction: float) -> tuple[float, bool]:
    """The largest work per tick [µs] that keeps ``fraction`` of the bare bus's speed, from
    the median shares at each spin: linear between the last level that keeps it and the first
    that does not (from no work at share 1 when no level is given at 0). Returns ``(budget,
    bounded)``: ``bounded`` False when every level keeps the fraction (the budget is then the
    largest level, a lower bound)."""
    points = sorted(share_at.items())
    if not points or points[0][0] != 0:
        points.insert(0, (0.0, 1.0))
    last_kept = points[0]
    for spin, share in points[1:]:
        if share < fraction:
            spin0, share0 = last_kept
            if share0 <= share:  # not falling: no line to cut
                return spin0, True
            return spin0 + (spin - spin0) * (share0 - fraction) / (share0 - share), True
        last_kept = (spin, share)
    return last_kept[0], False


def hot_ticks_us(ticks: int) -> dict[str, float]:
    """Each ``agent_tick.py`` case's own tick work, hot, in this process [µs of CPU per tick]
    (its neighbours' messages received, ``Agent.tick_work``): ``frisbee`` (the target's
    fleet), ``consensus`` (the integrator fleet) and ``smd`` (the lightest: no neighbours)."""
    from agent_tick import cases, measure, tick_loop  # noqa: PLC0415 - an agent's imports

    return {case.name: measure(tick_loop(case), ticks, 5) * 1e6 for case in cases()}


def level_json(level: Level, share: float) -> str:
    """The JSON line of one run (keys stable: docs/running.md)."""
    result = level.result
    return json.dumps({
        "kind": "work_budget",
        "round": level.round,
        "spin_us": level.spin_us,
        "speed": round(result.speed, 3),
        "share": round(share, 4),
        "client_cpu_ms": round(result.client_cpu_s * 1e3, 4),
        "cpu_busy": round(result.cpu_busy, 3),
        "load_1min": round(level.load_1min, 2),
    })  # fmt: skip


def summary_lines(
    levels: list[Level], fraction: float, hot_us: dict[str, float], load: float
) -> tuple[list[str], str]:
    """The closing lines and the summary JSON line of a sweep; ``hot_us``: each case's hot
    tick work [µs] (:func:`hot_ticks_us`); ``load``: the 1-minute load when it was measured."""
    share_at = shares(levels)
    value, bounded = budget(share_at, fraction)
    bare_speed = statistics.median(lvl.result.speed for lvl in levels if lvl.spin_us == 0)
    lines = [
        f"spin {spin:g} µs: {100 * share:.0f} % of the bare bus's speed (median over rounds)"
        for spin, share in share_at.items()
    ]
    percent = f"{100 * fraction:.0f} %"
    frisbee = hot_us["frisbee"]
    lightest = min(hot_us, key=hot_us.__getitem__)
    if not bounded:
        lines.append(f"budget: at least {value:g} µs (every level kept {percent}; "
                     "measure larger spins)")  # fmt: skip
    else:
        verdict = (
            "the Frisbee fleet's own tick work alone is over it, before any runtime cost"
            if frisbee > value
            else "the Frisbee fleet's own tick work is within it"
        )
        lines.append(
            f"budget: a client keeps {percent} of the bare bus's lockstep speed "
            f"({bare_speed:.1f}x) with at most {value:.0f} µs of hot CPU work per tick; a "
            f"Frisbee agent's tick work costs {frisbee:.0f} µs hot in this process: {verdict}; "
            f"the lightest case ({lightest}) {hot_us[lightest]:.0f} µs (load {load:.2f})"
        )
    summary = json.dumps({
        "kind": "work_budget_summary",
        "fraction": fraction,
        "budget_us": round(value, 1),
        "frisbee_hot_us": round(frisbee, 1),
        "bare_speed": round(bare_speed, 3),
        "load_1min": round(load, 2),
        "cases_hot_us": {name: round(us, 1) for name, us in hot_us.items()},
    })  # fmt: skip
    return lines, summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--short", action="store_true", help="CI-sized (< 40 s)")
    parser.add_argument(
        "--spins", type=float, nargs="+", metavar="US",
        help="work per client tick [µs of CPU] to measure (default 0 10 20 40 60 80); a run "
        "with none frames every round anyway",
    )  # fmt: skip
    parser.add_argument("--rounds", type=int, default=2, help="rounds over the levels")
    parser.add_argument(
        "--seconds", type=float, default=20.0, help="lockstep experiment per run [s]"
    )
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--rate", type=float, default=100.0, help="tick rate [Hz]")
    parser.add_argument(
        "--fraction", type=float, default=LOCKSTEP_FRACTION,
        help="share of the bare bus's speed to keep (the target's: 0.75)",
    )  # fmt: skip
    add_settle_option(parser)
    args = parser.parse_args(argv)
    spins = args.spins or ([20.0, 60.0] if args.short else [10.0, 20.0, 40.0, 60.0, 80.0])
    rounds, seconds = (1, 5.0) if args.short else (args.rounds, args.seconds)
    if any(not spin >= 0 for spin in spins):
        parser.error("--spins: expected CPU times >= 0 [µs]")
    if rounds < 1 or not seconds > 0 or args.agents < 2 or not 0 < args.fraction < 1:
        parser.error("--rounds >= 1, --seconds > 0, --agents >= 2 and 0 < --fraction < 1")
    levels: list[Level] = []
    print(
        f"bare bus, lockstep window {WINDOW}, {args.agents} clients at {args.rate:g} Hz, "
        f"{seconds:g} s of experiment per run; each client burns the given CPU time per tick",
        flush=True,
    )
    settle(args.settle_load)
    hot_load = os.getloadavg()[0]
    hot_us = hot_ticks_us(500 if args.short else 5000)  # first: the machine at its quietest
    ticks = ", ".join(f"{name} {us:.1f}" for name, us in hot_us.items())
    print(f"each case's tick work, hot in this process [µs of CPU per tick]: {ticks} "
          f"(load {hot_load:.2f})", flush=True)  # fmt: skip
    for round_ in range(rounds):
        order = [0.0, *(spin for spin in spins if spin != 0), 0.0]
        for spin in order:
            settle(args.settle_load)
            load = os.getloadavg()[0]
            result = run_bare(n=args.agents, rate_hz=args.rate, seconds=seconds, lockstep=True,
                              window=WINDOW, spin_us=spin)  # fmt: skip
            levels.append(Level(round_, spin, result, load))
            print(
                f"round {round_}: spin {spin:5g} µs  {result.speed:6.1f}x  client "
                f"{result.client_cpu_s * 1e3:.3f} ms of CPU per tick  "
                f"{100 * result.cpu_busy:.0f} % busy  load {load:.2f}",
                flush=True,
            )
        run = levels[-len(order) :]
        for level, share in zip(run, round_shares(run), strict=True):
            print(level_json(level, share), flush=True)
    lines, summary = summary_lines(levels, args.fraction, hot_us, hot_load)
    for line in lines:
        print(line)
    print(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())

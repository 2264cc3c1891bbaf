"""Swarm tick benchmark: how many agents the runtime keeps on schedule on this machine.

Realtime mode with simulated boards (Frisbee bots on ``sim://`` boards driving to a waypoint,
outputs exchanged along a ring graph), N agents at a given rate: p50/p99 tick completion time
(from the tick's scheduled time until the last y_k is in) and the fraction of late ticks.
Lockstep mode: speed as a multiple of real time.

    python benchmarks/swarm_ticks.py            # N = 8, 16, 32, 64 at 50/100/200 Hz + lockstep
    python benchmarks/swarm_ticks.py --short    # N = 8 at 50 Hz realtime + lockstep (< 60 s)
    python benchmarks/swarm_ticks.py --agents 32 --rates 100 --seconds 10

Every run records to a temporary MCAP file like a real run (``--no-record`` to leave it out).
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

from hilswarm.agents import bus
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.launcher import AgentLauncher, agent_config_for
from hilswarm.orchestrator.manager import InstanceManager, RunSummary
from hilswarm.orchestrator.recorder import Recorder


def ring_experiment(
    folder: Path, *, n: int, rate_hz: float, mode: str, seconds: float, vehicle: str
) -> Path:
    """An experiment file: ``n`` agents on a two-way ring."""
    names = [f"r{i}" for i in range(n)]
    rows = [
        [1 if n > 1 and j != i and (j - i) % n in (1, n - 1) else 0 for j in range(n)]
        for i in range(n)
    ]
    if vehicle == "frisbee":
        defaults = 'vehicle = "frisbee"\nlink = "sim://"\ncontroller = "waypoint"\n'
        agent = "initial_state = [{x}, 0.0, 0.0]\nparams = {{ waypoints = [[{x}, 1.0]] }}\n"
    else:
        defaults = (
            'vehicle = "simulated"\ncontroller = "consensus"\n'
            'vehicle_params = { plant = "integrator", plant_params = { n_dims = 2 } }\n'
            "params = { gain = 1.0 }\n"
        )
        agent = "initial_state = [{x}, 0.0]\n"
    text = (
        f'[experiment]\nname = "bench"\nrate_hz = {rate_hz}\nduration_s = {seconds}\n'
        f'mode = "{mode}"\non_agent_loss = "stop"\n\n[graph]\nagents = {names}\n'
        f"adjacency = {rows}\n\n[defaults]\n{defaults}\n"
    )
    for i, name in enumerate(names):
        text += f"[agents.{name}]\n" + agent.format(x=float(i)) + "\n"
    path = folder / f"bench-{n}-{rate_hz:g}-{mode}.toml"
    path.write_text(text, encoding="utf-8")
    return path


def run_once(
    *, n: int, rate_hz: float, mode: str, seconds: float, port: int, record: bool, vehicle: str
) -> tuple[RunSummary, float]:
    """Run one configuration; returns the summary and the manager's CPU per tick [s]."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        experiment = load_experiment(
            ring_experiment(
                folder, n=n, rate_hz=rate_hz, mode=mode, seconds=seconds, vehicle=vehicle
            )
        )
        endpoints = [bus.loopback_endpoint(port)]
        recorder = (
            Recorder(folder / "run.mcap", experiment, log_time_ns=time.time_ns())
            if record
            else None
        )
        manager = InstanceManager(experiment, recorder=recorder, listen=endpoints)
        try:
            manager.open()
            with AgentLauncher(endpoints) as launcher:
                launcher.start_all(
                    [agent_config_for(experiment, name) for name in experiment.agent_names]
                )
                manager.wait_for_agents(300, check=launcher.check)
                cpu0 = resource.getrusage(resource.RUSAGE_SELF)
                summary = manager.run()
                cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        finally:
            manager.close()
            if recorder is not None:
                recorder.close()
    cpu = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
    ticks = max(1, summary.ticks + summary.late_ticks)
    return summary, cpu / ticks


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--short", action="store_true", help="CI-sized run (< 60 s)")
    parser.add_argument("--agents", type=int, nargs="*", default=[8, 16, 32, 64])
    parser.add_argument("--rates", type=float, nargs="*", default=[50.0, 100.0, 200.0])
    parser.add_argument("--seconds", type=float, default=10.0, help="realtime run length [s]")
    parser.add_argument("--vehicle", choices=("frisbee", "simulated"), default="frisbee")
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument("--no-lockstep", action="store_true")
    parser.add_argument("--port", type=int, default=17700)
    args = parser.parse_args(argv)
    if args.short:
        args.agents, args.rates, args.seconds = [8], [50.0], 5.0
    record = not args.no_record
    print(
        f"vehicle {args.vehicle}, recording {'on' if record else 'off'}, "
        f"realtime runs of {args.seconds:g} s"
    )
    print(
        f"{'mode':9} {'N':>3} {'rate':>6} {'ticks':>6} {'p50 ms':>8} {'p99 ms':>8} "
        f"{'late %':>7} {'mgr cpu/tick ms':>16}"
    )
    port = args.port
    for n in args.agents:
        for rate in args.rates:
            summary, cpu = run_once(
                n=n,
                rate_hz=rate,
                mode="realtime",
                seconds=args.seconds,
                port=port,
                record=record,
                vehicle=args.vehicle,
            )
            port += 1
            total = summary.ticks + summary.late_ticks
            p50, p99 = summary.completion_percentiles()
            late = 100.0 * summary.late_ticks / max(1, total)
            print(
                f"{'realtime':9} {n:>3} {rate:>6g} {total:>6} {p50 * 1e3:>8.2f} {p99 * 1e3:>8.2f} "
                f"{late:>7.2f} {cpu * 1e3:>16.2f}",
                flush=True,
            )
    if not args.no_lockstep:
        seconds = 10.0 if args.short else 30.0
        summary, cpu = run_once(
            n=8,
            rate_hz=100.0,
            mode="lockstep",
            seconds=seconds,
            port=port,
            record=record,
            vehicle=args.vehicle,
        )
        p50, p99 = summary.completion_percentiles()
        print(
            f"{'lockstep':9} {8:>3} {100:>6g} {summary.ticks:>6} {p50 * 1e3:>8.2f} "
            f"{p99 * 1e3:>8.2f} {'-':>7} {cpu * 1e3:>16.2f}   speed {summary.speed:.1f}x real time"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

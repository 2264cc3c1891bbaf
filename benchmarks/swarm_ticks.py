"""Swarm tick benchmark: how many agents the runtime keeps on schedule on this machine.

Two fleets on a two-way ring graph: Frisbee bots on simulated ``sim://`` boards driving to a
waypoint, and simulated integrators running consensus. Realtime mode, N agents at a given
rate: p50/p99 tick completion time (from the tick's scheduled time until the last y_k is in)
and the fraction of late ticks. Lockstep mode: speed as a multiple of real time.

    python benchmarks/swarm_ticks.py            # both fleets, N = 8..64 at 50/100/200 Hz
    python benchmarks/swarm_ticks.py --short    # Frisbee fleet, N = 8 at 50 Hz (< 60 s)
    python benchmarks/swarm_ticks.py --agents 32 --rates 100 --vehicle simulated

Every run records to a temporary MCAP file through the recorder process, like ``hilswarm run``
(``--record inline``: inside the manager process, on its ticking thread; ``--record off``: not
at all). The last lines compare the figures with the issue's targets: met or missed, with the
numbers.

Each configuration is also run as a *bare bus* baseline (``benchmarks/bare_bus.py``, skip with
``--no-baseline``): the same router and one client process per agent answering every tick
from the bus callback, with no vehicle, controller or recording. It is measured in the same
process, right before the runtime, so a busy machine shows in both; the runtime cannot beat it.
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bare_bus import BareResult, run_bare
from hilswarm.agents import bus
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.launcher import AgentLauncher, agent_config_for
from hilswarm.orchestrator.manager import InstanceManager
from hilswarm.orchestrator.recorder import Recorder
from hilswarm.orchestrator.recorder_process import RecorderProcess
from hilswarm.orchestrator.run_security import RunSecurity
from hilswarm.orchestrator.run_summary import RunSummary


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


@dataclass
class Result:
    """One configuration's figures."""

    vehicle: str
    mode: str
    n: int
    rate_hz: float
    summary: RunSummary
    manager_cpu_s: float  # orchestrator process CPU per tick [s] (router threads included)
    recorder_cpu_s: float  # recorder process CPU per tick [s]

    @property
    def total(self) -> int:
        return self.summary.ticks + self.summary.late_ticks

    @property
    def on_schedule(self) -> bool:
        """Every planned tick ran and none was late."""
        return self.summary.stop_reason == "completed" and self.summary.late_ticks == 0

    @property
    def late_fraction(self) -> float:
        return self.summary.late_ticks / max(1, self.total)

    def row(self) -> str:
        p50, p99 = self.summary.completion_percentiles()
        late = "-" if self.mode == "lockstep" else f"{100 * self.late_fraction:.2f}"
        speed = f"{self.summary.speed:.1f}x" if self.mode == "lockstep" else "-"
        row = (
            f"{self.vehicle:9} {self.mode:9} {self.n:>3} {self.rate_hz:>5g} {self.total:>6} "
            f"{p50 * 1e3:>7.2f} {p99 * 1e3:>7.2f} {late:>6} {self.manager_cpu_s * 1e3:>8.3f} "
            f"{self.recorder_cpu_s * 1e3:>8.3f} {speed:>7}"
        )
        if self.summary.stop_reason != "completed":  # e.g. an agent starved past its lease
            row += f"  stopped early: {self.summary.stop_reason}"
        return row


HEADER = (
    f"{'vehicle':9} {'mode':9} {'N':>3} {'rate':>5} {'ticks':>6} {'p50 ms':>7} {'p99 ms':>7} "
    f"{'late%':>6} {'mgr ms':>8} {'rec ms':>8} {'speed':>7}"
)


def _process_cpu_s(pid: int) -> float:
    """User + system CPU of process ``pid`` so far [s] (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_once(
    *,
    n: int,
    rate_hz: float,
    mode: str,
    seconds: float,
    record: str,
    vehicle: str,
    secure: bool = False,
) -> Result:
    """Run one configuration like ``hilswarm run`` does (agents, manager, recorder process).

    ``secure``: with the run's authentication and access control, as ``hilswarm run`` has by
    default (off: as ``hilswarm run --insecure``).
    """
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        experiment = load_experiment(
            ring_experiment(
                folder, n=n, rate_hz=rate_hz, mode=mode, seconds=seconds, vehicle=vehicle
            )
        )
        listen = [bus.loopback_endpoint(0)]
        security = None
        if secure:
            security = RunSecurity.for_experiment(experiment, "bench", folder, listen=listen)
        sink: RecorderProcess | Recorder | None = None
        if record == "process":
            sink = RecorderProcess(folder / "run.mcap", experiment, log_time_ns=time.time_ns())
        elif record == "inline":
            sink = Recorder(folder / "run.mcap", experiment, log_time_ns=time.time_ns())
        manager = InstanceManager(
            experiment,
            recorder=sink,
            listen=listen,
            run_id="bench",
            security=security.router() if security else None,
        )
        recorder_cpu = 0.0
        try:
            manager.open()
            endpoints = manager.endpoints
            credentials = security.write_credentials(endpoints) if security else None
            with AgentLauncher(endpoints, credentials=credentials) as launcher:
                launcher.start_all(
                    [
                        agent_config_for(experiment, name, run_id="bench")
                        for name in experiment.agent_names
                    ]
                )
                manager.wait_for_agents(300, check=launcher.check)
                if isinstance(sink, RecorderProcess):
                    sink.wait_ready()
                    recorder_cpu = -_process_cpu_s(sink.process.pid)
                cpu0 = resource.getrusage(resource.RUSAGE_SELF)
                summary = manager.run()
                cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        finally:
            manager.close()
            if isinstance(sink, RecorderProcess):
                recorder_cpu += _process_cpu_s(sink.process.pid)
                sink.close()
            elif sink is not None:
                sink.close()
    cpu = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
    ticks = max(1, summary.ticks + summary.late_ticks)
    return Result(vehicle, mode, n, rate_hz, summary, cpu / ticks, max(0.0, recorder_cpu) / ticks)


def baseline_row(bare: BareResult) -> str:
    """A table row for a bare-bus baseline run (same columns as :meth:`Result.row`)."""
    p50, p99 = bare.percentiles_ms()
    late = "-" if bare.mode == "lockstep" else f"{100 * bare.late_fraction:.2f}"
    speed = f"{bare.speed:.1f}x" if bare.mode == "lockstep" else "-"
    return (
        f"{'bare bus':9} {bare.mode:9} {bare.n:>3} {bare.rate_hz:>5g} {bare.ticks:>6} "
        f"{p50:>7.2f} {p99:>7.2f} {late:>6} {'-':>8} {'-':>8} {speed:>7}"
    )


def verdicts(results: list[Result]) -> list[str]:
    """One honest line per target of the issue: met / missed / not measured, with numbers."""
    lines = []

    def realtime(vehicle: str, n: int, rate: float) -> Result | None:
        return next(
            (
                r
                for r in results
                if (r.vehicle, r.mode, r.n, r.rate_hz) == (vehicle, "realtime", n, rate)
            ),
            None,
        )

    for vehicle in sorted({r.vehicle for r in results}):
        target = realtime(vehicle, 32, 100.0)
        name = f"[{vehicle}] 32 agents at 100 Hz, p99 < 10 ms and no late ticks"
        if target is None:
            lines.append(f"{name}: not measured")
        else:
            _, p99 = target.summary.completion_percentiles()
            met = p99 < 0.010 and target.on_schedule
            lines.append(
                f"{name}: {'MET' if met else 'MISSED'} "
                f"(p99 {p99 * 1e3:.2f} ms, {target.summary.late_ticks} late of {target.total})"
            )
        target = realtime(vehicle, 64, 50.0)
        name = f"[{vehicle}] 64 agents at 50 Hz on schedule (no late ticks, p99 < 20 ms)"
        if target is None:
            lines.append(f"{name}: not measured")
        else:
            _, p99 = target.summary.completion_percentiles()
            met = p99 < 0.020 and target.on_schedule
            lines.append(
                f"{name}: {'MET' if met else 'MISSED'} "
                f"(p99 {p99 * 1e3:.2f} ms, {target.summary.late_ticks} late of {target.total})"
            )
        lock = next(
            (
                r
                for r in results
                if (r.vehicle, r.mode, r.n, r.rate_hz) == (vehicle, "lockstep", 8, 100.0)
            ),
            None,
        )
        name = f"[{vehicle}] lockstep 8 agents at 100 Hz >= 10x real time"
        if lock is None:
            lines.append(f"{name}: not measured")
        else:
            met = lock.summary.speed >= 10.0 and lock.summary.stop_reason == "completed"
            lines.append(f"{name}: {'MET' if met else 'MISSED'} ({lock.summary.speed:.1f}x)")
        kept = [
            r for r in results if r.vehicle == vehicle and r.mode == "realtime" and r.on_schedule
        ]
        if kept:
            best = max(kept, key=lambda r: (r.n * r.rate_hz, r.n))
            lines.append(
                f"[{vehicle}] most kept on schedule: {best.n} agents at {best.rate_hz:g} Hz "
                f"({best.n * best.rate_hz:g} agent-ticks/s)"
            )
        else:
            lines.append(f"[{vehicle}] no realtime configuration kept on schedule")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--short", action="store_true", help="CI-sized run (< 60 s)")
    parser.add_argument("--agents", type=int, nargs="*", default=[8, 16, 32, 64])
    parser.add_argument("--rates", type=float, nargs="*", default=[50.0, 100.0, 200.0])
    parser.add_argument("--seconds", type=float, default=10.0, help="realtime run length [s]")
    parser.add_argument(
        "--vehicle", choices=("frisbee", "simulated", "both"), default="both",
        help="fleet: Frisbee bots on sim:// boards, simulated integrators, or both",
    )  # fmt: skip
    parser.add_argument(
        "--record", choices=("process", "inline", "off"), default="process",
        help="recorder process (as hilswarm run), recorder inside the manager, or none",
    )  # fmt: skip
    parser.add_argument("--no-lockstep", action="store_true")
    parser.add_argument(
        "--no-baseline", action="store_true", help="skip the bare-bus baseline runs"
    )
    args = parser.parse_args(argv)
    lockstep_seconds = 30.0
    if args.short:
        args.agents, args.rates, args.seconds = [8], [50.0], 4.0
        args.vehicle = "frisbee" if args.vehicle == "both" else args.vehicle
        lockstep_seconds = 5.0
    fleets = ["frisbee", "simulated"] if args.vehicle == "both" else [args.vehicle]
    print(
        f"fleets {', '.join(fleets)}; recording: {args.record}; "
        f"realtime runs of {args.seconds:g} s; {os.cpu_count()} CPUs\n"
        "p50/p99: tick completion (scheduled time to last y_k in; a late tick counts as inf);\n"
        "mgr/rec ms: CPU per tick of the orchestrator process (Zenoh router included) and of "
        "the recorder process"
    )
    print(HEADER, flush=True)
    results: list[Result] = []
    baselines: dict[tuple[str, int, float], BareResult] = {}
    for vehicle in fleets:
        configs = [("realtime", n, rate, args.seconds) for n in args.agents for rate in args.rates]
        if not args.no_lockstep:
            configs.append(("lockstep", 8, 100.0, lockstep_seconds))
        for mode, n, rate, seconds in configs:
            if not args.no_baseline and (mode, n, rate) not in baselines:
                baselines[(mode, n, rate)] = run_bare(
                    n=n, rate_hz=rate, seconds=seconds, lockstep=mode == "lockstep"
                )
                print(baseline_row(baselines[(mode, n, rate)]), flush=True)
            result = run_once(
                n=n, rate_hz=rate, mode=mode, seconds=seconds, record=args.record,
                vehicle=vehicle,
            )  # fmt: skip
            results.append(result)
            print(result.row(), flush=True)
    print("\ntargets:")
    for line in verdicts(results):
        print("  " + line)
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.ERROR)
    sys.exit(main())

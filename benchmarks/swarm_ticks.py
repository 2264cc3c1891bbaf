"""Swarm tick benchmark: how many agents the runtime keeps on schedule on this machine.

Two fleets on a two-way ring graph: Frisbee bots on simulated ``sim://`` boards driving to a
waypoint, and simulated integrators running consensus. Realtime mode, N agents at a given
rate: p50/p99 tick completion time (from the tick's scheduled time until the last y_k is in)
and the fraction of late ticks. Lockstep mode: speed as a multiple of real time.

    python benchmarks/swarm_ticks.py            # the targets' configurations (Frisbee fleet)
    python benchmarks/swarm_ticks.py --short    # Frisbee fleet, N = 8 at 50 Hz (< 60 s)
    python benchmarks/swarm_ticks.py --agents 32 --rates 100 --vehicle simulated
    python benchmarks/swarm_ticks.py --agents 16 32 --rates 100 --seconds 4 --realtime-clock both
    python benchmarks/swarm_ticks.py --work-floor --settle-load 0.9   # each with its work floor
    python benchmarks/swarm_ticks.py --no-realtime --work-floor --settle-load 0.9  # lockstep alone

``--realtime-clock`` picks how realtime runs keep time (the experiment's ``realtime_clock``):
``shared`` (the default, as ``hilswarm run``: the agents keep the manager's schedule
themselves), ``manager`` (one tick message per period) or ``both`` (each configuration once
each way, back to back after the baselines).

Every run records to a temporary MCAP file through the recorder process, like ``hilswarm run``
(``--record inline``: inside the manager process, on its ticking thread; ``--record off``: not
at all). The last lines compare the figures with the issue's targets: met or missed, with the
numbers.

Each configuration is also run as a *bare bus* baseline (``benchmarks/bare_bus.py``, skip with
``--no-baseline``): the same router and one client process per agent answering every tick
from the bus callback, with no vehicle, controller or recording. It is measured in the same
process, right before the runtime, so a busy machine shows in both; the runtime cannot beat it.
The verdicts compare each runtime configuration with its paired baseline (targets in
docs/running.md, "Performance").

``--work-floor`` also runs each configuration's *work floor* before the runtime (a
``bus+work`` row): the bare bus whose clients run the fleet's own tick work before each answer
(``bare_bus.py --tick-work``), in the runtime's pattern (self-clocked when the runtime is;
lockstep within the default window). It is information, not a target: what the bus and the
fleet's work cost together here, a floor for any runtime with that fleet, and the last lines
set each runtime figure against it.

Every configuration (baseline and runtime) also prints one JSON line, for scripts that compare
runs; its keys are stable (docs/running.md, "Benchmark JSON lines"):

    {"kind": "bare"|"runtime"|"bare_work", "mode": "realtime"|"lockstep", "agents", "rate_hz",
     "p50_ms", "p99_ms", "late_fraction", "speed", "startup_s", "load_1min", "vehicle",
     "manager_cpu_ms", "agent_cpu_ms", "recorder_cpu_ms", "realtime_clock", "last_late_tick",
     "cpu_busy"}

``p99_ms`` is ``null`` when late ticks make it infinite; ``speed`` is ``null`` in realtime;
``late_fraction`` is ``null`` in lockstep; CPU figures are per tick (``agent_cpu_ms``: one
agent's mean; for the bare bus, one client's mean; its manager and recorder figures are
``null``; ``recorder_cpu_ms``: from the recorder's ready until every record is written, so what
it writes after the last tick when it fell behind counts too, the file's closing not);
``realtime_clock`` is the runtime's ``"manager"`` or ``"shared"`` in realtime (``null`` in
lockstep and for the ticked bare bus; ``"shared"`` for the self-clocked bare bus, run with
``--realtime-clock both`` for information: the verdicts keep the ticked bare bus);
``load_1min`` is the 1-minute load average when the configuration began (the benchmark's own
processes raise it; ``--settle-load 1`` waits for a quiet machine before each run);
``last_late_tick`` is the runtime's last late tick (``null``: none late; always ``null`` for
the bare bus): under ``START_TICKS`` every late tick was a start-up transient, and the verdict
line says so; ``cpu_busy`` is the fraction [0, 1] of the machine's CPU time that was busy while
the configuration ticked, anyone's work (``cpu_sampler.py``; the ``busy%`` column, and the
verdict lines beside their baseline's): near 1, the run was short of CPU.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import resource
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bare_bus import BareResult, run_bare
from cpu_sampler import CpuSampler, process_cpu_s
from hilswarm.agents import bus
from hilswarm.agents.agent_config import DEFAULT_LOCKSTEP_WINDOW
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.launcher import AgentLauncher, agent_config_for
from hilswarm.orchestrator.manager import InstanceManager
from hilswarm.orchestrator.recorder import Recorder
from hilswarm.orchestrator.recorder_process import RecorderProcess
from hilswarm.orchestrator.run_security import RunSecurity
from hilswarm.orchestrator.run_summary import RunSummary


def ring_experiment(
    folder: Path,
    *,
    n: int,
    rate_hz: float,
    mode: str,
    seconds: float,
    vehicle: str,
    realtime_clock: str = "shared",
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
        f'mode = "{mode}"\non_agent_loss = "stop"\nrealtime_clock = "{realtime_clock}"\n'
        f"\n[graph]\nagents = {names}\n"
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
    recorder_cpu_s: float  # recorder process CPU per tick [s], ready to every record written
    agent_cpu_s: float  # one agent process's CPU per tick [s] (mean over the agents)
    startup_s: float  # fork server started (bus opening beside it) to every agent armed [s]
    load_1min: float  # the machine's 1-minute load average when the configuration began
    realtime_clock: str = "shared"  # realtime: "shared" (self-clocked) or "manager" (ticks)
    cpu_busy: float = math.nan  # the machine's CPUs busy during the ticks [0, 1], anyone's work

    @property
    def label(self) -> str:
        """The mode column: ``rt/shared`` for a self-clocked realtime run."""
        return "rt/shared" if self.clocked else self.mode

    @property
    def clocked(self) -> bool:
        return self.mode == "realtime" and self.realtime_clock == "shared"

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

    @property
    def percentiles_ms(self) -> tuple[float, float]:
        """(p50, p99) tick completion [ms]; late ticks count as infinite."""
        p50, p99 = self.summary.completion_percentiles()
        return p50 * 1e3, p99 * 1e3

    def row(self) -> str:
        p50, p99 = self.percentiles_ms
        late = "-" if self.mode == "lockstep" else f"{100 * self.late_fraction:.2f}"
        speed = f"{self.summary.speed:.1f}x" if self.mode == "lockstep" else "-"
        row = (
            f"{self.vehicle:9} {self.label:9} {self.n:>3} {self.rate_hz:>5g} {self.total:>6} "
            f"{p50:>7.2f} {p99:>7.2f} {late:>6} {self.manager_cpu_s * 1e3:>8.3f} "
            f"{self.agent_cpu_s * 1e3:>8.3f} {self.recorder_cpu_s * 1e3:>8.3f} {speed:>7} "
            f"{self.startup_s:>6.2f} {self.load_1min:>5.2f} {_percent(self.cpu_busy):>5}"
        )
        if self.summary.stop_reason != "completed":  # e.g. an agent starved past its lease
            row += f"  stopped early: {self.summary.stop_reason}"
        return row


HEADER = (
    f"{'vehicle':9} {'mode':9} {'N':>3} {'rate':>5} {'ticks':>6} {'p50 ms':>7} {'p99 ms':>7} "
    f"{'late%':>6} {'mgr ms':>8} {'agt ms':>8} {'rec ms':>8} {'speed':>7} {'up s':>6} "
    f"{'load':>5} {'busy%':>5}"
)


def _percent(fraction: float) -> str:
    """A fraction as a whole percentage for the table (``-`` when unknown)."""
    return f"{100 * fraction:.0f}" if math.isfinite(fraction) else "-"


def _finite(value: float, digits: int = 3) -> float | None:
    """``value`` rounded, or ``None`` (JSON null) when it is not finite."""
    return round(value, digits) if math.isfinite(value) else None


def json_line(
    *,
    kind: str,
    mode: str,
    agents: int,
    rate_hz: float,
    p50_ms: float,
    p99_ms: float,
    late_fraction: float,
    speed: float,
    startup_s: float,
    load_1min: float,
    vehicle: str | None = None,
    manager_cpu_ms: float = math.nan,
    agent_cpu_ms: float = math.nan,
    recorder_cpu_ms: float = math.nan,
    realtime_clock: str | None = None,
    last_late_tick: int | None = None,
    cpu_busy: float = math.nan,
) -> str:
    """The stable JSON line of one configuration (keys documented in the module doc)."""
    lockstep = mode == "lockstep"
    return json.dumps(
        {
            "kind": kind,
            "mode": mode,
            "agents": agents,
            "rate_hz": rate_hz,
            "p50_ms": _finite(p50_ms),
            "p99_ms": _finite(p99_ms),
            "late_fraction": None if lockstep else round(late_fraction, 5),
            "speed": _finite(speed, 2) if lockstep else None,
            "startup_s": _finite(startup_s),
            "load_1min": round(load_1min, 2),
            "vehicle": vehicle,
            "manager_cpu_ms": _finite(manager_cpu_ms, 4),
            "agent_cpu_ms": _finite(agent_cpu_ms, 4),
            "recorder_cpu_ms": _finite(recorder_cpu_ms, 4),
            "realtime_clock": realtime_clock,
            "last_late_tick": last_late_tick,
            "cpu_busy": _finite(cpu_busy),
        }
    )


def result_json(result: Result) -> str:
    """:func:`json_line` of a runtime configuration."""
    p50, p99 = result.percentiles_ms
    return json_line(
        kind="runtime", mode=result.mode, agents=result.n, rate_hz=result.rate_hz,
        p50_ms=p50, p99_ms=p99, late_fraction=result.late_fraction,
        speed=result.summary.speed, startup_s=result.startup_s, load_1min=result.load_1min,
        vehicle=result.vehicle, manager_cpu_ms=result.manager_cpu_s * 1e3,
        agent_cpu_ms=result.agent_cpu_s * 1e3, recorder_cpu_ms=result.recorder_cpu_s * 1e3,
        realtime_clock=result.realtime_clock if result.mode == "realtime" else None,
        last_late_tick=result.summary.last_late_tick, cpu_busy=result.cpu_busy,
    )  # fmt: skip


def bare_json(
    bare: BareResult,
    load_1min: float,
    realtime_clock: str | None = None,
    *,
    vehicle: str | None = None,
) -> str:
    """:func:`json_line` of a bare-bus baseline (``agent_cpu_ms``: one client's CPU;
    ``realtime_clock`` ``"shared"``: the self-clocked bare bus). With ``vehicle``, the work
    floor of that fleet (``kind`` ``"bare_work"``: its clients ran the fleet's tick work)."""
    p50, p99 = bare.percentiles_ms()
    return json_line(
        kind="bare_work" if vehicle else "bare", mode=bare.mode, vehicle=vehicle,
        agents=bare.n, rate_hz=bare.rate_hz, p50_ms=p50, p99_ms=p99,
        late_fraction=bare.late_fraction, speed=bare.speed,
        startup_s=bare.startup_s, load_1min=load_1min, agent_cpu_ms=bare.client_cpu_s * 1e3,
        realtime_clock=realtime_clock, cpu_busy=bare.cpu_busy,
    )  # fmt: skip


def run_once(
    *,
    n: int,
    rate_hz: float,
    mode: str,
    seconds: float,
    record: str,
    vehicle: str,
    secure: bool = False,
    realtime_clock: str = "shared",
) -> Result:
    """Run one configuration like ``hilswarm run`` does (agents, manager, recorder process).

    ``secure``: with the run's authentication and access control, as ``hilswarm run`` has by
    default (off: as ``hilswarm run --insecure``).
    """
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        experiment = load_experiment(
            ring_experiment(
                folder,
                n=n,
                rate_hz=rate_hz,
                mode=mode,
                seconds=seconds,
                vehicle=vehicle,
                realtime_clock=realtime_clock,
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
        load = os.getloadavg()[0]
        try:
            with AgentLauncher([]) as launcher:
                # As ``hilswarm run``: the fork server imports the agent code while the bus
                # opens; start-up is counted from there (bus and credentials included).
                started = time.perf_counter()
                launcher.prepare()
                manager.open()
                launcher.endpoints = manager.endpoints
                if security:
                    launcher.credentials = security.write_credentials(manager.endpoints)
                launcher.start_all(
                    [
                        agent_config_for(experiment, name, run_id="bench")
                        for name in experiment.agent_names
                    ]
                )
                manager.wait_for_agents(300, check=launcher.check)
                startup = time.perf_counter() - started
                if isinstance(sink, RecorderProcess):
                    sink.wait_ready()
                    recorder_cpu = -(process_cpu_s(sink.process.pid) or 0.0)
                agents = CpuSampler([process.pid for process in launcher.processes.values()])
                agents.start()
                cpu0 = resource.getrusage(resource.RUSAGE_SELF)
                summary = manager.run()
                cpu1 = resource.getrusage(resource.RUSAGE_SELF)
                agents.stop()
        finally:
            manager.close()
            if isinstance(sink, RecorderProcess):
                # A recorder behind the ticks (niced, the CPUs full) writes the rest after the
                # last tick: its CPU is read once every record is written, before the file's
                # closing (a cost per run, not per tick).
                if not sink.wait_written(RECORDER_CATCH_UP_S):
                    print(
                        f"the recorder did not write every record within "
                        f"{RECORDER_CATCH_UP_S:g} s of the last tick: its CPU figure is short",
                        file=sys.stderr,
                    )
                recorder_cpu += process_cpu_s(sink.process.pid) or 0.0
                sink.close()
            elif sink is not None:
                sink.close()
    cpu = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
    ticks = max(1, summary.ticks + summary.late_ticks)
    return Result(
        vehicle, mode, n, rate_hz, summary, cpu / ticks, max(0.0, recorder_cpu) / ticks,
        agents.total_s() / ticks / n, startup, load, realtime_clock, agents.machine_busy(),
    )  # fmt: skip


def baseline_row(bare: BareResult, load_1min: float, label: str = "", what: str = "") -> str:
    """A table row for a bare-bus baseline run (same columns as :meth:`Result.row`; ``agt``:
    one client's CPU per tick; ``what``: the first column, default ``bare bus``)."""
    p50, p99 = bare.percentiles_ms()
    late = "-" if bare.mode == "lockstep" else f"{100 * bare.late_fraction:.2f}"
    speed = f"{bare.speed:.1f}x" if bare.mode == "lockstep" else "-"
    return (
        f"{what or 'bare bus':9} {label or bare.mode:9} {bare.n:>3} {bare.rate_hz:>5g} "
        f"{bare.ticks:>6} {p50:>7.2f} {p99:>7.2f} {late:>6} {'-':>8} "
        f"{bare.client_cpu_s * 1e3:>8.3f} {'-':>8} {speed:>7} {bare.startup_s:>6.2f} "
        f"{load_1min:>5.2f} {_percent(bare.cpu_busy):>5}"
    )


def settle(max_load: float | None, timeout_s: float = 240.0) -> None:
    """Wait (bounded) until the 1-minute load average is below ``max_load`` (``None``: no wait).

    The benchmark's own processes raise the load; waiting before each configuration keeps one
    configuration's load from weighing on the next.
    """
    if max_load is None:
        return
    deadline = time.monotonic() + timeout_s
    while os.getloadavg()[0] >= max_load and time.monotonic() < deadline:
        time.sleep(5.0)


def add_settle_option(parser: argparse.ArgumentParser) -> None:
    """``--settle-load LOAD``: :func:`settle` before each run (the benchmarks' one wording)."""
    parser.add_argument(
        "--settle-load", type=float, metavar="LOAD",
        help="before each run, wait (up to 4 min) until the 1-minute load average is below LOAD",
    )  # fmt: skip


#: Realtime configurations of the issue's targets: (agents, rate [Hz]).
REALTIME_TARGETS = ((16, 100.0), (32, 100.0), (64, 50.0))
#: Realtime: the runtime's late fraction may exceed its baseline's by this much [fraction].
LATE_MARGIN = 0.005
#: Realtime: the runtime's p99 may be at most this multiple of its baseline's.
P99_RATIO = 1.5
#: Lockstep, 8 agents at 100 Hz: absolute speed and the fraction of the bare bus's speed.
LOCKSTEP_SPEED, LOCKSTEP_FRACTION = 10.0, 0.75
#: Realtime: late ticks all below this index are reported as a start-up transient (the
#: verdict itself counts every late tick).
START_TICKS = 10
#: 32 agents ready within this [s].
STARTUP_S = 2.0
#: After the ticks, how long the recorder may take to write what it is behind with [s].
RECORDER_CATCH_UP_S = 60.0


def _busy_note(busy: float, bare_busy: float) -> str:
    """``, CPUs 93 % busy vs bare 48 %``: how near the run was to the machine's CPU limit
    ("" when it was not measured)."""
    if not math.isfinite(busy):
        return ""
    note = f", CPUs {100 * busy:.0f} % busy"
    return note + (f" vs bare {100 * bare_busy:.0f} %" if math.isfinite(bare_busy) else "")


def verdicts(
    results: list[Result], baselines: dict[tuple[str, int, float], BareResult]
) -> list[str]:
    """One line per target: MET / MISSED / not measured, each judged against its pair.

    A realtime target whose paired bare bus has over 1 % late ticks is NOT JUDGED ("the bare
    bus misses its deadlines as well"): the machine, not the runtime, is the limit of that
    run (the late-fraction rule alone would call 100 % late beside 99.5 % "met").
    """
    lines = []
    clocks = sorted({r.realtime_clock for r in results if r.mode == "realtime"}) or ["manager"]
    for vehicle in sorted({r.vehicle for r in results}):

        def find(
            mode: str, n: int, rate: float, vehicle: str = vehicle, clock: str = ""
        ) -> Result | None:
            key = (vehicle, mode, n, rate)
            return next(
                (
                    r
                    for r in results
                    if (r.vehicle, r.mode, r.n, r.rate_hz) == key
                    and (not clock or r.realtime_clock == clock)
                ),
                None,
            )

        for (n, rate), clock in [(target, c) for target in REALTIME_TARGETS for c in clocks]:
            name = f"[{vehicle}] realtime ({clock} clock) {n} agents at {rate:g} Hz"
            result = find("realtime", n, rate, clock=clock)
            bare = baselines.get(("realtime", n, rate))
            if result is None or bare is None:
                lines.append(f"{name}: not measured (with its baseline)")
                continue
            _, p99 = result.percentiles_ms
            _, bare_p99 = bare.percentiles_ms()
            late_ok = result.late_fraction <= bare.late_fraction + LATE_MARGIN
            p99_ok = p99 <= P99_RATIO * bare_p99
            absolute_ok = True
            if (n, rate) == (32, 100.0) and bare.late_ticks == 0:
                absolute_ok = p99 < 10.0 and result.summary.late_ticks == 0
            met = late_ok and p99_ok and absolute_ok
            bare_missed = not math.isfinite(bare_p99)  # over 1 % of the bare bus's ticks late
            figures = (
                f"late {100 * result.late_fraction:.2f} % vs bare {100 * bare.late_fraction:.2f}"
                f" %, p99 {p99:.2f} ms vs bare {bare_p99:.2f} ms "
                f"(ratio {p99 / bare_p99 if bare_p99 else math.inf:.2f}), "
                f"load {result.load_1min:.2f}{_busy_note(result.cpu_busy, bare.cpu_busy)}"
            )
            last_late = result.summary.last_late_tick
            if last_late is not None and last_late < START_TICKS:
                figures += f"; every late tick at the start ({result.summary.late_range()})"
            verdict = "MET" if met else "MISSED"
            if bare_missed:  # the machine, not the runtime, is the limit of this run
                verdict = "NOT JUDGED (the bare bus misses its deadlines as well)"
            lines.append(f"{name}: {verdict} ({figures})")
        name = f"[{vehicle}] lockstep 8 agents at 100 Hz >= {LOCKSTEP_SPEED:g}x"
        result, bare = find("lockstep", 8, 100.0), baselines.get(("lockstep", 8, 100.0))
        if result is None or bare is None:
            lines.append(f"{name}: not measured (with its baseline)")
        else:
            speed, ratio = result.summary.speed, result.summary.speed / max(bare.speed, 1e-9)
            met = speed >= LOCKSTEP_SPEED and ratio >= LOCKSTEP_FRACTION
            met = met and result.summary.stop_reason == "completed"
            verdict = "MET" if met else "MISSED"
            if not met and bare.speed < LOCKSTEP_SPEED:
                verdict += f" (the bare bus reaches only {bare.speed:.1f}x)"
            lines.append(
                f"{name} and >= {100 * LOCKSTEP_FRACTION:.0f} % of the bare bus: {verdict} "
                f"({speed:.1f}x vs bare {bare.speed:.1f}x, ratio {ratio:.2f}, "
                f"load {result.load_1min:.2f}{_busy_note(result.cpu_busy, bare.cpu_busy)})"
            )
        sized = [r for r in results if r.vehicle == vehicle and r.n >= 32]
        name = f"[{vehicle}] 32 agents ready < {STARTUP_S:g} s"
        if not sized:
            lines.append(f"{name}: not measured")
        else:
            worst = max(r.startup_s for r in sized if r.n == min(x.n for x in sized))
            verdict = "MET" if worst < STARTUP_S else "MISSED"
            lines.append(f"{name}: {verdict} ({worst:.2f} s)")
        for r in results:
            if r.vehicle == vehicle:
                lines.append(
                    f"[{vehicle}] CPU per tick, {r.label} {r.n} @ {r.rate_hz:g} Hz: manager "
                    f"{r.manager_cpu_s * 1e3:.3f} ms, each agent {r.agent_cpu_s * 1e3:.3f} ms, "
                    f"recorder {r.recorder_cpu_s * 1e3:.3f} ms"
                )
    return lines


#: ``--work-floor``: the ``bare_bus.py --tick-work`` case of each fleet's vehicle and
#: controller (``benchmarks/agent_tick.py``).
FLEET_TICK_WORK = {"frisbee": "frisbee", "simulated": "consensus"}


def run_work_floor(
    *, vehicle: str, mode: str, n: int, rate_hz: float, seconds: float, self_clocked: bool
) -> BareResult:
    """The bare bus whose clients also run the fleet's tick work (rehearsed first, as the
    agents' is) before each answer, in the runtime's own pattern (self-clocked or ticked;
    lockstep within the default window): what the bus and that work cost together here, a
    floor for any runtime with that fleet. The window pattern measures speed only (no
    per-tick completion times: p50/p99 NaN)."""
    lockstep = mode == "lockstep"
    return run_bare(
        n=n, rate_hz=rate_hz, seconds=seconds, lockstep=lockstep,
        self_clocked=self_clocked and not lockstep,
        window=DEFAULT_LOCKSTEP_WINDOW if lockstep else 0,
        tick_work=FLEET_TICK_WORK[vehicle],
    )  # fmt: skip


def floor_lines(
    results: list[Result], floors: dict[tuple[str, str, int, float], BareResult]
) -> list[str]:
    """Information, not a target: each runtime figure against its fleet's work floor."""
    lines = []
    for r in results:
        floor = floors.get((r.vehicle, r.mode, r.n, r.rate_hz))
        if floor is None:
            continue
        head = f"[{r.vehicle}] {r.label} {r.n} @ {r.rate_hz:g} Hz"
        if r.mode == "lockstep":
            lines.append(
                f"{head}: {r.summary.speed:.1f}x against the work floor's "
                f"{floor.speed:.1f}x (ratio {r.summary.speed / max(floor.speed, 1e-9):.2f})"
            )
            continue
        _, p99 = r.percentiles_ms
        _, floor_p99 = floor.percentiles_ms()
        ratio = p99 / floor_p99 if math.isfinite(floor_p99) and floor_p99 else math.nan
        lines.append(
            f"{head}: late {100 * r.late_fraction:.2f} % against the work floor's "
            f"{100 * floor.late_fraction:.2f} %, p99 {p99:.2f} ms against {floor_p99:.2f} ms "
            f"(ratio {ratio:.2f})"
        )
    return lines


def plan(args: argparse.Namespace) -> list[tuple[str, int, float, float]]:
    """The configurations a run measures, in order: ``(mode, agents, rate [Hz], seconds)``.

    ``seconds`` is the run length [s]: wall time in realtime, experiment time in lockstep.
    Realtime: ``--short`` 8 agents at 50 Hz (4 s), ``--agents``/``--rates`` a grid, else the
    targets' sizes; none with ``--no-realtime``. Lockstep: 8 agents at 100 Hz for
    ``--lockstep-seconds`` (default 30, 5 with ``--short``); none with ``--no-lockstep``.
    """
    seconds, lockstep_seconds = (4.0, 5.0) if args.short else (args.seconds, 30.0)
    if args.lockstep_seconds is not None:
        lockstep_seconds = args.lockstep_seconds
    if args.no_realtime:
        realtime: list[tuple[int, float]] = []
    elif args.short:
        realtime = [(8, 50.0)]
    elif args.agents or args.rates:
        realtime = [(n, rate) for n in args.agents or [16] for rate in args.rates or [100.0]]
    else:
        realtime = list(REALTIME_TARGETS)
    configs = [("realtime", n, rate, seconds) for n, rate in realtime]
    if not args.no_lockstep:
        configs.append(("lockstep", 8, 100.0, lockstep_seconds))
    return configs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--short", action="store_true", help="CI-sized run (< 60 s)")
    parser.add_argument(
        "--agents", type=int, nargs="*",
        help="realtime fleet sizes (a grid with --rates); default: the targets' "
        "16 and 32 agents at 100 Hz and 64 at 50 Hz",
    )  # fmt: skip
    parser.add_argument("--rates", type=float, nargs="*", help="realtime tick rates [Hz]")
    parser.add_argument("--seconds", type=float, default=10.0, help="realtime run length [s]")
    parser.add_argument(
        "--vehicle", choices=("frisbee", "simulated", "both"), default="frisbee",
        help="fleet: Frisbee bots on sim:// boards (default), simulated integrators, or both",
    )  # fmt: skip
    parser.add_argument(
        "--record", choices=("process", "inline", "off"), default="process",
        help="recorder process (as hilswarm run), recorder inside the manager, or none",
    )  # fmt: skip
    parser.add_argument(
        "--zenoh-runtime", choices=("lean", "default"), default="lean",
        help="Zenoh runtime pools of every process (baseline and runtime alike): hilswarm's "
        "own setting (bus.LEAN_RUNTIME, as hilswarm run) or Zenoh's defaults",
    )  # fmt: skip
    parser.add_argument(
        "--realtime-clock", choices=("shared", "manager", "both"), default="shared",
        help="realtime runs: agents keeping the manager's schedule on the shared monotonic "
        "clock (default, as hilswarm run), tick messages from the manager, or both (paired)",
    )  # fmt: skip
    parser.add_argument("--no-lockstep", action="store_true", help="skip the lockstep run")
    parser.add_argument(
        "--no-realtime", action="store_true",
        help="skip the realtime runs (lockstep only: the CPU-bound target, quickest to pair)",
    )  # fmt: skip
    parser.add_argument(
        "--lockstep-seconds", type=float, metavar="S",
        help="lockstep experiment length [s] (default 30, 5 with --short)",
    )  # fmt: skip
    add_settle_option(parser)
    parser.add_argument(
        "--no-baseline", action="store_true", help="skip the bare-bus baseline runs"
    )
    parser.add_argument(
        "--work-floor", action="store_true",
        help="also run each configuration's work floor: the bare bus whose clients run the "
        "fleet's own tick work before each answer, in the runtime's pattern (information: a "
        "floor for any runtime with that fleet here; the targets keep the bare bus)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.no_realtime and args.no_lockstep:
        parser.error("--no-realtime and --no-lockstep leave nothing to run")
    if args.lockstep_seconds is not None and not args.lockstep_seconds > 0:
        parser.error("--lockstep-seconds must be > 0")
    os.environ["ZENOH_RUNTIME"] = bus.LEAN_RUNTIME if args.zenoh_runtime == "lean" else "()"
    configs = plan(args)
    lengths = {mode: f"{seconds:g} s" for mode, _n, _rate, seconds in configs}
    fleets = ["frisbee", "simulated"] if args.vehicle == "both" else [args.vehicle]
    print(
        f"fleets {', '.join(fleets)}; recording: {args.record}; zenoh runtime: "
        f"{args.zenoh_runtime}; realtime runs of {lengths.get('realtime', 'none')}, lockstep of "
        f"{lengths.get('lockstep', 'none')} of experiment; {os.cpu_count()} CPUs; "
        f"python {platform.python_version()} ({os.path.realpath(sys.executable)})\n"
        "p50/p99: tick completion (scheduled time to last y_k in; a late tick counts as inf);\n"
        "mgr/agt/rec ms: CPU per tick of the orchestrator process (Zenoh router included), of "
        "one agent (mean) and of the recorder process;\nup s: agents started (the fork server "
        "and the bus, as hilswarm run) to all armed; "
        "load: 1-minute load average when the run began; busy%: the machine's CPUs busy while "
        "it ticked (anyone's work)",
        flush=True,
    )
    print(HEADER, flush=True)
    results: list[Result] = []
    baselines: dict[tuple[str, int, float], BareResult] = {}
    floors: dict[tuple[str, str, int, float], BareResult] = {}
    for vehicle in fleets:
        for mode, n, rate, seconds in configs:
            if not args.no_baseline and (mode, n, rate) not in baselines:
                settle(args.settle_load)
                load = os.getloadavg()[0]
                bare = run_bare(n=n, rate_hz=rate, seconds=seconds, lockstep=mode == "lockstep")
                baselines[(mode, n, rate)] = bare
                print(baseline_row(bare, load), flush=True)
                print(bare_json(bare, load), flush=True)
            clocks = (
                ["manager", "shared"] if args.realtime_clock == "both" else [args.realtime_clock]
            )
            if mode == "realtime" and len(clocks) > 1 and not args.no_baseline:
                # the fair pair of a self-clocked runtime: the self-clocked bare bus (info)
                settle(args.settle_load)
                load = os.getloadavg()[0]
                bare = run_bare(
                    n=n, rate_hz=rate, seconds=seconds, lockstep=False, self_clocked=True
                )
                print(baseline_row(bare, load, "rt/shared"), flush=True)
                print(bare_json(bare, load, "shared"), flush=True)
            if args.work_floor:
                settle(args.settle_load)
                load = os.getloadavg()[0]
                self_clocked = mode == "realtime" and "shared" in clocks
                floor = run_work_floor(
                    vehicle=vehicle, mode=mode, n=n, rate_hz=rate, seconds=seconds,
                    self_clocked=self_clocked,
                )  # fmt: skip
                floors[(vehicle, mode, n, rate)] = floor
                label = "rt/shared" if self_clocked else mode
                print(baseline_row(floor, load, label, what="bus+work"), flush=True)
                clock_key = "shared" if self_clocked else None
                print(bare_json(floor, load, clock_key, vehicle=vehicle), flush=True)
            for clock in clocks if mode == "realtime" else ["manager"]:
                settle(args.settle_load)
                result = run_once(
                    n=n, rate_hz=rate, mode=mode, seconds=seconds, record=args.record,
                    vehicle=vehicle, realtime_clock=clock,
                )  # fmt: skip
                results.append(result)
                print(result.row(), flush=True)
                print(result_json(result), flush=True)
    print("\ntargets (each runtime figure against its paired bare-bus baseline):")
    for line in verdicts(results, baselines):
        print("  " + line)
    if floors:
        print("\nagainst the work floor (the bus with the fleet's own tick work; information):")
        for line in floor_lines(results, floors):
            print("  " + line)
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.ERROR)
    sys.exit(main())

"""The swarm benchmark's verdicts and JSON line from given figures (no run): pure functions."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from hilswarm.orchestrator.run_summary import RunSummary


@pytest.fixture(scope="module")
def swarm_ticks(benchmarks_on_path: Path) -> ModuleType:
    """The benchmark script as a module."""
    import swarm_ticks

    return swarm_ticks


def runtime(swarm_ticks: ModuleType, late_ks: list[int], completion_s: float = 0.005) -> Any:
    summary = RunSummary(experiment="bench", mode="realtime", planned_ticks=400, dt_s=0.01,
                         stop_reason="completed", ticks=400 - len(late_ks))  # fmt: skip
    summary.completion_s = [completion_s] * summary.ticks
    for k in late_ks:
        summary.note_late_tick(k)
    return swarm_ticks.Result("frisbee", "realtime", 32, 100.0, summary, 0.002, 0.001, 0.0003,
                              1.2, 0.5)  # fmt: skip


def bare(swarm_ticks: ModuleType) -> Any:
    return swarm_ticks.BareResult(32, 100.0, "realtime", 400, 0, np.full(400, 0.004), 4.0)


def verdict_32(swarm_ticks: ModuleType, result: Any) -> str:
    lines = swarm_ticks.verdicts([result], {("realtime", 32, 100.0): bare(swarm_ticks)})
    return next(line for line in lines if "32 agents at 100 Hz" in line)


def test_late_ticks_under_a_finite_p99_are_judged_not_a_crash(swarm_ticks: ModuleType) -> None:
    """Two late ticks of 400 leave p99 finite (< 10 ms): the 32-agent rule (0 late) misses,
    and the verdict says that both were at the start."""
    line = verdict_32(swarm_ticks, runtime(swarm_ticks, [0, 1]))
    assert "MISSED" in line and "late 0.50 % vs bare 0.00 %" in line
    assert "every late tick at the start (between ticks 0 and 1)" in line
    assert "MET" in verdict_32(swarm_ticks, runtime(swarm_ticks, []))
    later = verdict_32(swarm_ticks, runtime(swarm_ticks, [3, 250]))
    assert "MISSED" in later and "at the start" not in later


def test_the_json_line_names_the_last_late_tick(swarm_ticks: ModuleType) -> None:
    line = json.loads(swarm_ticks.result_json(runtime(swarm_ticks, [0, 2])))
    assert line["last_late_tick"] == 2 and line["late_fraction"] == 0.005
    assert json.loads(swarm_ticks.result_json(runtime(swarm_ticks, [])))["last_late_tick"] is None
    assert json.loads(swarm_ticks.bare_json(bare(swarm_ticks), 0.5))["last_late_tick"] is None


def test_lockstep_start_up_and_cpu_lines(swarm_ticks: ModuleType) -> None:
    summary = RunSummary(experiment="bench", mode="lockstep", planned_ticks=3000, dt_s=0.01,
                         stop_reason="completed", ticks=3000, wall_s=6.0)  # fmt: skip
    lockstep = swarm_ticks.Result("frisbee", "lockstep", 8, 100.0, summary, 0.0007, 0.0002,
                                  0.0003, 0.4, 0.5)  # fmt: skip
    bare_lockstep = swarm_ticks.BareResult(8, 100.0, "lockstep", 3000, 0, np.zeros(0), 2.5)
    baselines = {("realtime", 32, 100.0): bare(swarm_ticks), ("lockstep", 8, 100.0): bare_lockstep}
    lines = swarm_ticks.verdicts([runtime(swarm_ticks, []), lockstep], baselines)
    text = "\n".join(lines)
    assert "lockstep 8 agents at 100 Hz >= 10x and >= 75 % of the bare bus: MISSED" in text
    assert "(5.0x vs bare 12.0x, ratio 0.42, load 0.50)" in text
    assert "32 agents ready < 2 s: MET (1.20 s)" in text
    assert "CPU per tick, lockstep 8 @ 100 Hz: manager 0.700 ms" in text


def test_the_machine_s_busy_cpus_beside_the_baseline_s(swarm_ticks: ModuleType) -> None:
    """A run's busy CPUs go into its row, its JSON line and its verdict, beside its pair's."""
    result = runtime(swarm_ticks, [5])
    assert json.loads(swarm_ticks.result_json(result))["cpu_busy"] is None  # not measured
    assert "busy" not in verdict_32(swarm_ticks, result)
    result.cpu_busy = 0.93412
    paired = bare(swarm_ticks)
    paired.cpu_busy = 0.48
    assert json.loads(swarm_ticks.result_json(result))["cpu_busy"] == 0.934
    assert json.loads(swarm_ticks.bare_json(paired, 0.5))["cpu_busy"] == 0.48
    assert result.row().split()[-1] == "93"
    assert swarm_ticks.baseline_row(paired, 0.5).split()[-1] == "48"
    lines = swarm_ticks.verdicts([result], {("realtime", 32, 100.0): paired})
    line = next(line for line in lines if "32 agents at 100 Hz" in line)
    assert "load 0.50, CPUs 93 % busy vs bare 48 %" in line


def test_the_work_floor_s_rows_json_and_lines(swarm_ticks: ModuleType) -> None:
    """``--work-floor``: its JSON line is kind ``bare_work`` with the fleet; each runtime figure
    is set against its fleet's floor (ratios from the given figures), the others are not."""
    floor = swarm_ticks.BareResult(32, 100.0, "realtime", 400, 0, np.full(400, 0.0025), 4.0)
    line = json.loads(swarm_ticks.bare_json(floor, 0.5, "shared", vehicle="frisbee"))
    assert (line["kind"], line["vehicle"], line["realtime_clock"]) == (
        "bare_work",
        "frisbee",
        "shared",
    )
    assert json.loads(swarm_ticks.bare_json(bare(swarm_ticks), 0.5))["kind"] == "bare"
    assert swarm_ticks.baseline_row(floor, 0.5, "rt/shared", what="bus+work").startswith(
        "bus+work  rt/shared  32   100"
    )
    summary = RunSummary(experiment="bench", mode="lockstep", planned_ticks=3000, dt_s=0.01,
                         stop_reason="completed", ticks=3000, wall_s=5.0)  # fmt: skip
    lockstep = swarm_ticks.Result("frisbee", "lockstep", 8, 100.0, summary, 0.0007, 0.0002,
                                  0.0003, 0.4, 0.5)  # fmt: skip
    lockstep_floor = swarm_ticks.BareResult(8, 100.0, "lockstep", 3000, 0, np.zeros(0), 3.0)
    floors = {
        ("frisbee", "realtime", 32, 100.0): floor,
        ("frisbee", "lockstep", 8, 100.0): lockstep_floor,
    }
    lines = swarm_ticks.floor_lines([runtime(swarm_ticks, [7]), lockstep], floors)
    assert lines == [
        "[frisbee] rt/shared 32 @ 100 Hz: late 0.25 % against the work floor's 0.00 %, "
        "p99 5.00 ms against 2.50 ms (ratio 2.00)",
        "[frisbee] lockstep 8 @ 100 Hz: 6.0x against the work floor's 10.0x (ratio 0.60)",
    ]
    assert swarm_ticks.floor_lines([runtime(swarm_ticks, [])], {}) == []


def plan_of(swarm_ticks: ModuleType, **given: Any) -> list[tuple[str, int, float, float]]:
    """The configurations a run with these options measures (the defaults of ``main``)."""
    options = dict(short=False, agents=None, rates=None, seconds=10.0, no_lockstep=False,
                   no_realtime=False, lockstep_seconds=None)  # fmt: skip
    options.update(given)
    return swarm_ticks.plan(argparse.Namespace(**options))


def test_the_plan_of_a_run_from_its_options(swarm_ticks: ModuleType) -> None:
    targets = [("realtime", n, rate, 10.0) for n, rate in swarm_ticks.REALTIME_TARGETS]
    assert plan_of(swarm_ticks) == [*targets, ("lockstep", 8, 100.0, 30.0)]
    assert plan_of(swarm_ticks, short=True) == [
        ("realtime", 8, 50.0, 4.0),
        ("lockstep", 8, 100.0, 5.0),
    ]
    assert plan_of(swarm_ticks, no_realtime=True, lockstep_seconds=12.5) == [
        ("lockstep", 8, 100.0, 12.5)
    ]
    assert plan_of(swarm_ticks, agents=[4], rates=[20.0, 40.0], no_lockstep=True) == [
        ("realtime", 4, 20.0, 10.0),
        ("realtime", 4, 40.0, 10.0),
    ]


@pytest.mark.parametrize(
    "argv",
    [["--no-realtime", "--no-lockstep"], ["--lockstep-seconds", "0"]],
)
def test_options_that_leave_nothing_to_run_are_refused(
    swarm_ticks: ModuleType, argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        swarm_ticks.main(argv)
    assert exc.value.code == 2
    assert "--" in capsys.readouterr().err

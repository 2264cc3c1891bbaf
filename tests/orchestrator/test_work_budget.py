"""The work-budget benchmark's arithmetic from given figures (no run): pure functions."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest


@pytest.fixture(scope="module")
def work_budget(benchmarks_on_path: Path) -> ModuleType:
    """The benchmark script as a module."""
    import work_budget

    return work_budget


def run(work_budget: ModuleType, round_: int, spin_us: float, speed: float) -> object:
    """A level whose bare-bus run reached ``speed`` (x real time) over 100 ticks at 100 Hz."""
    from bare_bus import BareResult

    wall = 1.0 / speed  # 100 ticks at 100 Hz are 1 s of experiment
    result = BareResult(8, 100.0, "lockstep", 100, 0, np.zeros(0), wall, client_cpu_s=1e-4,
                        cpu_busy=0.9)  # fmt: skip
    return work_budget.Level(round_, spin_us, result, 0.5)


@pytest.mark.parametrize(
    ("share_at", "expected"),
    [
        ({0.0: 1.0, 10.0: 0.9, 20.0: 0.8, 40.0: 0.6}, (25.0, True)),  # between 20 and 40
        ({0.0: 1.0, 40.0: 0.9}, (40.0, False)),  # every level kept: a lower bound
        ({20.0: 0.5}, (10.0, True)),  # no 0 level: from no work at share 1
        ({0.0: 1.0, 10.0: 0.7, 20.0: 0.8}, (25.0 / 3.0, True)),  # the first level below counts
        ({0.0: 0.7, 10.0: 0.7}, (0.0, True)),  # nothing kept, no line to cut
    ],
)
def test_the_budget_is_cut_where_the_share_falls_below_the_fraction(
    work_budget: ModuleType, share_at: dict[float, float], expected: tuple[float, bool]
) -> None:
    value, bounded = work_budget.budget(share_at, 0.75)
    assert value == pytest.approx(expected[0])
    assert bounded is expected[1]


def test_shares_are_medians_of_each_round_against_its_own_runs_without_spin(
    work_budget: ModuleType,
) -> None:
    levels = [
        run(work_budget, 0, 0.0, 18.0), run(work_budget, 0, 40.0, 10.0),
        run(work_budget, 0, 0.0, 22.0),  # round 0: no spin at 20x on average
        run(work_budget, 1, 0.0, 10.0), run(work_budget, 1, 40.0, 6.0),
        run(work_budget, 1, 0.0, 10.0),  # round 1: a slower machine, 10x
    ]  # fmt: skip
    share_at = work_budget.shares(levels)
    assert share_at[40.0] == pytest.approx((0.5 + 0.6) / 2)
    assert share_at[0.0] == pytest.approx(1.0)


def test_a_round_without_a_run_without_spin_is_an_error(work_budget: ModuleType) -> None:
    with pytest.raises(ValueError, match="no run without spin"):
        work_budget.shares([run(work_budget, 0, 40.0, 10.0)])


@pytest.mark.parametrize(("frisbee", "words"), [(53.0, "alone is over it"), (20.0, "within it")])
def test_the_summary_sets_the_budget_against_the_frisbee_tick(
    work_budget: ModuleType, frisbee: float, words: str
) -> None:
    hot_us = {"frisbee": frisbee, "consensus": 33.0, "smd": 19.0}
    levels = [run(work_budget, 0, 0.0, 20.0), run(work_budget, 0, 40.0, 10.0),
              run(work_budget, 0, 0.0, 20.0)]  # fmt: skip
    lines, summary = work_budget.summary_lines(levels, 0.75, hot_us, 0.4)
    assert "spin 40 µs: 50 %" in lines[1]
    assert "at most 20 µs of hot CPU work per tick" in lines[-1]
    assert words in lines[-1]
    assert lines[-1].endswith("the lightest case (smd) 19 µs (load 0.40)")
    figures = json.loads(summary)
    assert list(figures) == ["kind", "fraction", "budget_us", "frisbee_hot_us", "bare_speed",
                             "load_1min", "cases_hot_us"]  # fmt: skip
    assert figures["frisbee_hot_us"] == frisbee
    assert figures["cases_hot_us"] == hot_us
    assert figures["kind"] == "work_budget_summary"
    assert figures["budget_us"] == pytest.approx(20.0)
    assert figures["bare_speed"] == pytest.approx(20.0)


def test_the_json_line_of_a_run(work_budget: ModuleType) -> None:
    figures = json.loads(work_budget.level_json(run(work_budget, 1, 40.0, 12.5), 0.625))
    assert figures == {"kind": "work_budget", "round": 1, "spin_us": 40.0, "speed": 12.5,
                       "share": 0.625, "client_cpu_ms": 0.1, "cpu_busy": 0.9,
                       "load_1min": 0.5}  # fmt: skip

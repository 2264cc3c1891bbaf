"""Counting a run's ticks and keeping the agents' reports (orchestrator/run_tally.py), in
closed form."""

from __future__ import annotations

import math

import pytest
from hilswarm.orchestrator.run_summary import RunSummary
from hilswarm.orchestrator.run_tally import (
    OVERLOAD_BLOCK_TICKS,
    OVERLOAD_LATE_FRACTION,
    RunTally,
    counts,
)

NAMES = ("a", "b", "c")


def tally(n_ticks: int = 300) -> tuple[RunTally, RunSummary, list[str]]:
    summary = RunSummary(experiment="x", mode="realtime", planned_ticks=n_ticks, dt_s=0.01)
    summary.late = dict.fromkeys(NAMES, 0)
    said: list[str] = []
    return RunTally(summary, NAMES, n_ticks, 100.0, say=said.append), summary, said


def test_ticks_are_counted_on_time_or_late_per_agent() -> None:
    t, summary, _ = tally()
    t.completed(0, 0.004)
    t.count(0, [])
    t.completed(1, 0.012)
    t.count(1, [0, 2])
    t.completed(2, math.nan)
    t.count(2, [2])
    assert summary.ticks == 1
    assert summary.late == {"a": 1, "b": 0, "c": 2}
    assert summary.late_ticks == 2
    assert t.completion[0] == pytest.approx(0.004)
    assert math.isnan(t.completion[1])  # complete but late: infinite in the percentiles
    assert t.completion_s() == [pytest.approx(0.004)]


def test_the_overload_warning_comes_once_above_a_tenth_of_a_block() -> None:
    limit = int(OVERLOAD_LATE_FRACTION * OVERLOAD_BLOCK_TICKS)
    t, _, said = tally()
    for k in range(OVERLOAD_BLOCK_TICKS):  # exactly the limit: no warning
        t.count(k, [1] if k < limit else [])
    assert said == []
    for k in range(OVERLOAD_BLOCK_TICKS, 2 * OVERLOAD_BLOCK_TICKS):  # one more: warned
        t.count(k, [1] if k < OVERLOAD_BLOCK_TICKS + limit + 1 else [])
    assert len(said) == 1
    assert said[0].startswith(f"{limit + 1} of ticks 100..199 were late")
    assert "100 Hz" in said[0]
    for k in range(2 * OVERLOAD_BLOCK_TICKS, 3 * OVERLOAD_BLOCK_TICKS):  # never again
        t.count(k, [0])
    assert len(said) == 1


def test_statuses_keep_the_first_safe_entry_degradations_and_counters() -> None:
    t, summary, _ = tally()
    t.note_status("a", "degraded", {"k": 4, "detail": "link", "kind": "transition"}, stopping=False)
    t.note_status("a", "degraded", {"k": 5, "kind": "inputs"}, stopping=False)  # not a transition
    t.note_status("a", "safe", {"k": 7, "detail": "first"}, stopping=False)
    t.note_status("a", "safe", {"k": 9, "detail": "second"}, stopping=False)
    t.note_status("b", "safe", {"k": 12, "detail": "the stop's"}, stopping=True)
    t.note_status(
        "c", "running", {"k": "x", "dropped": {"a": 2, "b": True}, "skipped": 3}, stopping=False
    )
    assert [(e.tick, e.detail) for e in summary.degraded["a"]] == [(4, "link")]
    assert (summary.safe["a"].tick, summary.safe["a"].detail) == (7, "first")
    assert "b" not in summary.safe
    assert summary.counters["c"] == {"dropped": {"a": 2}, "skipped": 3}


def test_counts_reads_a_count_or_counts_by_key() -> None:
    assert counts(3) == 3
    assert counts(True) is None
    assert counts({"x": 1, "y": "2", 5: 4}) == {"x": 1, "5": 4}
    assert counts("3") is None


def overloaded(busy_per_block: float | None) -> str:
    """The overload warning of a block of late ticks on a machine whose CPUs were
    ``busy_per_block`` busy over it (``None``: the times are not available)."""
    readings = iter([(0.0, 0.0), (0.0 + (busy_per_block or 0.0) * 2.0, 2.0)])
    summary = RunSummary(experiment="x", mode="realtime", planned_ticks=200, dt_s=0.01)
    summary.late = dict.fromkeys(NAMES, 0)
    said: list[str] = []
    times = (lambda: next(readings)) if busy_per_block is not None else (lambda: None)
    t = RunTally(summary, NAMES, 200, 100.0, say=said.append, cpu_times=times)
    for k in range(OVERLOAD_BLOCK_TICKS):
        t.count(k, [1])
    assert len(said) == 1
    return said[0]


def test_the_overload_warning_says_whether_the_cpus_were_full() -> None:
    full = overloaded(0.96)
    assert "the CPUs were 96 % busy over those ticks: too many agents for them" in full
    idle = overloaded(0.2)
    assert "the CPUs were only 20 % busy over those ticks: more likely a slow agent" in idle
    unknown = overloaded(None)
    assert "(too many agents for the CPU cores, or slow links)" in unknown
    assert "see docs/running.md, Performance" in unknown

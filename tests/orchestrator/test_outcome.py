"""The outcome of a run (exit status and degradations) from its summary: pure decisions."""

from __future__ import annotations

import pytest
from hilswarm.orchestrator.outcome import CLEAN, DEGRADED, FAILED, INTERRUPTED, decide
from hilswarm.orchestrator.run_summary import AgentEvent, RecordingReport, RunSummary


def summary(**changes: object) -> RunSummary:
    base = RunSummary(experiment="toy", mode="realtime", ticks=400, planned_ticks=400,
                      stop_reason="completed", late={"a": 0, "b": 0})  # fmt: skip
    for key, value in changes.items():
        setattr(base, key, value)
    return base


def test_a_clean_run_exits_0() -> None:
    result = decide(summary())
    assert result.code == CLEAN and not result.degradations and not result.failures
    assert decide(summary(stop_reason="stop requested: done", ticks=120)).code == CLEAN


def test_every_degradation_is_listed_with_counts_and_ticks() -> None:
    result = decide(
        summary(
            safe={"a": AgentEvent(37, "battery low")},
            lost=["b"],
            lost_at={"b": AgentEvent(120, "liveliness token lost")},
            degraded={"c": [AgentEvent(5, "link stalled"), AgentEvent(9, "link stalled")]},
            counters={
                "c": {"malformed": {"tick": 2, "y": 1}, "dropped": {"y_ahead": 2}, "skipped": 4}
            },
            late={"a": 5, "b": 7},
            late_ticks=12,
            recording=RecordingReport(
                segments=["run.mcap", "run.1.mcap"],
                failures=["recorder killed at tick 50; continued in run.1.mcap"],
            ),
        )
    )
    assert result.code == DEGRADED and not result.failures
    text = result.text()
    assert "agent a safe from tick 37: battery low" in text
    assert "agent b lost at tick 120" in text and "280 ticks missed (ticks 120..399)" in text
    assert "agent c degraded 2 times (ticks 5, 9)" in text
    assert "agent c: 3 malformed messages (tick=2, y=1), 2 dropped messages (y_ahead=2)" in text
    assert "degraded: ticks skipped by agents that fell behind: c=4" in text  # 3 % late
    assert "12 of 400 ticks late (3.0 %" in text or "12 of 400 ticks late (3.0%" in text
    assert "a=5, b=7" in text and "continued in run.1.mcap" in text
    assert text.startswith("outcome: degraded (exit status 3)")


def test_late_ticks_within_max_late_fraction_are_a_note() -> None:
    result = decide(summary(late={"a": 2}, late_ticks=2))  # 0.5 % <= 1 %
    assert result.code == CLEAN and result.notes
    assert decide(summary(late={"a": 5}, late_ticks=5)).code == DEGRADED  # 1.25 % > 1 %
    assert decide(summary(late={"a": 5}, late_ticks=5, max_late_fraction=0.05)).code == CLEAN


def test_the_late_ticks_are_placed_so_a_start_up_transient_shows() -> None:
    run = summary(late={"a": 3})
    for k in (0, 1, 2):
        run.note_late_tick(k)
    assert (run.late_ticks, run.first_late_tick, run.last_late_tick) == (3, 0, 2)
    line = "3 of 400 ticks late (0.8%, max_late_fraction 1.0%; between ticks 0 and 2)"
    assert line in decide(run).text()
    assert run.text().endswith("late ticks 3 (between ticks 0 and 2)")
    one = summary(late={"a": 1})
    one.note_late_tick(250)
    assert one.late_range() == "at tick 250" and "(0.2%, max_late_fraction 1.0%; at tick 250)" in (
        decide(one).text()
    )
    assert summary().late_range() == "" and summary().text().endswith("late ticks 0")


def test_an_agent_safe_from_its_first_tick_fails_the_run() -> None:
    result = decide(summary(safe={"leader": AgentEvent(0, "has no pose_source")}))
    assert result.code == FAILED
    assert "safe from its first tick" in result.failures[0]


def test_failures_interruptions_and_incomplete_recordings() -> None:
    assert decide(None, error="port in use").code == FAILED
    assert decide(None, interrupted=True).code == INTERRUPTED
    assert decide(summary(failed=True, stop_reason="agent b lost; stop")).code == FAILED
    assert decide(summary(ticks=0, stop_reason="interrupted"), interrupted=True).code == 130
    assert decide(summary(ticks=0)).code == FAILED  # nothing ran
    lost = RecordingReport(segments=["run.mcap"], lost_records=40, lost_ticks=(50, 60),
                           stopped_at_tick=50)  # fmt: skip
    result = decide(summary(recording=lost, dt_s=0.02))
    assert result.code == DEGRADED
    assert "recording: at most 40 records lost (ticks 50..60, 0.22 s)" in result.text()
    assert "recording: stopped at tick 50" in result.text()
    assert decide(summary(estop_tick=25, stop_reason="e-stop at tick 25")).code == DEGRADED


def test_lost_records_of_the_last_batch_end_at_the_last_tick() -> None:
    """The manager's last batch carries the tick after the last one: not a tick of the run."""
    lost = RecordingReport(segments=["run.mcap"], lost_records=90, lost_ticks=(367, 400),
                           stopped_at_tick=367)  # fmt: skip
    text = decide(summary(recording=lost, dt_s=0.02)).text()
    assert "recording: at most 90 records lost (ticks 367..399, 0.66 s)" in text, text
    assert (
        "recording: stopped at tick 367; ticks 367..399 are not recorded, or only in part" in text
    ), text


def test_a_degraded_link_alone_degrades_the_run() -> None:
    result = decide(summary(degraded={"leader": [AgentEvent(40, "board link fault")]}))
    assert result.code == DEGRADED and not result.failures
    assert "agent leader degraded 1 times (ticks 40): board link fault" in result.text()


def test_a_restarted_recorder_that_lost_nothing_says_so() -> None:
    split = RecordingReport(
        segments=["run.mcap", "run.1.mcap"],
        failures=["killed by SIGKILL at tick 60; continued in run.1.mcap"],
    )
    result = decide(summary(recording=split))
    assert result.code == DEGRADED  # the recording is split: a script must know
    assert "recording: no record lost" in result.text()
    assert "recording in segments: run.mcap, run.1.mcap" in result.text()


def test_on_recording_failure_is_read_from_the_experiment() -> None:
    from types import SimpleNamespace

    from hilswarm.orchestrator.commands.run import on_recording_failure

    assert on_recording_failure(SimpleNamespace()) == "stop"  # the default
    assert on_recording_failure(SimpleNamespace(on_recording_failure="continue")) == "continue"


def test_stale_drops_alone_are_a_note() -> None:
    result = decide(summary(counters={"a": {"dropped": {"stale": 7}}}))
    assert result.code == CLEAN and "agent a: 7 dropped messages (stale=7)" in result.notes


def test_the_late_answers_of_a_large_swarm_fit_one_line() -> None:
    """48 agents late: the 8 with most late answers by name (ties in experiment order), the
    rest counted."""
    late = {f"r{i}": 1 + i % 5 for i in range(48)}  # r4, r9, ...: 5 each
    text = decide(summary(late=late, late_ticks=60)).text()
    line = next(line for line in text.splitlines() if "late answers:" in line)
    listed = line.split("late answers: ")[1]
    assert listed == (
        "r4=5, r9=5, r14=5, r19=5, r24=5, r29=5, r34=5, r39=5 "
        f"and {sum(late.values()) - 40} more from 40 other agents"
    )
    few = decide(summary(late={"b": 1, "a": 3}, late_ticks=4)).text()
    assert "late answers: b=1, a=3" in few  # up to 8 agents: all, in experiment order


def test_skipped_ticks_are_late_ticks_judged_by_max_late_fraction() -> None:
    """An agent that skipped a tick was late for it (its y never came): within the tolerance
    of late ticks a note, beyond it a degradation."""
    within = decide(summary(late={"a": 2}, late_ticks=2, counters={"a": {"skipped": 1}}))
    assert within.code == CLEAN
    assert within.notes[0] == "ticks skipped by agents that fell behind: a=1", within.notes
    beyond = decide(summary(late={"a": 6}, late_ticks=6, counters={"a": {"skipped": 1}}))
    assert beyond.code == DEGRADED  # 1.5 % > 1 %
    assert "ticks skipped by agents that fell behind: a=1" in beyond.degradations
    malformed = decide(summary(late={"a": 2}, late_ticks=2, counters={"a": {"skipped": 1,
                       "malformed": {"y": 1}}}))  # fmt: skip
    assert malformed.code == DEGRADED  # the other counters degrade as before


def test_the_summary_counts_late_ticks_as_run_in_ticks_and_speed() -> None:
    """99 of 100 ticks late at 50 Hz in 2 s: 100 ticks ran (99 late), about real time; not
    '1/100 ticks, 0.0x real time'."""
    run = summary(ticks=1, late_ticks=99, planned_ticks=100, wall_s=2.0, dt_s=0.02)
    assert run.ticks_run == 100
    assert run.speed == pytest.approx(1.0)
    assert run.text().startswith(
        "experiment 'toy' (realtime): 100/100 ticks (99 late) in 2.00 s wall clock (1.0x real time)"
    )
    never = decide(summary(ticks=0, late_ticks=100, planned_ticks=100, late={"a": 100}))
    assert never.code == FAILED and never.failures == ["no tick completed on time (100 late)"]
    clean = summary(wall_s=20.0, dt_s=0.05)
    assert clean.text().startswith("experiment 'toy' (realtime): 400/400 ticks in 20.00 s")


def test_agents_with_the_same_counters_share_a_line() -> None:
    """A large swarm's counters: agents with the same counters on one line, the skipped ticks
    of all agents on one line (most first)."""
    counters: dict[str, dict] = {f"r{i}": {"skipped": 1 + i % 3} for i in range(12)}
    for name in ("r2", "r5", "r7"):
        counters[name]["malformed"] = {"y": 1}
    counters["r9"]["link_faults"] = 2
    result = decide(summary(late={"r0": 14}, late_ticks=14, counters=counters))
    assert result.code == DEGRADED  # 3.5 % late: the skipped ticks degrade too
    assert result.degradations == [
        "agents r2, r5, r7: 1 malformed messages (y=1)",
        "agent r9: 2 link faults",
        "ticks skipped by agents that fell behind: r2=3, r5=3, r8=3, r11=3, r1=2, r4=2, r7=2, "
        "r10=2 and 4 more from 4 other agents",
        result.degradations[3],  # the late ticks' line
    ]

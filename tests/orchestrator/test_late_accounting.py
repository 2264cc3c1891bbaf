"""Late ticks of a self-clocked realtime run: an answer that came after the next tick was due
is late, however late the manager's ticking thread gets to close the tick (a busy machine)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.tick_window import TickWindow
from test_realtime_clock import manager, write

DT = 0.1  # the experiment's 10 Hz


def test_late_at_names_the_agents_not_in_by_the_deadline() -> None:
    window = TickWindow(3, 2)
    window.release(0, 0.0, 0.0)
    window.arrived[0, :2] = True
    window.answered_at[0, :2] = (0.004, 0.012)  # agent 2: no answer
    assert window.late_at(0.010) == [1, 2]
    assert window.late_at(0.012) == [2]  # on the deadline: in time
    window.lost[2] = True
    assert window.late_at(0.010) == [1]  # a lost agent is not late


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def answer(m: object, k: int, i: int, at: float) -> None:
    """What the manager's y callback stores for agent ``i``'s y_k received at ``at``."""
    tick = m._tick  # type: ignore[attr-defined]
    slot = k % tick.window
    tick.arrived[slot, i] = True
    tick.answered_at[slot, i] = at
    tick.count[slot] += 1


def test_an_answer_after_the_next_due_time_is_late_even_if_the_step_comes_later(
    tmp_path: Path,
) -> None:
    m = manager(load_experiment(write(tmp_path, "")), clock=time.monotonic)
    assert m.self_clocked
    clock = Clock()
    m._clock = clock  # the ticking thread's steps, driven by hand on a clock of the test's
    m._schedule = (0, 19, 0.0)  # T0 = 0: tick k due at k * DT
    m._step_k = 0
    m._clocked_step()  # at T0: ticks 0 and 1 open
    answer(m, 0, 0, 0.03)
    answer(m, 0, 1, DT + 0.002)  # 2 ms after tick 1 was due: the swarm ran tick 1 without it
    clock.now = DT + 0.005  # the step for tick 1 comes 5 ms late, both answers are in by then
    m._clocked_step()
    assert m.summary.late == {"a": 0, "b": 1}
    assert m.summary.ticks == 0
    # complete and late: in the summary's percentiles once, as infinite (the recorded
    # account keeps its completion, DT + 2 ms)
    assert np.isnan(m._completion[0])
    answer(m, 1, 0, DT + 0.01)
    answer(m, 1, 1, DT + 0.02)
    clock.now = 2 * DT + 0.001
    m._clocked_step()
    assert m.summary.late == {"a": 0, "b": 1} and m.summary.ticks == 1  # tick 1 on time
    assert np.isclose(m._completion[1], 0.02)

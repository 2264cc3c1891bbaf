"""The bare bus with an agent's tick work (``bare_bus.py --tick-work``): the floor of a fleet."""

from __future__ import annotations

import time
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from hilswarm.agents import bus


@pytest.fixture(scope="module")
def bare_bus(benchmarks_on_path: Path) -> ModuleType:
    """The bare-bus benchmark module."""
    import bare_bus

    return bare_bus


def test_the_tick_work_steps_a_frisbee_with_the_neighbours_heard(bare_bus: ModuleType) -> None:
    """Ring neighbours 3 and 1 become the case's two neighbours in order; a third index is
    nobody's; each tick answers with the Frisbee's real y message for that tick."""
    work = bare_bus.TickWork("frisbee", [3, 1])
    assert list(work.names) == [3, 1]
    assert all(values is None for values in work.neighbours.values())  # no data yet
    first, second = work.names[3], work.names[1]
    y0, report = work.tick(0, 0.0)
    k, t, values = bus.decode_vector(y0)
    assert (k, t) == (0, 0.0)
    assert values.size >= 3 and np.all(np.isfinite(values))
    assert report
    heard = np.array([1.0, 2.0, 0.5])
    work.heard(3, heard)
    work.heard(7, np.zeros(3))  # not a neighbour: ignored
    assert work.neighbours == {first: heard, second: None}
    k, t, _ = bus.decode_vector(work.tick(1, 0.01)[0])
    assert (k, t) == (1, 0.01)


def test_an_unknown_case_is_refused_before_anything_starts(bare_bus: ModuleType) -> None:
    with pytest.raises(ValueError, match="expected one of"):
        bare_bus.run_bare(n=2, rate_hz=100.0, seconds=0.1, lockstep=True, tick_work="blimp")


def test_a_lockstep_bare_bus_with_frisbee_work_completes_every_tick(
    bare_bus: ModuleType,
) -> None:
    """Three real client processes, each stepping a Frisbee in its callback: every tick
    completes, and the clients' CPU is measured."""
    result = bare_bus.run_bare(n=3, rate_hz=100.0, seconds=0.3, lockstep=True, tick_work="frisbee")
    assert result.ticks == 30
    assert result.completion_s.size == 30
    assert result.speed > 0
    assert result.client_cpu_s > 0
    line = bare_bus.describe(result, self_clocked=False, window=0, tick_work="frisbee")
    assert line.startswith("bare bus + frisbee tick work, lockstep barrier, 3 clients")


def test_spin_burns_at_least_the_cpu_time_asked(bare_bus: ModuleType) -> None:
    before = time.thread_time()
    bare_bus.spin(0.002)
    assert time.thread_time() - before >= 0.002


def test_a_negative_spin_is_refused_before_anything_starts(bare_bus: ModuleType) -> None:
    with pytest.raises(ValueError, match="CPU time >= 0"):
        bare_bus.run_bare(n=2, rate_hz=100.0, seconds=0.1, lockstep=True, spin_us=-1.0)


def test_a_lockstep_bare_bus_with_spin_completes_and_pays_for_it(bare_bus: ModuleType) -> None:
    """Three real client processes in the runtime's window pattern, each burning 300 µs of its
    CPU before each answer: every tick completes, and each client's CPU per tick holds the
    spin (a lower bound: the spin counts the thread's CPU time, not the wall clock)."""
    result = bare_bus.run_bare(n=3, rate_hz=100.0, seconds=0.3, lockstep=True, window=8,
                               spin_us=300.0)  # fmt: skip
    assert result.ticks == 30
    assert result.speed > 0
    assert result.client_cpu_s >= 300e-6
    line = bare_bus.describe(result, self_clocked=False, window=8, spin_us=300.0)
    assert line.startswith("bare bus + 300 µs spin, lockstep window 8, 3 clients")

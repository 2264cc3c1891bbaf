"""Late ticks of a self-clocked realtime run: an answer that came after the next tick was due
is late, however late the manager's ticking thread gets to close the tick (a busy machine)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents import bus
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.orchestrator import plotting
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.manager import InstanceManager
from hilswarm.orchestrator.plotting import load_recording
from hilswarm.orchestrator.recorder import Recorder
from hilswarm.orchestrator.stream_recorder import StreamRecorder
from hilswarm.orchestrator.tick_window import CLOSED_KEPT, TickWindow
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
    assert np.isnan(m._tally.completion[0])
    answer(m, 1, 0, DT + 0.01)
    answer(m, 1, 1, DT + 0.02)
    clock.now = 2 * DT + 0.001
    m._clocked_step()
    assert m.summary.late == {"a": 0, "b": 1} and m.summary.ticks == 1  # tick 1 on time
    assert np.isclose(m._tally.completion[1], 0.02)


def test_an_answer_after_its_tick_closed_is_timed_once_from_the_send() -> None:
    window = TickWindow(3, 2)
    window.release(0, 1.0, 1.002)  # scheduled at 1 s, sent 2 ms later
    window.arrived[0, 0] = True  # agent 0 answered in time; 1 and 2 did not
    window.lost[2] = True  # agent 2 is lost
    window.close_base()
    assert window.late_answer(0, 1, 1.05) == pytest.approx(0.048)  # from the send
    assert window.late_answer(0, 1, 1.06) is None  # once per agent and tick
    assert window.late_answer(0, 0, 1.05) is None  # it was in when the tick closed
    assert window.late_answer(0, 2, 1.05) is None  # lost: not waited for
    assert window.late_answer(1, 1, 1.05) is None  # tick 1 is not closed
    for k in range(1, CLOSED_KEPT + 1):  # tick 0 drops out of the ticks remembered
        window.release(k, float(k), float(k))
        window.close_base()
    assert window.late_answer(0, 1, 99.0) is None
    assert window.late_answer(CLOSED_KEPT, 1, CLOSED_KEPT + 0.5) == pytest.approx(0.5)


def test_an_answer_after_its_tick_closed_is_in_the_recorded_ledger(tmp_path: Path) -> None:
    """The real callbacks and ticking steps (on a test clock) into a real MCAP file: agent b's
    y_0 comes after tick 0 was closed without it; ``/orchestrator/late`` says when, with the
    times of its report."""
    experiment = load_experiment(write(tmp_path, ""))
    path = tmp_path / "run.mcap"
    start_ns = 1_000_000_000  # the file's log time is experiment time from here
    with Recorder(path, experiment, log_time_ns=start_ns) as recorder:
        m = InstanceManager(
            experiment,
            recorder=StreamRecorder(recorder, experiment),
            listen=[bus.loopback_endpoint(0)],
            clock=time.monotonic,
        )
        assert m.self_clocked and m._record_ticks
        clock = Clock()
        m._clock = clock
        m._schedule = (0, 19, 0.0)  # T0 = 0: tick k due at k * DT
        m._step_k = 0
        m._clocked_step()  # at T0: ticks 0 and 1 open
        on_y = [m._y_callback(0), m._y_callback(1)]
        clock.now = 0.004
        on_y[0](YSample(0, compute_s=0.001))
        clock.now = DT + 0.001
        m._clocked_step()  # tick 0 closes: b late, no answer
        clock.now = DT + 0.03  # b's y_0, 130 ms after tick 0 was due (and sent)
        on_y[1](YSample(0, compute_s=0.002, actuate_s=0.003, sense_s=0.004, link_s=0.005))
        on_y[1](YSample(0, compute_s=0.002))  # a duplicate: no second entry
        m._flush_records()
    ticks = [msg for _, _, msg in iter_messages(path, ["/orchestrator/ticks"])]
    assert ticks[0]["late"] == ["b"] and "b" not in ticks[0]["agents"]
    assert ticks[0]["agents"]["a"]["answer_s"] == pytest.approx(0.004)
    late = list(iter_messages(path, ["/orchestrator/late"]))
    assert len(late) == 1, late
    _, log_ns, entry = late[0]
    assert log_ns == start_ns  # at tick 0's experiment time, its wall time in the message
    assert isinstance(entry["wall_ns"], int)
    assert (entry["k"], entry["agent"]) == (0, "b")
    assert entry["answer_s"] == pytest.approx(DT + 0.03)
    assert entry["compute_s"] == pytest.approx(0.002) and entry["link_s"] == pytest.approx(0.005)
    assert entry["bus_s"] == pytest.approx(DT + 0.03 - 0.014)
    assert (entry["skipped"], entry["retries"]) == (0, 0)
    # hilswarm plot: tick 0 counted late and drawn when its last answer came; b's late
    # answer in the ledger figure's rows
    data = load_recording(path)
    assert plotting.late_tick_completions(data.ticks, data.late) == {0: pytest.approx(DT + 0.03)}
    t_b, parts_b = plotting.tick_ledger(data.ticks, data.late)["b"]
    assert t_b.tolist() == [0.0]
    assert parts_b[0, [key for key, _ in plotting.LEDGER_PARTS].index("link_s")] == 0.005
    written = plotting.plot_recording(path, tmp_path / "plots", latency=True)
    assert {p.name for p in written} >= {"ticks.png", "latency.png"}


class YSample:
    """What the manager's y callback reads of a Zenoh sample: y_k with its tick report."""

    def __init__(self, k: int, **timing: float) -> None:
        self.payload = _Bytes(bus.encode_vector(k, k * DT, np.zeros(1)))
        report = bus.encode_report(bus.AgentTiming(**timing), None, None)  # type: ignore[arg-type]
        self.attachment = _Bytes(report)


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data

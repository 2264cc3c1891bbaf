"""When the manager hands its records to the recorder in a realtime run: as a tick completes
(the swarm idle until its next tick), once per flush period, not at a tick's due time."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from hilswarm.agents import bus
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.manager import InstanceManager
from test_late_accounting import Clock
from test_realtime_clock import write

DT = 0.01  # 100 Hz
FLUSH_S = 0.02  # the manager's default flush period


class Sink:
    """A record sink that notes when each batch came and how many records it held."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.batches: list[tuple[float, int]] = []

    def write(
        self,
        data: bytes,
        *,
        seq: int,
        count: int = 0,
        tick: int = -1,
        first_tick: int = -1,
        defines: bool = False,
    ) -> None:
        self.batches.append((self.clock.now, count))


class Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class Sample:
    """What the manager's y callback reads of a Zenoh sample."""

    def __init__(self, k: int) -> None:
        self.payload = Payload(bus.encode_vector(k, k * DT, np.zeros(1)))
        self.attachment = None


def rig(tmp_path: Path, *, record: bool) -> tuple[InstanceManager, Clock, Sink]:
    experiment = load_experiment(write(tmp_path, ""), overrides={"rate_hz": 1 / DT})
    clock = Clock()
    sink = Sink(clock)
    m = InstanceManager(
        experiment,
        recorder=sink if record else None,
        listen=[bus.loopback_endpoint(0)],
        clock=time.monotonic,
        record_ticks=False,
    )
    assert m.self_clocked and m.dt == DT
    m._clock = clock  # the ticking thread's steps and the callbacks' stamps on the test's clock
    m._schedule = (0, m.experiment.n_ticks - 1, 0.0)
    m._step_k = 0
    return m, clock, sink


def answer_tick(m: InstanceManager, clock: Clock, k: int, at: tuple[float, float]) -> list[int]:
    """Both agents answer tick ``k`` at times ``at``; the completions the callbacks announce."""
    callbacks = [m._y_callback(0), m._y_callback(1)]
    for callback, when in zip(callbacks, at, strict=True):
        clock.now = when
        callback(Sample(k))  # type: ignore[arg-type]
    announced = []
    while not m._events.empty():
        item = m._events.get_nowait()
        announced.append(item[1])
        m._handle(item)
    return announced


def test_a_realtime_batch_goes_when_a_tick_completes_once_per_flush_period(
    tmp_path: Path,
) -> None:
    m, clock, sink = rig(tmp_path, record=True)
    m._clocked_step()  # T0 = 0: ticks 0 and 1 open
    assert answer_tick(m, clock, 0, (0.002, 0.003)) == [0]
    assert sink.batches == [(0.003, 2)]  # the two y records, as tick 0 completed
    clock.now = DT
    m._clocked_step()
    # tick 1 completes 10 ms after the batch: the next is due 20 ms after it, not carried yet
    assert answer_tick(m, clock, 1, (DT + 0.002, DT + 0.003)) == []
    clock.now = 2 * DT
    m._clocked_step()
    # tick 2 completes 20 ms after the batch (from half a period before it is due): it goes
    assert answer_tick(m, clock, 2, (2 * DT + 0.001, 2 * DT + 0.002)) == [2]
    assert sink.batches == [(0.003, 2), (2 * DT + 0.002, 4)]


def test_without_a_recorder_no_completion_is_announced(tmp_path: Path) -> None:
    m, clock, _sink = rig(tmp_path, record=False)
    m._clocked_step()
    assert answer_tick(m, clock, 0, (0.002, 0.003)) == []

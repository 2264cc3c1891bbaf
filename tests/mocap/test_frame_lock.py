"""The frame lock (orchestrator/frame_lock.py): the frame phase estimate and the tick schedule,
with closed-form and seeded frame sequences (times passed in; no clock, no process)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.orchestrator.experiment import parse_experiment
from hilswarm.orchestrator.frame_lock import (
    ACQUIRE_FRAMES,
    JUMP_FRAMES,
    FrameLock,
    TickClock,
    default_timeout_s,
)

P100 = 0.01  # 100 Hz frames [s]
P240 = 1.0 / 240.0


def feed(lock: FrameLock, numbers, frame_times, arrivals) -> None:
    for n, f, a in zip(numbers, frame_times, arrivals, strict=True):
        lock.on_frame(int(n), float(f), float(a))


def test_exact_frames_lock_after_acquisition_at_their_arrival() -> None:
    lock = FrameLock(P100)
    phase, delivery = 3.0004, 0.0007  # frame n at phase + n P on its clock, 0.7 ms to us
    for n in range(ACQUIRE_FRAMES):
        f = phase + n * P100
        assert not lock.locked(f + delivery)
        lock.on_frame(1000 + n, f, f + delivery)
    now = phase + (ACQUIRE_FRAMES - 1) * P100 + delivery
    assert lock.locked(now)
    assert lock.offset_s == pytest.approx(delivery, abs=1e-12)
    # The next frame arrives one period after the last one; a time on a frame is that frame.
    assert lock.next_frame(now + 1e-6) == pytest.approx(now + P100, abs=1e-9)
    assert lock.next_frame(now + P100) == pytest.approx(now + P100, abs=1e-9)
    assert lock.next_frame(now + 5.5 * P100) == pytest.approx(now + 6 * P100, abs=1e-9)


def test_jittered_frames_give_the_grid_of_the_earliest_ones() -> None:
    """Frames built and delivered late by a seeded exponential jitter (mean 0.5 / 1 ms): the
    estimate is the true grid plus the quickest delivery, a little late (the minima rise by the
    leak, 4 us per frame, between the rare frames near the minimum: about sqrt(4 us x mean
    jitter) each, ~0.1 ms here), never early."""
    rng = np.random.default_rng(7)
    n = np.arange(2000)
    grid = 10.0 + n * P240
    frame_times = grid + rng.exponential(0.5e-3, n.size)
    arrivals = frame_times + 0.3e-3 + rng.exponential(1e-3, n.size)
    lock = FrameLock(P240)
    feed(lock, n, frame_times, arrivals)
    now = arrivals[-1]
    assert lock.locked(now)
    expected = grid[-1] + 0.3e-3 + P240  # the next frame at its quickest
    error = lock.next_frame(grid[-1] + 0.3e-3 + P240 / 2) - expected
    assert 0.0 <= error < 0.3e-3, error
    frames, mean, top = lock.take_stats()
    assert frames > 1900
    assert mean == pytest.approx(0.5e-3, rel=0.2)  # the frames' jitter about the grid
    assert top < 0.5 * P240
    assert lock.take_stats()[0] == 0  # counting starts again


def test_one_late_frame_does_not_move_the_estimate() -> None:
    lock = FrameLock(P100)
    for n in range(100):
        late = 0.02 if n == 50 else 0.0  # delayed by two periods (a stalled process)
        f = 1.0 + n * P100
        lock.on_frame(n, f, f + 0.001 + late)
    assert lock.next_frame(1.0 + 100 * P100) == pytest.approx(1.001 + 100 * P100, abs=1e-6)


def test_a_drifting_frame_clock_is_followed() -> None:
    """The system's frames 100 ppm slower than nominal (a real system's crystal against the
    host's): after 60 s (6000 frames, 6 ms of drift) the estimate still holds the grid."""
    rng = np.random.default_rng(3)
    true_period = P100 * (1 + 1e-4)
    n = np.arange(6000)
    grid = 5.0 + n * true_period
    frame_times = grid + rng.exponential(0.3e-3, n.size)
    lock = FrameLock(P100)
    feed(lock, n, frame_times, frame_times + 0.5e-3)
    predicted = lock.next_frame(grid[-1] + 0.5e-3 + P100 / 2) - 0.5e-3
    assert predicted == pytest.approx(grid[-1] + true_period, abs=0.2e-3)


def test_no_frames_unlocks_and_new_frames_lock_to_their_own_phase() -> None:
    lock = FrameLock(P100)
    for n in range(50):
        lock.on_frame(n, n * P100, n * P100 + 0.001)
    last = 49 * P100 + 0.001
    assert lock.timeout_s == pytest.approx(default_timeout_s(P100))
    assert lock.locked(last + lock.timeout_s - 1e-6)
    assert not lock.locked(last + lock.timeout_s + 1e-6)  # no frames: free at once
    # The server comes back 2 s later with another phase and other numbers.
    start, restarts = 2.0037, lock.restarts
    for n in range(ACQUIRE_FRAMES):
        assert not lock.locked(start + n * P100 + 0.001)
        lock.on_frame(7 + n, start + n * P100, start + n * P100 + 0.001)
    assert lock.restarts == restarts + 1
    now = start + (ACQUIRE_FRAMES - 1) * P100 + 0.001
    assert lock.locked(now)
    assert lock.next_frame(now + 1e-6) == pytest.approx(now + P100, abs=1e-9)


def test_a_phase_jump_without_a_gap_restarts_the_estimate() -> None:
    """Frames that keep coming half a period or more after the estimated grid (a restarted
    server, frames a client did not number): after JUMP_FRAMES the estimate follows them."""
    lock = FrameLock(P100)
    for n in range(100):
        lock.on_frame(n, n * P100, n * P100)
    shift = 0.6 * P100
    for n in range(100, 100 + JUMP_FRAMES + 20):
        lock.on_frame(n, n * P100 + shift, n * P100 + shift)
    t = 200 * P100
    assert lock.next_frame(t) == pytest.approx(t + shift, abs=1e-9)
    # An earlier phase is taken at once (a minimum).
    lock.on_frame(300, 300 * P100, 300 * P100)
    assert lock.next_frame(301 * P100 - 1e-6) == pytest.approx(301 * P100, abs=1e-9)


def locked_lock(period: float, phase: float, delivery: float = 0.0, frames: int = 50):
    lock = FrameLock(period)
    for n in range(frames):
        f = phase + n * period
        lock.on_frame(n, f, f + delivery)
    return lock, phase + (frames - 1) * period + delivery


@pytest.mark.parametrize(("frame_hz", "tick_hz"), [(100.0, 100.0), (200.0, 100.0), (100.0, 20.0)])
def test_integer_ratios_lock_exactly(frame_hz: float, tick_hz: float) -> None:
    period, dt, lag = 1.0 / frame_hz, 1.0 / tick_hz, 0.002
    lock, now = locked_lock(period, phase=0.00123, delivery=0.0004)
    clock = TickClock(dt, lock, lag)
    assert clock.enabled and clock.integer_ratio
    clock.start(now + 0.05)
    dues = []
    for k in range(50):
        # frames keep coming up to the tick (the lock holds)
        while now < clock.t0 + k * dt:
            now += period
            lock.on_frame(round((now - 0.00123 - 0.0004) / period), now - 0.0004, now)
        dues.append(clock.due(k, now))
        assert clock.locked
        clock.released()
    dues = np.array(dues)
    frames = 0.00123 + 0.0004 + np.round((dues - lag - 0.00123 - 0.0004) / period) * period
    np.testing.assert_allclose(dues, frames + lag, atol=1e-9)  # on a frame, plus the lag
    np.testing.assert_allclose(np.diff(dues), dt, atol=1e-9)  # every tick one period apart
    # the grid is half a frame before each tick's frame: estimation noise cannot flip it
    grid = clock.t0 + np.arange(50) * dt
    np.testing.assert_allclose(dues - lag - grid, period / 2, atol=1e-9)
    assert (clock.ticks_locked, clock.ticks_free) == (50, 0)


def test_240_over_100_ticks_sit_on_frames_and_jitter_within_one_frame() -> None:
    period, dt, lag = P240, 0.01, 0.001
    lock, now = locked_lock(period, phase=0.0002)
    clock = TickClock(dt, lock, lag)
    assert clock.enabled and not clock.integer_ratio
    clock.start(now)
    dues = []
    for k in range(60):
        while now < clock.t0 + k * dt + period:
            now += period
            lock.on_frame(round((now - 0.0002) / period), now, now)
        dues.append(clock.due(k, now))
    dues = np.array(dues)
    on_frame = (dues - lag - 0.0002) / period
    np.testing.assert_allclose(on_frame, np.round(on_frame), atol=1e-6)
    steps = np.diff(dues)
    assert np.all(np.abs(steps - dt) < period + 1e-9), steps
    # experiment time stays k dt: the mean period is dt
    assert (dues[-1] - dues[0]) / 59 == pytest.approx(dt, abs=period / 59 + 1e-9)
    grid = clock.t0 + np.arange(60) * dt
    assert np.all((dues - lag >= grid - 1e-12) & (dues - lag < grid + period))


def test_free_without_frames_and_back_on_the_grid_at_once() -> None:
    dt = 0.05
    assert TickClock(dt).due(3, 0.0) == pytest.approx(3 * dt)  # no lock: the free grid
    lock, now = locked_lock(P100, phase=0.0)
    clock = TickClock(dt, lock, 0.002)
    clock.start(now)
    locked_due = clock.due(1, now)
    assert clock.locked
    assert clock.due(1, now + 0.001) == locked_due  # once per tick
    # Frames stop: as soon as the lock times out the due time is the free grid point.
    late = now + lock.timeout_s + 1e-6
    due = clock.due(1, late)
    assert not clock.locked and due == pytest.approx(clock.t0 + dt)
    clock.released()
    assert (clock.ticks_locked, clock.ticks_free) == (0, 1)


def test_resume_and_ticks_faster_than_frames() -> None:
    lock, now = locked_lock(P100, phase=0.0)
    clock = TickClock(0.05, lock, 0.001)
    clock.reanchor(now, 40)  # resume: tick 41 one period after now, then on its frame
    due = clock.due(41, now)
    assert now + 0.05 - 1e-9 <= due - 0.001 <= now + 0.05 + P100 + 1e-9
    fast = TickClock(0.005, lock, 0.001)  # 200 Hz ticks, 100 Hz frames: never locked
    assert not fast.enabled
    fast.start(0.0)
    assert fast.due(2, now) == pytest.approx(0.01) and not fast.locked


def test_bad_period() -> None:
    with pytest.raises(ValueError, match="frame period"):
        FrameLock(0.0)
    assert math.isnan(FrameLock(P100).take_stats()[1])


DEMO = (Path(__file__).resolve().parents[2] / "graphs" / "lead_follow_mocap.toml").read_text()


def demo_with(tmp_path: Path, lines: str) -> Path:
    assert "hold_frames = 50" in DEMO
    path = tmp_path / "experiment.toml"
    path.write_text(DEMO.replace("hold_frames = 50", f"{lines}\nhold_frames = 50", 1))
    return path


@pytest.mark.parametrize(
    ("lines", "reason"),
    [
        ("tick_lag_ms = 10.0", "not under one frame period (10 ms at rate_hz = 100)"),
        ("tick_lag_ms = -1.0", "out of range; expected tick_lag_ms >= 0"),
        ('tick_lag_ms = "2"', "number"),
        ("tick_lag_ms = true", "number"),
        ("tick_lock = 1", "is not true or false"),
        ("pose_wait_ms = 10.0", "not under one frame period (10 ms at rate_hz = 100)"),
        ("pose_wait_ms = -1.0", "out of range; expected pose_wait_ms >= 0"),
    ],
)
def test_the_schema_refuses_a_bad_lag(tmp_path: Path, lines: str, reason: str) -> None:
    _, problems = parse_experiment(demo_with(tmp_path, lines))
    key = "mocap." + lines.split(maxsplit=1)[0]
    assert any(p.key == key and reason in p.message for p in problems), problems


def test_the_lag_setting_and_its_default(tmp_path: Path) -> None:
    experiment, problems = parse_experiment(demo_with(tmp_path, "tick_lag_ms = 3.5"))
    assert not problems, problems
    assert experiment.mocap.tick_lag_s == pytest.approx(3.5e-3)
    assert experiment.mocap.tick_lock
    experiment, problems = parse_experiment(demo_with(tmp_path, "tick_lock = false"))
    assert not problems and not experiment.mocap.tick_lock
    assert experiment.mocap.tick_lag_s == pytest.approx(3e-3)  # 100 Hz: the default 3 ms
    fast = MocapSettings(system="sim", rate_hz=240.0)
    assert fast.tick_lag_s == pytest.approx(0.3 / 240.0)  # at most 0.3 of a frame period
    assert MocapSettings.from_dict(fast.to_dict()) == fast


def test_the_pose_wait_setting_and_its_default(tmp_path: Path) -> None:
    experiment, problems = parse_experiment(demo_with(tmp_path, "pose_wait_ms = 5.0"))
    assert not problems, problems
    assert experiment.mocap.pose_wait_s == pytest.approx(5e-3)
    experiment, problems = parse_experiment(demo_with(tmp_path, "tick_lag_ms = 2.0"))
    assert not problems and experiment.mocap.pose_wait_s == 0.0  # the default: no wait
    unlocked = "pose_wait_ms = 5.0\ntick_lock = false"
    experiment, problems = parse_experiment(demo_with(tmp_path, unlocked))
    assert not problems and experiment.mocap.pose_wait_s == 0.0  # only with locked ticks


def test_the_spread_setting_gives_each_agent_its_phase(tmp_path: Path) -> None:
    """``tick_spread_frames``: agent i (graph order) ticks (i mod N) frame periods late."""
    experiment, problems = parse_experiment(demo_with(tmp_path, "tick_spread_frames = 2"))
    assert not problems, problems
    mocap = experiment.mocap
    assert mocap.tick_spread_frames == 2
    assert [mocap.tick_phase_s(i) for i in range(4)] == pytest.approx([0, 0.01, 0, 0.01])
    assert MocapSettings.from_dict(mocap.to_dict()) == mocap
    experiment, problems = parse_experiment(demo_with(tmp_path, "tick_lag_ms = 2.0"))
    assert not problems and experiment.mocap.tick_spread_frames == 1  # the default: none
    assert experiment.mocap.tick_phase_s(5) == 0.0
    unlocked = MocapSettings(system="sim", tick_lock=False, tick_spread_frames=3)
    assert unlocked.tick_phase_s(1) == 0.0


@pytest.mark.parametrize(
    ("lines", "reason"),
    [
        # 100 Hz frames, 20 Hz control: 5 frames per period, a spread of at most 4
        ("tick_spread_frames = 5", "5 frames (50 ms at [mocap] rate_hz = 100) do not fit in "
                                   "one control period (50 ms at rate_hz = 20); at most 4"),
        ("tick_spread_frames = 0", "out of range; expected tick_spread_frames >= 1"),
        ("tick_spread_frames = 2\ntick_lock = false", "needs tick_lock = true"),
        ("tick_spread_frames = 2\ntick_frames_only = true", "does not go with tick_frames_only"),
    ],
)  # fmt: skip
def test_a_spread_that_cannot_work_is_refused(tmp_path: Path, lines: str, reason: str) -> None:
    _, problems = parse_experiment(demo_with(tmp_path, lines))
    assert any(p.key == "mocap.tick_spread_frames" and reason in p.message for p in problems), (
        problems
    )
    fits, problems = parse_experiment(demo_with(tmp_path, "tick_spread_frames = 4"))
    assert not problems and fits.mocap.tick_spread_frames == 4

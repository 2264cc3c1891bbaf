"""The mocap process on a real Zenoh bus: poses to the agent's pose source, occlusion hold ->
"lost tracking", and the server's loss reported with no stale pose used.

A router session on a free loopback port stands in for the orchestrator's; the simulator and
the real client (qtm-rt) run in this process on threads; every wait is bounded.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.control import Controller, ControlModel, TickInput
from hilswarm.agents.mocap import message
from hilswarm.agents.mocap.clients import QualisysClient
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.agents.mocap.pose_source import MocapPoseSource
from hilswarm.agents.mocap.process import MocapProcess
from hilswarm.agents.mocap.qtm_sim import QtmSimulator, SimSettings
from hilswarm.agents.telemetry import Telemetry

EXPERIMENT = "mocap_bus"
TIMEOUT_S = 30.0


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


@pytest.fixture
def router() -> Iterator[list[str]]:
    session = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
    endpoints = bus.bound_endpoints(session)  # the free port the router bound
    try:
        yield endpoints
    finally:
        session.close()


class Rig:
    """Simulator + mocap process (thread) + one agent-side pose source, on one bus."""

    def __init__(
        self,
        endpoints: list[str],
        sim: SimSettings,
        *,
        hold_frames: int,
        neighbours: dict[str, str] | None = None,
        pose_wait_s: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
        tick_frames_only: bool = False,
        tick_spread_frames: int = 1,
    ) -> None:
        self.sim = QtmSimulator(sim)
        self.sim.start()
        settings = MocapSettings(
            system="sim", rate_hz=sim.rate_hz, hold_frames=hold_frames,
            tick_frames_only=tick_frames_only, tick_spread_frames=tick_spread_frames,
        )  # fmt: skip
        self.process = MocapProcess(
            settings, EXPERIMENT, sim.bodies, endpoints,
            client=QualisysClient("127.0.0.1", self.sim.port),
        )  # fmt: skip
        self.exit_code: list[int] = []
        self.thread = threading.Thread(
            target=lambda: self.exit_code.append(self.process.run()), daemon=True
        )
        self.thread.start()
        self.session = bus.open_session(bus.client_config(endpoints))
        self.lost: list[str] = []
        self.source = MocapPoseSource(
            sim.bodies[0], hold_frames=hold_frames, hold_s=settings.hold_s,
            start_timeout_s=10.0, on_lost=self.lost.append,
            frame_period_s=1.0 / sim.rate_hz, pose_wait_s=pose_wait_s, clock=clock,
        )  # fmt: skip
        self.source.neighbours = dict(neighbours or {})
        self.telemetry = Telemetry()
        self.source.add_telemetry(self.telemetry)
        self.entities = self.source.attach_bus(self.session, bus.BusKeys(EXPERIMENT))

    def close(self) -> None:
        self.process.stop()
        self.thread.join(10.0)
        self.sim.close()
        self.entities.clear()
        self.session.close()


def test_poses_reach_the_agent_filtered_in_the_world_frame(router: list[str]) -> None:
    rig = Rig(router, SimSettings(bodies=("f1", "f2"), rate_hz=100.0), hold_frames=5)
    try:
        truth = np.array([0.5, -0.25, 0.0, 0.0, 0.0, 1.0])
        rig.sim.set_truth("f1", truth)
        rig.sim.set_truth("f2", truth + 1.0)
        rig.source.wait_first()
        wait_for(lambda: np.allclose(rig.source.pose(), truth, atol=1e-4), "the filtered pose")
        rig.source.record(0, 0.0)
        row = rig.telemetry["mocap"]
        assert len(row) == 1
        assert not rig.lost
        # The process publishes exactly the bodies it was given, each on its own key.
        got: list[bytes] = []
        sub = rig.session.declare_subscriber(
            bus.BusKeys(EXPERIMENT).mocap("f2"),
            zenoh.handlers.Callback(lambda s: got.append(s.payload.to_bytes()), indirect=False),
        )
        wait_for(lambda: len(got) >= 3, "f2's poses")
        np.testing.assert_allclose(message.decode(got[-1]).pose, truth + 1.0, atol=1e-4)
        del sub
    finally:
        rig.close()


def test_an_occlusion_longer_than_the_hold_means_lost_tracking(router: list[str]) -> None:
    sim = SimSettings(bodies=("f1",), rate_hz=100.0, occlusions={"f1": (0.5, 10.0)})
    rig = Rig(router, sim, hold_frames=10)
    try:
        rig.sim.set_truth("f1", np.zeros(6))
        rig.source.wait_first()
        occluded_but_held = []

        def lost() -> bool:
            pose = rig.source.pose()
            latest = rig.source._latest
            if np.all(np.isfinite(pose)) and latest is not None and latest[0].occluded:
                occluded_but_held.append(latest[0].occluded)
            return not np.all(np.isfinite(pose))

        wait_for(lost, "tracking to be lost")
        assert rig.lost and rig.lost[0].startswith("lost tracking: body 'f1' not seen for")
        # Held while occluded for at most hold_frames frames (polled at least once in 0.1 s).
        assert occluded_but_held and max(occluded_but_held) <= 10
        assert np.all(np.isnan(rig.source.pose()))  # latched: no pose afterwards
        assert len(rig.lost) == 1
    finally:
        rig.close()


def test_the_server_lost_is_reported_and_no_stale_pose_is_used(router: list[str]) -> None:
    rig = Rig(router, SimSettings(bodies=("f1",), rate_hz=100.0), hold_frames=50)
    try:
        rig.sim.set_truth("f1", np.ones(6) * 0.1)
        rig.source.wait_first()
        assert np.all(np.isfinite(rig.source.pose()))
        rig.sim.close()  # the mocap server disappears
        wait_for(lambda: bool(rig.exit_code), "the mocap process to end")
        assert rig.exit_code == [1]
        wait_for(lambda: not np.all(np.isfinite(rig.source.pose())), "the pose to be refused")
        assert "mocap server lost" in rig.lost[0]
    finally:
        rig.close()


def test_a_body_never_seen_is_named_with_the_visible_ones(router: list[str]) -> None:
    rig = Rig(router, SimSettings(bodies=("ghost", "f2"), rate_hz=100.0), hold_frames=5)
    rig.source.start_timeout_s = 1.5
    try:
        rig.sim.set_truth("f2", np.zeros(6))
        wait_for(lambda: rig.source._status.get("visible") == ["f2"], "the status")
        with pytest.raises(LookupError, match=r"'ghost' is not visible .* sees: f2"):
            rig.source.wait_first()
    finally:
        rig.close()


class PoseReader(Controller):
    """Returns the x of its neighbour ``n2``'s mocap pose as u (NaN-free: 0 while lost)."""

    uses_neighbour_poses = True

    def step(self, tick: TickInput, x_hat: np.ndarray, params: object) -> tuple:
        pose = tick.neighbour_poses.get("n2")
        return np.array([0.0 if pose is None else pose[0]]), x_hat


def test_a_controller_that_asks_gets_its_neighbours_poses(router: list[str]) -> None:
    sim = SimSettings(bodies=("f1", "f2", "f3"), rate_hz=100.0)
    rig = Rig(router, sim, hold_frames=5, neighbours={"n2": "f2"})
    try:
        rig.sim.set_truth("f1", np.zeros(6))
        rig.sim.set_truth("f2", np.array([0.75, 0.5, 0.0, 0.0, 0.0, 0.25]))
        rig.sim.set_truth("f3", np.ones(6))
        rig.source.wait_first()
        model = ControlModel(PoseReader(), dt=0.05, n_inputs=1, n_outputs=1)
        model.neighbour_poses = rig.source.neighbour_poses
        wait_for(lambda: rig.source.neighbour_poses()["n2"] is not None, "the neighbour's pose")
        assert set(rig.source.neighbour_poses()) == {"n2"}  # only the neighbour it was given
        u = model.step(np.zeros(1), np.zeros(1))
        assert u[0] == pytest.approx(0.75, abs=1e-4)
    finally:
        rig.close()


def test_a_sense_waits_bounded_for_an_overdue_pose(router: list[str]) -> None:
    """``pose_wait_s``: a sense whose newest pose arrived over one frame period ago (the next
    frame's is overdue) waits for it (and gets it), at most ``pose_wait_s``; one whose newest
    pose is younger than a period never waits, even past half of it; with no
    frame coming it gives up at the bound and uses the newest pose it has.

    The source's clock is this machine's plus an offset the test sets: its poses' arrival
    stamps and its "now" both move with it, so the age a sense sees is set exactly."""
    period, bound = 0.1, 0.08  # 10 Hz frames
    offset = [0.0]
    rig = Rig(
        router, SimSettings(bodies=("f1",), rate_hz=10.0), hold_frames=50, pose_wait_s=bound,
        clock=lambda: time.monotonic() + offset[0],
    )  # fmt: skip
    source = rig.source

    def seen_age(age: float) -> None:  # the newest pose looks ``age`` [s] old from now on
        offset[0] += age - (source._clock() - source._latest[1])

    def newest_is_old() -> bool:  # over half a period, really: the next frame is near
        latest = source._latest
        return latest is not None and source._clock() - latest[1] > 0.5 * period

    try:
        rig.sim.set_truth("f1", np.zeros(6))
        source.wait_first()

        # Younger than a period but over half of one (0.6 periods; the rule before waited
        # then): no wait, the newest pose is used.
        wait_for(newest_is_old, "the newest pose to be over half a frame period old")
        frame = source._latest[0].frame
        seen_age(0.6 * period)
        assert np.all(np.isfinite(source.pose()))
        assert source.pose_waits == source.pose_wait_timeouts == 0
        source.record(0, 0.0)
        assert rig.telemetry["mocap"].field("pose_wait_s")[-1] == 0.0
        assert rig.telemetry["mocap"].field("frame")[-1] >= frame

        # Over a period old: the next frame's pose is overdue; the sense waits and gets it.
        wait_for(newest_is_old, "the newest pose to be over half a frame period old")
        frame = source._latest[0].frame
        seen_age(1.2 * period)
        assert np.all(np.isfinite(source.pose()))
        assert source._latest[0].frame > frame  # it waited for the next frame's pose
        assert source.pose_waits == 1 and source.pose_wait_timeouts == 0
        source.record(1, 0.1)
        waited = rig.telemetry["mocap"].field("pose_wait_s")[-1]  # that sense's wait [s]
        assert 0.0 < waited <= bound + 0.05  # bounded (the slack: a loaded machine's wake-up)

        rig.process.stop()  # no more frames: a sense gives up at the bound
        rig.thread.join(10.0)
        seen_age(1.2 * period)
        began = time.monotonic()
        assert np.all(np.isfinite(source.pose()))  # within hold_s: the newest pose, held
        assert time.monotonic() - began >= bound
        assert source.pose_wait_timeouts == 1
        assert not rig.lost
    finally:
        rig.close()


def test_a_sense_told_its_ticks_due_time_waits_for_that_frames_pose(router: list[str]) -> None:
    """A self-clocked tick (``tick_due``): the sense waits exactly when the newest pose reached
    the mocap process over half a frame period before the tick's frame did (due minus the
    lag), whatever the arrival times; at most ``pose_wait_s``; each hint is for one sense."""
    period, bound = 0.1, 0.35  # 10 Hz frames; a bound over the frames the test waits for
    rig = Rig(router, SimSettings(bodies=("f1",), rate_hz=10.0), hold_frames=50,
              pose_wait_s=bound)  # fmt: skip
    source = rig.source
    source.tick_lag_s = 0.02
    try:
        rig.sim.set_truth("f1", np.zeros(6))
        source.wait_first()
        newest = source._latest[0]
        # The tick of the newest frame (its pose reached the mocap process then): no wait.
        source.tick_due(newest.received_s + source.tick_lag_s)
        assert np.all(np.isfinite(source.pose()))
        assert source.pose_waits == source.pose_wait_timeouts == 0
        # The tick of the frame after next: its pose is not in yet; the sense waits for it.
        newest = source._latest[0]
        source.tick_due(newest.received_s + 2 * period + source.tick_lag_s)
        assert np.all(np.isfinite(source.pose()))
        assert source.pose_waits == 1 and source.pose_wait_timeouts == 0
        used = source._latest[0]
        assert used.frame >= newest.frame + 2
        assert used.received_s >= newest.received_s + 1.5 * period
        source.record(0, 0.0)
        assert 0.0 < rig.telemetry["mocap"].field("pose_wait_s")[-1] <= bound + 0.05
        # No hint (a tick message's tick): the arrival rule, and the newest pose is young.
        assert np.all(np.isfinite(source.pose())) and source.pose_waits == 1

        rig.process.stop()  # no more frames: the told sense gives up at the bound
        rig.thread.join(10.0)
        source.tick_due(source._latest[0].received_s + period + source.tick_lag_s)
        began = time.monotonic()
        assert np.all(np.isfinite(source.pose()))  # within hold_s: the newest pose, held
        assert time.monotonic() - began >= bound
        assert source.pose_wait_timeouts == 1 and not rig.lost
    finally:
        rig.close()


def test_with_a_schedule_only_the_ticks_frames_and_a_keep_alive_are_published(
    router: list[str], caplog: pytest.LogCaptureFixture
) -> None:
    """``tick_frames_only``: given the manager's schedule of a self-clocked run on the tick
    key, the process publishes the frames its ticks use (the last one before a tick's due
    time and the one before it) and at least every ``hold_frames // 2``-th frame; a tick
    message (a run driven by them) brings every frame back. Frames from the real simulator
    through qtm-rt."""
    rate, hold = 100.0, 10
    period, keep_alive = 1 / rate, hold // 2
    rig = Rig(
        router, SimSettings(bodies=("f1",), rate_hz=rate), hold_frames=hold,
        tick_frames_only=True,
    )  # fmt: skip
    keys = bus.BusKeys(EXPERIMENT)
    got: list[message.BodyPose] = []
    sub = rig.session.declare_subscriber(
        keys.mocap("f1"),
        zenoh.handlers.Callback(lambda s: got.append(message.decode(s.payload.to_bytes()))),
    )
    tick_pub = rig.session.declare_publisher(keys.tick)
    try:
        rig.sim.set_truth("f1", np.zeros(6))
        rig.source.wait_first()
        wait_for(lambda: len(got) >= 5, "the first poses")
        assert consecutive([m.frame for m in got[-5:]], rig)  # no schedule: every frame
        # Ticks every 20 frames (5 Hz), each due 3 ms after a frame (the simulator stamps
        # frames with this host's clock, the one the schedule uses).
        dt, t0 = 20 * period, got[-1].frame_time_s + 0.003
        tick_pub.put(bus.encode_schedule(bus.ScheduleMessage(0, 10_000, t0, dt)))
        wait_for(lambda: rig.process.decimator.decimating, "the schedule to reach the process")
        start = len(got) + 2  # poses on their way when it came may follow
        wait_for(lambda: len(got) >= start + 30, "poses under the schedule (~5 ticks)")
        kept = got[start:]

        def for_a_tick(m: message.BodyPose) -> bool:  # the next tick is due within 2 frames
            due = t0 + math.ceil((m.frame_time_s - t0) / dt) * dt
            return due - m.frame_time_s < 2 * period

        # The others are the keep-alives: one in keep_alive frames.
        others = [m.frame for m in kept if not for_a_tick(m)]
        span = kept[-1].frame - kept[0].frame
        assert 1 <= len(others) <= span / keep_alive + 1, (others, span)
        gaps = [b.frame - a.frame for a, b in itertools.pairwise(kept)]
        # at most keep_alive frames apart (plus frames the process skipped if it fell behind);
        # a tick's two frames one apart
        assert max(gaps) <= keep_alive + rig.process.skipped and 1 in gaps, gaps
        assert rig.process.decimator.left_out > 0
        assert not rig.lost  # never counted lost while frames were left out
        # A tick message: a run driven by them gets every frame again.
        tick_pub.put(bus.encode_tick(bus.TickMessage(k=0, t=0.0, missing=(), realtime=True)))
        wait_for(lambda: rig.process.decimator.ticked, "the tick message to reach the process")
        wait_for(lambda: rig.process._tick_sub is None, "the process to stop hearing ticks")
        assert "tick_frames_only has no effect in this run" in caplog.text
        start = len(got) + 2
        wait_for(lambda: len(got) >= start + 12, "every frame again")
        assert consecutive([m.frame for m in got[start:]], rig)
    finally:
        del sub, tick_pub
        rig.close()


def test_by_default_every_frame_is_published_whatever_the_schedule(router: list[str]) -> None:
    rig = Rig(router, SimSettings(bodies=("f1",), rate_hz=100.0), hold_frames=10)
    keys = bus.BusKeys(EXPERIMENT)
    got: list[int] = []
    sub = rig.session.declare_subscriber(
        keys.mocap("f1"),
        zenoh.handlers.Callback(lambda s: got.append(message.decode(s.payload.to_bytes()).frame)),
    )
    tick_pub = rig.session.declare_publisher(keys.tick)
    try:
        rig.sim.set_truth("f1", np.zeros(6))
        rig.source.wait_first()
        wait_for(lambda: len(got) >= 2, "the first poses")
        t0 = time.monotonic() + 0.003
        tick_pub.put(bus.encode_schedule(bus.ScheduleMessage(0, 10_000, t0, 0.2)))
        start = len(got)
        wait_for(lambda: len(got) >= start + 40, "40 more poses")
        assert consecutive(got[start:], rig)
        assert rig.process.decimator.left_out == 0
    finally:
        del sub, tick_pub
        rig.close()


def test_with_a_spread_the_bodies_that_sense_at_a_frame_are_put_first(
    router: list[str],
) -> None:
    """``tick_spread_frames = 2``, four bodies (agents 0 and 2 at the swarm's due time, 1 and
    3 a frame later): given the schedule, the poses of the frame before each phase's senses
    come with that phase's bodies first; the other frames' in the bodies' own order. Frames
    from the real simulator through qtm-rt, on a real bus (one publisher session: its puts
    arrive in order)."""
    rate = 100.0
    period = 1 / rate
    bodies = ("f0", "f1", "f2", "f3")
    rig = Rig(
        router, SimSettings(bodies=bodies, rate_hz=rate), hold_frames=10, tick_spread_frames=2
    )
    keys = bus.BusKeys(EXPERIMENT)
    got: list[tuple[float, str]] = []  # (frame time, body) in arrival order
    sub = rig.session.declare_subscriber(
        f"{keys.prefix}/mocap/*",
        zenoh.handlers.Callback(
            lambda s: got.append(
                (message.decode(s.payload.to_bytes()).frame_time_s, str(s.key_expr))
            )
        ),
    )
    tick_pub = rig.session.declare_publisher(keys.tick)
    try:
        for body in bodies:
            rig.sim.set_truth(body, np.zeros(6))
        rig.source.wait_first()
        wait_for(lambda: len(got) >= 8, "the first poses")
        natural = [keys.mocap(b) for b in bodies]
        assert [b for _, b in got[-4:]] == natural  # no schedule: the bodies' own order
        # Ticks every 6 frames, each due 3 ms after a frame (the simulator stamps frames with
        # this host's clock, the one the schedule uses).
        dt, t0 = 6 * period, got[-1][0] + 0.003
        tick_pub.put(bus.encode_schedule(bus.ScheduleMessage(0, 10_000, t0, dt)))
        wait_for(lambda: rig.process.put_order.schedule is not None, "the schedule")
        start = len(got) + 8  # poses on their way when it came may follow
        wait_for(lambda: len(got) >= start + 4 * 24, "24 more frames")
        frames: dict[float, list[str]] = {}
        for time_s, body in got[start:]:
            frames.setdefault(time_s, []).append(body)
        seen = {0: 0, 1: 0, None: 0}
        for time_s, order in frames.items():
            if len(order) < 4:
                continue  # the last frame, still arriving
            phase = next((p for p in (0, 1) if (t0 + p * period - time_s) % dt < period), None)
            first = {0: ["f0", "f2"], 1: ["f1", "f3"], None: ["f0", "f1"]}[phase]
            assert order[:2] == [keys.mocap(b) for b in first], (phase, order)
            assert sorted(order) == natural
            seen[phase] += 1
        assert seen[0] >= 2 and seen[1] >= 2 and seen[None] >= 6, seen
    finally:
        del sub, tick_pub
        rig.close()


def consecutive(numbers: list[int], rig: Rig) -> bool:
    """Every frame's pose in ``numbers`` (frame numbers, in order), but for frames the mocap
    process skipped because it fell behind (a loaded machine)."""
    gaps = [b - a for a, b in itertools.pairwise(numbers)]
    return all(1 <= gap <= 1 + rig.process.skipped for gap in gaps)

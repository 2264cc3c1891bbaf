"""Malformed mocap pose messages are dropped and counted, never used and never fatal.

At the pose source's level on a real Zenoh bus (a router session on a free loopback port, a
publishing client session standing in for the mocap process), and end to end: garbage put on
a robot's body key during an ``--insecure`` ``hilswarm run`` of the mocap demo shows in its
agent's status counters (``malformed["mocap"]``) and in the run summary.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.mocap import message
from hilswarm.agents.mocap.pose_source import MocapPoseSource

# The integration tests' harness (a `hilswarm run` process, a spy session on its bus).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))
from swarm_harness import REPO, RunProcess, connect_spy, read_recording

EXPERIMENT = "mocap_malformed"
TIMEOUT_S = 30.0
#: Payloads that are no pose message: empty, short, one byte too long, JSON.
GARBAGE = (b"", b"\x01\x02\x03", b"\x00" * (message.SIZE + 1), b'{"x": 1.0}')


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


def pose_message(frame: int, x: float) -> bytes:
    """A well-formed pose message: body seen at ``[x, 0, 0]`` (world frame), heading 0."""
    pose = [x, 0.0, 0.0, 0.0, 0.0, 0.0]
    values = [*pose, *pose, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    return message.encode_row(frame, 0.0, time.monotonic(), 0.0, occluded=0, values=values)


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """A router on a free loopback port and a client session on it (the publisher)."""
    router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
    try:
        publisher = bus.open_session(bus.client_config(bus.bound_endpoints(router)))
        try:
            yield router, publisher
        finally:
            publisher.close()
    finally:
        router.close()


def test_malformed_poses_are_counted_and_never_used(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    router, publisher = sessions
    keys = bus.BusKeys(EXPERIMENT)
    calls: list[int] = []
    source = MocapPoseSource("f1", hold_frames=5, hold_s=60.0, start_timeout_s=10.0)
    source.neighbours = {"n2": "f2"}
    source.on_malformed = lambda: calls.append(1)
    entities = source.attach_bus(router, keys)
    try:

        def put(key: str, payload: bytes) -> None:
            publisher.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

        def delivered(key: str, frame: int, x: float, seen: Callable[[], bool]) -> None:
            """Put a good pose until it arrives (the subscription reaches the publisher)."""
            deadline = time.monotonic() + TIMEOUT_S
            while not seen():
                if time.monotonic() > deadline:
                    raise AssertionError(f"pose frame {frame} on {key} never arrived")
                put(key, pose_message(frame, x))
                time.sleep(0.02)

        def own_at(x: float) -> Callable[[], bool]:
            return lambda: source._latest is not None and source._latest[0].pose[0] == x

        def neighbour_at(x: float) -> Callable[[], bool]:
            return lambda: (pose := source.neighbour_poses()["n2"]) is not None and pose[0] == x

        delivered(keys.mocap("f1"), 1, 0.5, own_at(0.5))
        delivered(keys.mocap("f2"), 1, 0.25, neighbour_at(0.25))
        for payload in GARBAGE:
            put(keys.mocap("f1"), payload)
            put(keys.mocap("f2"), payload)
        # In order from one publisher: once the next good poses are in, so is the garbage.
        delivered(keys.mocap("f1"), 2, 0.75, own_at(0.75))
        delivered(keys.mocap("f2"), 2, 0.5, neighbour_at(0.5))
        assert source.malformed == 2 * len(GARBAGE)
        assert len(calls) == 2 * len(GARBAGE)  # each one counted by the agent too
        # Never used: the newest good poses stand, tracking is not lost.
        np.testing.assert_array_equal(source.pose(), [0.75, 0.0, 0.0, 0.0, 0.0, 0.0])
        assert source.lost() is None
    finally:
        entities.clear()


@pytest.mark.integration
@pytest.mark.slow
def test_malformed_poses_show_in_the_agent_status_and_the_run_summary(tmp_path: Path) -> None:
    """Garbage on f1's body key (frisbee2) in an ``--insecure`` run (no router access control,
    so only the agent's own defence stands): counted as ``malformed["mocap"]``, the run still
    completes every tick, and the summary lists the count (exit status 3, degraded)."""
    demo = REPO / "graphs" / "lead_follow_mocap.toml"
    run = RunProcess(tmp_path, demo, "--duration", "4", "--insecure")
    spy = None
    try:
        spy = connect_spy(run, "lead_follow_mocap")
        deadline = time.monotonic() + 120
        while spy.last_tick() < 5:
            assert run.process.poll() is None, run.output()
            assert time.monotonic() < deadline, "tick 5 never came\n" + run.output()
            time.sleep(0.02)
        for payload in GARBAGE:  # blocking: a dropped put would not be counted
            spy.session.put(
                spy.keys.mocap("frisbee2"),
                payload,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        assert run.wait(240) == 3, run.output()
        assert f"agent f1: {len(GARBAGE)} malformed messages (mocap={len(GARBAGE)})" in (
            run.output()
        ), run.output()
        recording = read_recording(run.out)
        last = recording["/f1/status"][-1]
        assert last["malformed"] == {"mocap": len(GARBAGE)}, last
        for name in ("leader", "f2"):
            assert "malformed" not in recording[f"/{name}/status"][-1], name
        ys = recording["/f1/y"]
        assert [m["k"] for m in ys] == list(range(80))  # every tick, none lost to the garbage
        assert all(v is not None for m in ys for v in m["values"])  # no NaN pose used
    finally:
        if spy is not None:
            spy.close()
        run.cleanup()

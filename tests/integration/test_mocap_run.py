"""Motion capture end to end with ``hilswarm run``: the demo, occlusion -> safe, server loss.

Real processes: the orchestrator, one agent per robot, the mocap process with the real client
library (qtm-rt) and the protocol-level simulator (Qualisys RT over TCP on loopback), a real
Zenoh bus and a real MCAP file. Every process is killed by the harness's cleanup.
"""

from __future__ import annotations

import math
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from swarm_harness import (
    REPO,
    RunProcess,
    children_running,
    connect_spy,
    read_recording,
    wait_for,
)

pytestmark = [pytest.mark.integration, pytest.mark.slow]

DEMO = REPO / "graphs" / "lead_follow_mocap.toml"
RUN_TIMEOUT_S = 240


def variant(tmp_path: Path, **replace: str) -> Path:
    """The demo file with lines replaced (old line -> new text)."""
    text = DEMO.read_text()
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / "experiment.toml"
    path.write_text(text)
    return path


def outputs(recording: dict, agent: str) -> np.ndarray:
    """``/<agent>/y`` as floats (NaN is recorded as null)."""
    rows = recording[f"/{agent}/y"]
    return np.array([[np.nan if v is None else v for v in m["values"]] for m in rows])


def statuses(recording: dict, agent: str) -> list[tuple[str, str]]:
    return [(m["state"], m.get("detail", "")) for m in recording.get(f"/{agent}/status", [])]


def test_the_demo_runs_with_poses_through_the_real_client(
    runs: list[RunProcess], tmp_path: Path
) -> None:
    run = RunProcess(tmp_path, DEMO, "--duration", "4")
    runs.append(run)
    assert run.wait(RUN_TIMEOUT_S) == 0, run.output()
    recording = read_recording(run.out)
    for agent in ("leader", "f1", "f2"):
        y = outputs(recording, agent)
        assert len(y) == 80 and np.all(np.isfinite(y)), agent
        assert all(state != "safe" or "completed" in detail or "stop" in detail
                   for state, detail in statuses(recording, agent))  # fmt: skip
        rows = recording[f"/{agent}/telemetry/mocap"]
        latency = np.array([r["latency_s"] for r in rows])
        assert np.all(np.isfinite(latency)) and np.all(latency >= 0), agent
        assert np.median(latency) < 0.1, agent  # frame time -> sense, same host
        delivery = np.array([r["delivery_s"] for r in rows])  # frame time -> arrival here
        assert np.all(delivery >= 0) and np.all(delivery <= latency), agent
    # The leader drove towards its first waypoint (1, 0): the pose loop closed.
    assert recording["/leader/y"][-1]["values"][0] > 0.2
    # /<agent>/pose with Foxglove's well-known schema (the 3D panel's).
    schemas = {channel.topic: schema.name for schema, channel, _ in _raw(run.out)}
    assert schemas["/f1/pose"] == "foxglove.PoseInFrame"
    pose = recording["/f1/pose"][-1]
    assert pose["frame_id"] == "world"
    q = pose["pose"]["orientation"]
    assert math.isclose(q["x"] ** 2 + q["y"] ** 2 + q["z"] ** 2 + q["w"] ** 2, 1.0, rel_tol=1e-9)


def _raw(path: Path) -> Iterator:
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        yield from make_reader(stream).iter_messages()


def test_an_occluded_body_puts_its_agent_safe_with_lost_tracking(
    runs: list[RunProcess], tmp_path: Path
) -> None:
    experiment = variant(
        tmp_path,
        **{"dropout_frames = 3      # its length [frames] (held, well under hold_frames)":
           "dropout_frames = 3\nocclusions = { frisbee2 = [1.5, 60.0] }"},
    )  # fmt: skip
    run = RunProcess(tmp_path, experiment, "--duration", "8")
    runs.append(run)
    assert run.wait(RUN_TIMEOUT_S) == 1, run.output()  # on_agent_safe = "stop": ended early
    recording = read_recording(run.out)
    f1 = statuses(recording, "f1")
    lost = "lost tracking: body 'frisbee2' not seen for"
    assert any(s == "safe" and lost in d for s, d in f1), f1
    # The occlusion is scripted in experiment time: from t = 1.5 s; held for 50 frames
    # (0.5 s at 100 Hz), then no pose: the first NaN output is at about t = 2.0 s (k = 40).
    y = outputs(recording, "f1")
    ks = [m["k"] for m in recording["/f1/y"]]
    first_nan = ks[int(np.argmax(~np.all(np.isfinite(y), axis=1)))]
    assert 39 <= first_nan <= 60, first_nan  # up to 3 s: a starved simulator frames late
    assert np.all(np.isfinite(y[: ks.index(first_nan)]))  # tracked until then


def test_the_mocap_server_lost_stops_the_run_and_no_stale_pose_is_used(
    runs: list[RunProcess], tmp_path: Path
) -> None:
    run = RunProcess(tmp_path, DEMO, "--duration", "60")
    runs.append(run)
    run.remember_agents(3)

    def simulator() -> list[int]:
        return children_running(run.process.pid, b"hilswarm.agents.mocap.sim_process")

    wait_for(lambda: bool(simulator()), 60, "the mocap simulator process")
    spy = connect_spy(run, "lead_follow_mocap")
    try:
        wait_for(lambda: spy.last_tick() >= 20 or run.process.poll() is not None, 90, "ticks")
    finally:
        spy.close()
    assert run.process.poll() is None, run.output()
    os.kill(simulator()[0], signal.SIGKILL)  # the mocap server disappears
    assert run.wait(RUN_TIMEOUT_S) == 1, run.output()
    recording = read_recording(run.out)
    details = [d for agent in ("leader", "f1", "f2") for s, d in statuses(recording, agent)
               if s == "safe"]  # fmt: skip
    assert any("lost tracking" in d for d in details), details
    # No stale pose: once lost, every y is NaN, none repeats the last pose.
    for agent in ("leader", "f1", "f2"):
        y = outputs(recording, agent)
        lost = np.flatnonzero(~np.all(np.isfinite(y), axis=1))
        if lost.size:
            assert np.all(np.isnan(y[lost[0] :])), agent

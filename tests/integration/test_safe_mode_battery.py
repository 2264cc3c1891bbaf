"""Safe mode end to end: a low battery mid-run stops one vehicle; the recording shows it.

Runs ``hilswarm run graphs/safe_mode_battery.toml`` (real agent processes, a real Zenoh bus on
loopback, simulated boards) and reads the MCAP back.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.controllers.follower import OffsetFollower
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.orchestrator.experiment import load_experiment

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
EXPERIMENT = REPO / "graphs" / "safe_mode_battery.toml"
RUN_TIMEOUT_S = 240


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("safe_mode") / "run.mcap"
    command = [sys.executable, "-m", "hilswarm.orchestrator.cli", "run", str(EXPERIMENT),
               "--out", str(out), "--port", str(free_port())]  # fmt: skip
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True, cwd=out.parent,
    )  # fmt: skip
    try:
        output, _ = process.communicate(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        output, _ = process.communicate(timeout=10)
        pytest.fail(f"hilswarm run did not finish in {RUN_TIMEOUT_S} s:\n{output}")
    assert process.returncode == 0, output
    messages: dict[str, list[dict]] = {}
    for topic, _, message in iter_messages(out):
        messages.setdefault(topic, []).append(message)
    return messages


def expected_safe_time_s() -> float:
    leader = load_experiment(EXPERIMENT).agent("leader")
    params = {"sim_battery_full_v": 12.6, **leader.vehicle_params}
    return (params["sim_battery_full_v"] - params["battery_low_v"]) / params[
        "sim_battery_drain_v_per_s"
    ]


def test_leader_state_machine_goes_safe_on_low_battery(recording):
    states = [(m["state"], m["detail"], m["t"]) for m in recording["/leader/status"]]
    names = [s for s, _, _ in states]
    assert names.index("running") < names.index("safe") < names.index("stopped")
    _, detail, t_safe = states[names.index("safe")]
    assert "low battery" in detail
    # The battery crosses 10.5 V after (12.6 - 10.5) / 0.21 = 10 s of simulated time.
    assert t_safe == pytest.approx(expected_safe_time_s(), abs=0.2)


def test_leader_stops_moving_once_safe(recording):
    t_safe = next(m["t"] for m in recording["/leader/status"] if m["state"] == "safe")
    ys = [(m["t"], np.array(m["values"])) for m in recording["/leader/y"]]
    before = [y for t, y in ys if t_safe - 1.0 <= t < t_safe]
    after = [y for t, y in ys if t > t_safe + 0.2]
    assert np.ptp(np.array(before)[:, :2], axis=0).max() > 1e-3  # it was moving
    assert len(after) > 100
    assert np.ptp(np.array(after), axis=0).max() == 0.0  # motors off: not a micrometre more


def test_follower_keeps_running_and_comes_to_rest_behind_the_leader(recording):
    t_safe = next(m["t"] for m in recording["/leader/status"] if m["state"] == "safe")
    f1_states = [
        m["state"] for m in recording["/f1/status"] if m["t"] < recording["/f1/y"][-1]["t"]
    ]
    assert "safe" not in f1_states  # the follower was not stopped by the leader's safe mode
    follower = [(m["t"], np.array(m["values"])) for m in recording["/f1/y"]]
    moved_after = [y for t, y in follower if t > t_safe + 0.2]
    assert np.ptp(np.array(moved_after)[:, :2], axis=0).max() > 1e-3
    leader_final = np.array(recording["/leader/y"][-1]["values"])
    slot = OffsetFollower().slot(leader_final, OffsetFollower().validate_params(
        {"leader": "leader", "distance_m": 0.3}))  # fmt: skip
    final = follower[-1][1]
    assert math.dist(final[:2], slot) < 0.02

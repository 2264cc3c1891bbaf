"""Safe mode end to end: a low battery mid-run stops one vehicle; the recording shows it.

Runs ``hilswarm run graphs/safe_mode_battery.toml`` (real agent processes, a real Zenoh bus on
loopback, simulated boards) and reads the MCAP back; then the same experiment with
``on_agent_safe = "stop"`` (``tests/integration/data/safe_mode_battery_stop.toml``), where the
leader's safe mode ends the run for everyone.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.controllers.follower import OffsetFollower
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.orchestrator.experiment import load_experiment
from swarm_harness import finish_in_group

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
EXPERIMENT = REPO / "graphs" / "safe_mode_battery.toml"
STOP_EXPERIMENT = Path(__file__).resolve().parent / "data" / "safe_mode_battery_stop.toml"
RUN_TIMEOUT_S = 240


def run_experiment(experiment: Path, folder: Path) -> tuple[int, str, dict[str, list[dict]]]:
    """``hilswarm run`` of ``experiment``: exit status, output, messages by topic."""
    out = folder / "run.mcap"
    command = [sys.executable, "-m", "hilswarm.orchestrator.cli", "run", str(experiment),
               "--out", str(out)]  # fmt: skip
    code, output = finish_in_group(command, cwd=out.parent, timeout_s=RUN_TIMEOUT_S)
    messages: dict[str, list[dict]] = {}
    for topic, _, message in iter_messages(out):
        messages.setdefault(topic, []).append(message)
    return code, output, messages


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    code, output, messages = run_experiment(EXPERIMENT, tmp_path_factory.mktemp("safe_mode"))
    assert code == 3, output  # completed, degraded: the leader went safe (low battery)
    assert "degraded: agent leader safe from tick" in output, output
    return messages


@pytest.fixture(scope="module")
def stop_run(tmp_path_factory):
    return run_experiment(STOP_EXPERIMENT, tmp_path_factory.mktemp("safe_mode_stop"))


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


def test_policy_stop_brings_every_agent_to_safe_mode_and_ends_the_run(stop_run):
    code, output, recording = stop_run
    assert code == 1, output  # the run ended early by policy: not what was planned
    assert "on_agent_safe = stop" in output
    leader = [(m["state"], m["detail"], m["k"]) for m in recording["/leader/status"]]
    names = [s for s, _, _ in leader]
    assert names[-2:] == ["safe", "stopped"]
    _, detail, k_safe = leader[names.index("safe")]
    assert "low battery" in detail
    assert k_safe * load_experiment(STOP_EXPERIMENT).dt == pytest.approx(
        expected_safe_time_s(), abs=0.2
    )
    # f1 was healthy: it went safe because of the policy, and says why.
    f1 = recording["/f1/status"]
    assert [m["state"] for m in f1][-2:] == ["safe", "stopped"]
    f1_safe = next(m for m in f1 if m["state"] == "safe")
    assert "on_agent_safe = stop" in f1_safe["detail"]
    assert "leader" in f1_safe["detail"]
    # The run stopped shortly after the leader's safe mode, long before its 20 s (400 ticks).
    # In lockstep f1, which follows the leader, may trail it by up to the window.
    last_k = recording["/f1/y"][-1]["k"]
    window = load_experiment(STOP_EXPERIMENT).lockstep_window
    assert k_safe - window <= last_k <= k_safe + 20, (k_safe, last_k)
    # The orchestrator recorded why it stopped.
    stopping = [m for m in recording["/orchestrator/status"] if m["state"] == "stopping"]
    assert len(stopping) == 1
    assert "agent leader entered safe mode" in stopping[0]["detail"]
    assert "on_agent_safe = stop" in stopping[0]["detail"]

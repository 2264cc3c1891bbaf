"""The demo experiments in graphs/ run end to end through `hilswarm run` (lockstep)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.calibration import Calibration
from hilswarm.agents.sim import chapter3
from hilswarm.agents.vehicles.frisbee import DEFAULT_CALIBRATION
from hilswarm.orchestrator.calibration_report import calibration_as_json
from hilswarm.orchestrator.experiment import load_experiment
from swarm_harness import REPO, RunProcess, read_recording

pytestmark = pytest.mark.integration

GRAPHS = REPO / "graphs"


@pytest.fixture(scope="module")
def lead_follow_recording(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict]:
    """The recording of ``graphs/lead_follow.toml`` (run once for the tests that read it)."""
    started: list[RunProcess] = []
    try:
        yield run_demo(started, tmp_path_factory.mktemp("lead_follow"), "lead_follow")
    finally:
        for run in started:
            run.cleanup()


def run_demo(runs: list[RunProcess], tmp_path: Path, name: str) -> dict:
    run = RunProcess(tmp_path, GRAPHS / f"{name}.toml")
    runs.append(run)
    assert run.wait(300) == 0, run.output()
    assert "recording:" in run.output()
    return read_recording(run.out)


def test_spring_mass_damper_equals_the_sil_euler_closed_loop(
    runs: list[RunProcess], tmp_path: Path
) -> None:
    recording = run_demo(runs, tmp_path, "spring_mass_damper")
    y = np.array([m["values"] for m in recording["/smd/y"]])
    assert [m["k"] for m in recording["/smd/y"]] == list(range(len(y)))
    experiment = load_experiment(GRAPHS / "spring_mass_damper.toml")
    reference = chapter3.sil_fixed_step(
        experiment.agents[0].params["K"],
        z0=experiment.agents[0].initial_state,
        dt=experiment.dt,
        n_ticks=experiment.n_ticks - 1,
        method="euler",
    )
    assert y.shape == reference.z.shape
    np.testing.assert_allclose(y, reference.z, rtol=0, atol=1e-9)


def test_consensus_ring_converges_to_the_average_of_initial_states(
    runs: list[RunProcess], tmp_path: Path
) -> None:
    recording = run_demo(runs, tmp_path, "consensus_ring")
    experiment = load_experiment(GRAPHS / "consensus_ring.toml")
    average = np.mean([spec.initial_state for spec in experiment.agents], axis=0)
    for spec in experiment.agents:
        ys = recording[f"/{spec.name}/y"]
        assert len(ys) == experiment.n_ticks
        np.testing.assert_allclose(ys[0]["values"], spec.initial_state)
        np.testing.assert_allclose(ys[-1]["values"], average, atol=1e-3)


def test_lead_follow_every_agent_reaches_its_goal(lead_follow_recording: dict) -> None:
    recording = lead_follow_recording
    experiment = load_experiment(GRAPHS / "lead_follow.toml")
    leader = experiment.agent("leader").params
    final = {
        name: np.array(recording[f"/{name}/y"][-1]["values"]) for name in ("leader", "f1", "f2")
    }
    goal = np.array(leader["waypoints"][-1])
    assert np.linalg.norm(final["leader"][:2] - goal) <= leader["waypoint_tolerance_m"] + 1e-9
    for follower in ("f1", "f2"):
        params = experiment.agent(follower).params
        ahead = final[params["leader"]]
        heading = ahead[2]
        target = ahead[:2] - params["distance_m"] * np.array([np.cos(heading), np.sin(heading)])
        assert np.linalg.norm(final[follower][:2] - target) < 0.05, (follower, final)


def test_lead_follow_records_every_vehicles_calibration(lead_follow_recording: dict) -> None:
    """Each Frisbee bot runs with the shipped reference calibration; the run records it."""
    expected = calibration_as_json(Calibration.from_file(DEFAULT_CALIBRATION))
    assert expected["inputs"], "the reference calibration has tables"
    for name in ("leader", "f1", "f2"):
        messages = lead_follow_recording[f"/{name}/calibration"]
        assert len(messages) == 1
        message = messages[0]
        assert (message["k"], message["t"], message["values"]) == (0, 0.0, [])
        for key in ("vehicle_id", "date", "source"):
            assert message[key] == expected[key]
        assert [i["name"] for i in message["inputs"]] == [i["name"] for i in expected["inputs"]]
        for got, want in zip(message["inputs"], expected["inputs"], strict=True):
            assert got["unit"] == want["unit"]
            np.testing.assert_allclose(got["u"], want["u"], rtol=0, atol=0)
            np.testing.assert_allclose(got["pwm"], want["pwm"], rtol=0, atol=0)
    # The outputs are named after the vehicle's output_names, beside values.
    first = lead_follow_recording["/leader/y"][0]
    assert first["values"] == [first["x"], first["y"], first["psi"]]


def test_lockstep_results_do_not_depend_on_the_window(
    lead_follow_recording: dict, runs: list[RunProcess], tmp_path: Path
) -> None:
    """Window 1 (a swarm-wide barrier every tick) records exactly what the default records.

    An agent's input depends only on its own and its neighbours' outputs, so letting agents
    run ahead of non-neighbours (the default window of 8 ticks) changes no number.
    """
    text = (GRAPHS / "lead_follow.toml").read_text(encoding="utf-8")
    barrier = tmp_path / "lead_follow_barrier.toml"
    barrier.write_text(
        text.replace('mode = "lockstep"', 'mode = "lockstep"\nlockstep_window = 1', 1),
        encoding="utf-8",
    )
    assert load_experiment(barrier).lockstep_window == 1
    assert load_experiment(GRAPHS / "lead_follow.toml").lockstep_window > 1
    run = RunProcess(tmp_path, barrier)
    runs.append(run)
    assert run.wait(300) == 0, run.output()
    strict = read_recording(run.out)
    for name in ("leader", "f1", "f2"):
        for leaf in ("y", "u"):
            got = [(m["k"], m["values"]) for m in lead_follow_recording[f"/{name}/{leaf}"]]
            want = [(m["k"], m["values"]) for m in strict[f"/{name}/{leaf}"]]
            assert got == want, (name, leaf)
    ticks = strict["/orchestrator/ticks"]
    assert [m["k"] for m in ticks] == list(range(len(ticks)))

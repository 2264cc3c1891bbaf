"""The ``realtime_clock`` setting: read and checked, and when the manager self-clocks."""

from __future__ import annotations

import textwrap
import time
from pathlib import Path
from typing import Any

from hilswarm.agents import bus
from hilswarm.orchestrator.experiment import Experiment, load_experiment, parse_experiment
from hilswarm.orchestrator.manager import InstanceManager

TEXT = """
[experiment]
name = "t"
rate_hz = 10
duration_s = 2
mode = "realtime"
{setting}

[graph]
agents = ["a", "b"]
adjacency = [[0, 1], [1, 0]]

[defaults]
vehicle = "simulated"
controller = "consensus"
vehicle_params = {{ plant = "integrator" }}

[agents.a]
[agents.b]
initial_state = [1.0]
"""


def write(tmp_path: Path, setting: str) -> Path:
    path = tmp_path / "exp.toml"
    path.write_text(textwrap.dedent(TEXT.format(setting=setting)), encoding="utf-8")
    return path


def manager(experiment: Experiment, **kwargs: Any) -> InstanceManager:
    return InstanceManager(experiment, recorder=None, listen=[bus.loopback_endpoint(0)], **kwargs)


def test_realtime_clock_is_read_checked_and_overridable(tmp_path: Path) -> None:
    assert load_experiment(write(tmp_path, "")).realtime_clock == "shared"  # the default
    shared = load_experiment(write(tmp_path, 'realtime_clock = "shared"'))
    assert shared.realtime_clock == "shared"
    overridden = load_experiment(write(tmp_path, ""), overrides={"realtime_clock": "manager"})
    assert overridden.realtime_clock == "manager"
    experiment, problems = parse_experiment(write(tmp_path, 'realtime_clock = "wall"'))
    assert experiment is None
    assert [p.key for p in problems] == ["experiment.realtime_clock"], problems


def test_the_manager_self_clocks_only_realtime_runs_of_local_agents(tmp_path: Path) -> None:
    shared = load_experiment(write(tmp_path, 'realtime_clock = "shared"'))
    assert manager(shared).self_clocked
    assert manager(shared).window == 2  # the next tick is opened in advance
    assert not manager(shared, remote=["b"]).self_clocked  # b joins from another host
    assert not manager(shared, clock=lambda: 0.0).self_clocked  # not CLOCK_MONOTONIC
    assert manager(shared, clock=time.monotonic).self_clocked
    lockstep = load_experiment(
        write(tmp_path, 'realtime_clock = "shared"'), overrides={"mode": "lockstep"}
    )
    assert not manager(lockstep).self_clocked
    assert manager(load_experiment(write(tmp_path, ""))).self_clocked  # the default
    ticked = load_experiment(write(tmp_path, 'realtime_clock = "manager"'))
    assert not manager(ticked).self_clocked and manager(ticked).window == 1

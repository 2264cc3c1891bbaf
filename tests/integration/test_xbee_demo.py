"""graphs/xbee_swarm.toml end to end: six Frisbees on one simulated coordinator, one of them
the real firmware in simavr behind its simulated radio, through the gateway process."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from hilswarm.agents.errors import SimulatorError
from hilswarm.agents.link.simavr import locate_build
from swarm_harness import REPO, RunProcess, free_port, read_recording

pytestmark = [pytest.mark.integration, pytest.mark.firmware, pytest.mark.slow]


@pytest.fixture
def runs() -> Iterator[list[RunProcess]]:
    started: list[RunProcess] = []
    yield started
    for run in started:
        run.cleanup()


def test_xbee_swarm_demo_runs_and_every_robot_moves(runs: list[RunProcess], tmp_path: Path) -> None:
    try:
        locate_build("duemilanove")
    except SimulatorError as exc:
        pytest.skip(str(exc))
    run = RunProcess(
        tmp_path, REPO / "graphs" / "xbee_swarm.toml", "--duration", "3", port=free_port()
    )
    runs.append(run)
    assert run.wait(300) == 0, run.output()
    output = run.output()
    assert "XBee gateway: READY" in output and "completed" in output, output
    recording = read_recording(run.out)
    for name, x0 in [("leader", 0.0), ("f1", -0.3), ("f5", -1.5)]:
        ys = recording[f"/{name}/y"]
        assert len(ys) == 60, name
        assert ys[-1]["x"] > x0 + 0.1, (name, ys[-1])  # it drove forward: the loop is closed

"""Every agent of every demo in graphs/ that may be rehearsed (agents/rehearsal.py) runs its
whole rehearsal: the made-up inputs suit each of the project's vehicles and controllers."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from hilswarm.agents.agent import Agent
from hilswarm.agents.rehearsal import REHEARSAL_TICKS, can_rehearse, rehearse
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.launcher import agent_config_for

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
DEMOS = sorted(p.name for p in GRAPHS.glob("*.toml"))


@pytest.mark.parametrize("demo", DEMOS)
def test_every_rehearsable_agent_of_a_demo_rehearses_every_tick(
    demo: str, caplog: pytest.LogCaptureFixture
) -> None:
    experiment = load_experiment(GRAPHS / demo)
    configs = [agent_config_for(experiment, name, run_id="r") for name in experiment.agent_names]
    ticks: dict[str, list[int]] = {}

    class Counting(Agent):
        def tick_work(self, k, t, **kwargs):  # type: ignore[no-untyped-def]
            ticks.setdefault(self.config.name, []).append(k)
            return super().tick_work(k, t, **kwargs)

    caplog.set_level(logging.DEBUG, logger="hilswarm.agents.rehearsal")
    rehearsed = [config.name for config in configs if can_rehearse(config)]
    for config in configs:
        rehearse(Counting, config)
    assert "ended early" not in caplog.text
    assert ticks == {name: list(range(REHEARSAL_TICKS)) for name in rehearsed}
    if demo.startswith("xbee"):
        assert rehearsed == []  # robots behind a radio: a real link, never rehearsed

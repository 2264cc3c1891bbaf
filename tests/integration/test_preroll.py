"""The pre-roll of a self-clocked realtime run: warm-up outputs before tick 0, which every
receiver ignores. One real agent on a real Zenoh router (``agent_rig``), and a whole run."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import hilswarm.agents.agent as agent_module
import numpy as np
import pytest
from agent_rig import DT, Rig, cart_config, cart_hardware
from hilswarm.agents import bus
from hilswarm.agents.agent import AgentConfig, build_hardware
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.tick_engine import PREROLL_TICKS, start_lead
from swarm_harness import RunProcess, read_recording, wait_for, write_toy_experiment
from swarm_toys import FullBattery

pytestmark = pytest.mark.integration

LAST = 9  # the schedule's last tick


@pytest.fixture
def rigs() -> Iterator[list[Rig]]:
    started: list[Rig] = []
    yield started
    for rig in started:
        rig.close()


def start_schedule(rig: Rig) -> float:
    """Send the run's schedule as the manager does, with its lead; returns T0 [s]."""
    t0 = time.perf_counter() + start_lead(DT, self_clocked=True)
    rig.tick_pub.put(bus.encode_schedule(bus.ScheduleMessage(0, LAST, t0, DT)))
    return t0


def test_the_agent_puts_its_warm_up_outputs_before_tick_0(rigs: list[Rig]) -> None:
    board = SimBoard(plant=FullBattery(), dt=DT)
    rig = Rig(cart_config(link="sim://"), cart_hardware(board))
    rigs.append(rig)
    t0 = start_schedule(rig)
    wait_for(lambda: LAST in rig.answered(), 10, "the schedule's last tick")
    assert time.perf_counter() >= t0 + LAST * DT
    answered = rig.answered()
    warmups = [k for k in answered if k < 0]
    ticks = [k for k in answered if k >= 0]
    assert answered == warmups + ticks  # every warm-up before tick 0
    # oldest first, k = -8 .. -1 (a warm-up whose time passed on a loaded machine is skipped,
    # never sent late); then each tick once, those the agent fell behind on counted as skipped
    assert warmups and warmups == sorted(set(warmups)), warmups
    assert set(warmups) <= set(range(-PREROLL_TICKS, 0)), warmups
    assert ticks == sorted(set(ticks)) and len(ticks) + rig.agent.skipped == LAST + 1, ticks
    running = [m for m in rig.statuses if m["state"] == "running"]
    assert running[0]["detail"] == "schedule received"
    assert rig.agent.k == LAST
    assert rig.close() == 0


def test_a_neighbours_warm_up_outputs_are_ignored(rigs: list[Rig]) -> None:
    config = dataclasses.replace(
        cart_config(link="sim://"), agent_names=("cart", "other"), neighbours=("other",)
    )
    board = SimBoard(plant=FullBattery(), dt=DT)
    rig = Rig(config, cart_hardware(board))
    rigs.append(rig)
    other = rig.router.declare_publisher(rig.keys.y("other"), **bus.TICK_PATH_QOS)
    try:
        for k in range(-PREROLL_TICKS, 0):
            other.put(bus.encode_vector(k, k * DT, np.full(1, np.nan)))
        other.put(bus.encode_vector(0, 0.0, np.ones(1)))  # tick 0's output: kept
        engine = rig.agent.engine
        wait_for(lambda: "other" in engine.received_from, 10, "the neighbour's y_0")
        assert set(engine.history["other"]) == {0}  # no warm-up kept
        assert not any(rig.agent.malformed.values()) and not any(engine.dropped.values())
    finally:
        other.undeclare()


def test_a_run_records_no_warm_up_output(runs: list[RunProcess], tmp_path: Path) -> None:
    path = write_toy_experiment(tmp_path / "toy.toml", mode="realtime", duration_s=1.0)
    text = path.read_text(encoding="utf-8").replace(
        'mode = "realtime"\n', 'mode = "realtime"\nmax_late_fraction = 1.0\n'
    )
    path.write_text(text, encoding="utf-8")  # the default clock: self-clocked
    run = RunProcess(tmp_path, path, "--no-check")
    runs.append(run)
    assert run.wait(120) == 0, run.output()
    recording = read_recording(run.out)
    assert [m["k"] for m in recording["/orchestrator/ticks"]] == list(range(50))
    for name in ("a", "b", "c", "d"):  # no k < 0; a tick skipped under load is absent
        ks = [m["k"] for m in recording[f"/{name}/y"]]
        assert ks == sorted(set(ks)) and ks[0] >= 0 and ks[-1] == 49, (name, ks)


def test_the_agent_rehearses_before_it_is_armed(
    rigs: list[Rig], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A Frisbee on ``sim://`` with a registry controller rehearses its tick path once, on
    copies, before it reports ``armed`` (agents/rehearsal.py); a toy of the tests does not."""
    calls: list[tuple[str, float | None]] = []
    real = agent_module.rehearse

    def watched(make_agent: Any, config: AgentConfig) -> float | None:
        took = real(make_agent, config)
        calls.append((config.name, took))
        return took

    monkeypatch.setattr(agent_module, "rehearse", watched)
    config = dataclasses.replace(
        cart_config(link="sim://", name="disc"),
        vehicle="frisbee",
        controller="waypoint",
        params={"waypoints": [[1.0, 0.0]]},
        initial_state=(0.0, 0.0, 0.0),
    )
    rig = Rig(config, build_hardware)  # waits for armed
    rigs.append(rig)
    assert len(calls) == 1 and calls[0][0] == "disc" and calls[0][1] is not None
    t0 = start_schedule(rig)
    wait_for(lambda: LAST in rig.answered(), 10, "the schedule's last tick")
    assert time.perf_counter() >= t0
    assert rig.close() == 0

    toy = Rig(cart_config(link="sim://"), cart_hardware(SimBoard(plant=FullBattery(), dt=DT)))
    rigs.append(toy)
    assert calls[1:] == [("cart", None)]  # asked, and refused: a user's classes

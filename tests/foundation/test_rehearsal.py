"""The rehearsal (agents/rehearsal.py): an agent's tick path run on throwaway copies before it
is armed, which must never change what the agent itself computes."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
from hilswarm.agents import bus
from hilswarm.agents.agent import Agent, AgentConfig, build_hardware
from hilswarm.agents.errors import BoardConnectionError
from hilswarm.agents.rehearsal import REHEARSAL_TICKS, can_rehearse, rehearse

DT = 0.01
TICKS = 40


def frisbee(**changes: object) -> AgentConfig:
    """A Frisbee on ``sim://`` with the waypoint controller, two ring neighbours and noisy
    simulated mocap (so that a shared random generator would show)."""
    config = AgentConfig(
        experiment="rehearsal",
        name="a0",
        agent_names=("a0", "a1", "a2"),
        neighbours=("a1", "a2"),
        vehicle="frisbee",
        link="sim://",
        controller="waypoint",
        dt=DT,
        params={"waypoints": [[1.0, 1.0], [0.0, 1.0]]},
        initial_state=(0.0, 0.0, 0.0),
        seed=7,
        mocap_noise_std_m=0.002,
        mocap_noise_std_rad=0.01,
    )
    return dataclasses.replace(config, **changes)


def offline(config: AgentConfig) -> Agent:
    agent = Agent(config, ["tcp/127.0.0.1:9"])  # never connected
    agent.use_hardware(build_hardware(config))
    for event in ("connect", "configure", "arm", "start"):
        agent.lifecycle.send(event)
    return agent


def _bytes(values: np.ndarray | None) -> bytes:
    return b"" if values is None else values.tobytes()


def run(agent: Agent) -> list[tuple[bytes, bytes, bytes]]:
    """``TICKS`` ticks with neighbour outputs that change every tick: every y message, u and
    x_hat (the tick reports hold timings, which differ from run to run)."""
    out = []
    n = int(agent.hardware.vehicle.n_outputs)
    for k in range(TICKS):
        if k > 0:
            for i, name in enumerate(agent.config.neighbours):
                values = np.linspace(0.1, 0.4, n) * (i + 1) + 0.01 * k
                agent.receive_neighbour(name, bus.encode_vector(k - 1, (k - 1) * DT, values))
        y_payload, _report, u, x_hat = agent.tick_work(k, k * DT)
        out.append((y_payload, _bytes(u), _bytes(x_hat)))
    return out


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({}, True),
        ({"link": "sim://uno?board_id=3"}, True),
        (
            {
                "vehicle": "simulated",
                "link": None,
                "controller": "consensus",
                "vehicle_params": {"plant": "integrator", "plant_params": {"n_dims": 2}},
            },
            True,
        ),
        ({"link": "simavr://uno"}, False),  # a simulator process of its own: not for a copy
        ({"link": "/dev/ttyUSB0"}, False),  # a real board never sees made-up ticks
        ({"link": "socket://127.0.0.1:5000"}, False),
        ({"link": "xbee://0013A20040000001"}, False),
        ({"controller": "my_lab.control:Mine"}, False),  # a user's class: effects unknown
        ({"vehicle": "my_lab.robots:Bot"}, False),
    ],
)
def test_only_the_projects_own_classes_on_a_simulated_board_are_rehearsed(
    changes: dict[str, object], expected: bool
) -> None:
    assert can_rehearse(frisbee(**changes)) is expected


def test_a_user_controller_is_never_run_by_a_rehearsal() -> None:
    assert rehearse(Agent, frisbee(controller="no_such_module:Nothing")) is None


def test_the_agent_computes_the_same_with_or_without_a_rehearsal() -> None:
    plain = run(offline(frisbee()))
    agent = offline(frisbee())  # built first, as in a run: the rehearsal comes after it
    took = rehearse(Agent, frisbee())
    assert took is not None and took > 0
    assert run(agent) == plain  # every y, bit for bit (noise, plant, controller, encoding)


def test_a_rehearsal_is_quiet_and_leaves_no_board_open(caplog: pytest.LogCaptureFixture) -> None:
    boards = []

    class Recording(Agent):
        def use_hardware(self, hardware):  # type: ignore[no-untyped-def]
            boards.append(hardware.board)
            super().use_hardware(hardware)

    caplog.set_level(logging.DEBUG)
    assert rehearse(Recording, frisbee()) is not None
    assert [r for r in caplog.records if r.levelno >= logging.INFO] == []
    assert len(boards) == 1
    with pytest.raises(BoardConnectionError, match="not open"):
        boards[0].estop()  # closed


def test_a_failure_inside_a_rehearsal_ends_it_and_is_never_the_runs(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ticks: list[int] = []

    class Refusing(Agent):
        def tick_work(self, k, t, **kwargs):  # type: ignore[no-untyped-def]
            ticks.append(k)
            if k == 3:
                raise ValueError("made-up inputs refused")
            return super().tick_work(k, t, **kwargs)

    caplog.set_level(logging.DEBUG, logger="hilswarm.agents.rehearsal")
    assert rehearse(Refusing, frisbee()) is not None
    assert ticks == [0, 1, 2, 3]
    assert "rehearsal ended early: ValueError: made-up inputs refused" in caplog.text


def test_a_rehearsal_runs_its_ticks() -> None:
    ticks: list[int] = []

    class Counting(Agent):
        def tick_work(self, k, t, **kwargs):  # type: ignore[no-untyped-def]
            ticks.append(k)
            return super().tick_work(k, t, **kwargs)

    rehearse(Counting, frisbee())
    assert ticks == list(range(REHEARSAL_TICKS))

"""The gateway end to end: bus <-> gateway <-> simulated coordinator <-> air <-> robots.

Real Zenoh sessions on loopback, the real gateway on the simulated coordinator's pty (API
frames on a real tty), boards in the agent's role through ``xbee://`` links.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.errors import BoardTimeoutError
from hilswarm.agents.link.board import PROTOCOL_VERSION, PinConfig, PinMode
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.xbee.api_frames import FrameFamily
from hilswarm.agents.xbee.config import GatewayConfig
from hilswarm.agents.xbee.gateway import Gateway, GatewayError
from hilswarm.agents.xbee.sim_coordinator import SimCoordinator, SimRemote
from hilswarm.agents.xbee.sim_robot import WireServerUart
from hilswarm.agents.xbee.transport import board_from_url
from xbee_rig import wait_for

EXP = "xbee_test"
ADDRS = {"r1": 0x0013A20040000001, "r2": 0x0013A20040000002}
PINS = [
    PinConfig(5, PinMode.PWM),
    PinConfig(7, PinMode.DIGITAL_OUT),
    PinConfig(14, PinMode.ANALOG_IN),
]


@pytest.fixture
def swarm(
    client_session: Callable[[], zenoh.Session], request: pytest.FixtureRequest
) -> Iterator[tuple[SimCoordinator, Gateway, dict[str, object], dict[str, SimBoard]]]:
    family, api_mode = getattr(request, "param", (FrameFamily.IEEE_802_15_4, 1))
    sims = {name: SimBoard(dt=0.05) for name in ADDRS}
    remotes = [SimRemote(ADDRS[n], WireServerUart(sims[n]), node_id=n) for n in ADDRS]
    with ExitStack() as stack:
        coordinator = stack.enter_context(
            SimCoordinator(remotes, api_mode=api_mode, family=family, seed=3)
        )
        config = GatewayConfig(port="sim", api_mode=api_mode)
        gateway = Gateway(
            config,
            bus.BusKeys(EXP),
            ADDRS,
            client_session(),
            port_url=coordinator.url,
            stats_period_s=0.1,
        )
        stack.enter_context(gateway)
        agent_session = client_session()
        boards = {}
        for name, address in ADDRS.items():
            board = board_from_url(
                f"xbee://{address:016X}", session=agent_session, experiment=EXP, agent=name
            )
            stack.callback(board.close)
            boards[name] = board
        yield coordinator, gateway, boards, sims


@pytest.mark.parametrize(
    "swarm",
    [
        (FrameFamily.IEEE_802_15_4, 1),
        (FrameFamily.IEEE_802_15_4, 2),
        (FrameFamily.ZIGBEE, 1),
        (FrameFamily.ZIGBEE, 2),
    ],
    indirect=True,
    ids=["802.15.4-AP1", "802.15.4-AP2", "zigbee-AP1", "zigbee-AP2"],
)
def test_unicast_round_trips_through_the_gateway(swarm: tuple) -> None:
    coordinator, gateway, boards, sims = swarm
    assert gateway.family == coordinator.family
    for name, board in boards.items():
        info = board.open()
        assert info.protocol_version == PROTOCOL_VERSION
        board.configure(PINS, watchdog_s=0.5)
        sims[name].set_analog_input(14, 2.5)
    for k in range(20):
        for name, board in boards.items():
            reply = board.exchange({5: 10 * k, 7: k % 2}, [14])
            assert reply.samples[14] == pytest.approx(512, abs=2)
            assert sims[name].outputs[5] == 10 * k
    stats = gateway.stats.robots
    assert all(s.delivered >= 22 and s.tx_failures == 0 for s in stats.values())


def test_robot_out_of_range_misses_its_ticks_others_go_on(swarm: tuple) -> None:
    coordinator, gateway, boards, _ = swarm
    for board in boards.values():
        board.open()
        board.configure(PINS, watchdog_s=0.5)
    coordinator.set_out_of_range(ADDRS["r1"])
    boards["r1"].timeout_s = 0.1
    boards["r1"].retries = 1
    with pytest.raises(BoardTimeoutError):
        boards["r1"].exchange({5: 1}, [14])
    for _ in range(5):
        boards["r2"].exchange({5: 2}, [14])
    wait_for(lambda: gateway.stats.robots["r1"].tx_failures >= 2, 5.0, "TX status failures of r1")
    assert gateway.stats.robots["r2"].tx_failures == 0
    coordinator.set_out_of_range(ADDRS["r1"], False)
    boards["r1"].exchange({5: 3}, [14])  # back in range: the next tick works


def test_coordinator_unplugged_and_replugged(swarm: tuple) -> None:
    coordinator, gateway, boards, _ = swarm
    board = boards["r1"]
    board.open()
    board.configure(PINS, watchdog_s=0.5)
    board.timeout_s = 0.1
    board.retries = 0
    coordinator.unplug()
    wait_for(lambda: not gateway.connected.is_set(), 5.0, "the gateway to notice the unplug")
    with pytest.raises(BoardTimeoutError):
        board.exchange({5: 1}, [14])
    coordinator.replug()
    wait_for(gateway.connected.is_set, 5.0, "the gateway to reconnect")
    assert gateway.stats.reconnections == 1
    board.retries = 3
    board.exchange({5: 4}, [14])


def test_gateway_puts_a_coordinator_in_the_other_api_mode_back_in_its_own(
    client_session: Callable[[], zenoh.Session],
) -> None:
    sim = SimBoard(dt=0.05)
    remote = SimRemote(ADDRS["r1"], WireServerUart(sim))
    with SimCoordinator([remote], api_mode=2) as coordinator:
        config = GatewayConfig(port="sim", api_mode=1)
        session = client_session()
        with Gateway(
            config, bus.BusKeys(EXP), {"r1": ADDRS["r1"]}, session, port_url=coordinator.url
        ):
            assert coordinator.api_mode == 1
            board = board_from_url(
                f"xbee://{ADDRS['r1']:016X}", session=client_session(), experiment=EXP, agent="r1"
            )
            try:
                board.open()
                board.configure(PINS, watchdog_s=0.5)
                board.exchange({5: 9}, [14])
                assert sim.outputs[5] == 9
            finally:
                board.close()


def test_no_coordinator_is_a_clear_error(
    client_session: Callable[[], zenoh.Session], tmp_path: Path
) -> None:
    config = GatewayConfig(port=str(tmp_path / "ttyUSB7"))
    gateway = Gateway(config, bus.BusKeys(EXP), {"r1": ADDRS["r1"]}, client_session())
    with pytest.raises(GatewayError, match="cannot open the coordinator"):
        gateway.start()

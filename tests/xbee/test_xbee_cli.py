"""`hilswarm xbee scan|setup` with digi-xbee and `hilswarm gateway`, against the simulated
coordinator's pty (digi-xbee cannot tell it from a radio)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.xbee import radio_setup
from hilswarm.agents.xbee.api_frames import FrameFamily
from hilswarm.agents.xbee.sim_coordinator import SimCoordinator, SimRemote
from hilswarm.agents.xbee.sim_robot import WireServerUart
from hilswarm.orchestrator.cli import main

REPO = Path(__file__).resolve().parents[2]
ADDRS = [0x0013A20040000001, 0x0013A20040000002]


@pytest.fixture(params=[FrameFamily.IEEE_802_15_4, FrameFamily.ZIGBEE], ids=lambda f: f.value)
def coordinator(request: pytest.FixtureRequest) -> Iterator[SimCoordinator]:
    remotes = [
        SimRemote(a, WireServerUart(SimBoard(dt=0.05)), node_id=f"bot{i}", rssi_dbm=-40 - 10 * i)
        for i, a in enumerate(ADDRS)
    ]
    with SimCoordinator(remotes, family=request.param) as sim:
        yield sim


def test_scan_lists_every_radio(
    coordinator: SimCoordinator, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["xbee", "scan", "--port", coordinator.url, "--timeout", "5"]) == 0
    out = capsys.readouterr().out
    assert "0013A20040000001   bot0" in out and "-40" in out
    assert "0013A20040000002   bot1" in out and "-50" in out


def test_setup_configures_the_robots_then_the_coordinator(
    coordinator: SimCoordinator, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(
        ["xbee", "setup", "--port", coordinator.url, "--all", "--api-mode", "2",
         "--pan-id", "0x1234", "--channel", "0x0F"]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    for remote in coordinator.remotes.values():
        assert remote.params["ID"] == b"\x12\x34" and remote.params["CH"] == b"\x0f"
        assert remote.params["AP"] == b"\x00"  # transparent: the firmware needs no new wiring
        assert remote.params["DL"] == coordinator.params["SL"]
    assert coordinator.params["AP"] == b"\x02" and coordinator.params["CH"] == b"\x0f"


def test_setup_checks_every_setting_before_any_radio(coordinator: SimCoordinator) -> None:
    """A bad coordinator rate is refused before the robots are switched (they would be left on
    a channel the coordinator is not on)."""
    before = {a: dict(r.params) for a, r in coordinator.remotes.items()}
    own = dict(coordinator.params)
    with pytest.raises(radio_setup.RadioSettingError, match="1234 baud is not a standard"):
        radio_setup.setup(
            coordinator.url, channel=0x0F, new_baud=1234, remotes=ADDRS, progress=lambda _: None
        )
    with pytest.raises(radio_setup.RadioSettingError, match="channel 0x40 is out of range"):
        radio_setup.setup(coordinator.url, channel=0x40, remotes=ADDRS, progress=lambda _: None)
    assert {a: dict(r.params) for a, r in coordinator.remotes.items()} == before
    assert dict(coordinator.params) == own


def test_setup_reports_a_silent_robot_radio(
    coordinator: SimCoordinator, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["xbee", "setup", "--port", coordinator.url, "--remote", "0013A200400000AA"])
    assert code == 1
    assert "robot radio 0013A200400000AA" in capsys.readouterr().err


def test_no_coordinator_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A port with no radio in API mode behind it: exit 1, saying so; a device that does not
    exist: bad input (exit 2), listing the serial ports present."""
    controller, port = os.openpty()  # a serial port on which nothing answers
    name = os.ttyname(port)
    try:
        assert main(["xbee", "scan", "--port", name, "--timeout", "1"]) == 1
    finally:
        os.close(controller)
        os.close(port)
    error = capsys.readouterr().err
    assert error.startswith(f"asking the radio at {name} (115200 baud)...\n"), error
    assert "no XBee in API mode answers" in error, error
    assert main(["xbee", "scan", "--port", str(tmp_path / "ttyUSB9")]) == 2
    error = capsys.readouterr().err
    assert "does not exist" in error, error
    assert "serial ports present" in error or "no serial ports" in error, error


def test_gateway_command_without_xbee_agents(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["gateway", str(REPO / "graphs" / "lead_follow.toml"), "--connect", "tcp/x:1"])
    assert code == 2
    assert "links through xbee://" in capsys.readouterr().err

"""Board faults at a running agent: e-stop while an exchange is blocked, stalled and unplugged
boards (the real firmware in simavr, and a socket board server), a link that does not come
back. One real agent on a real Zenoh router (``agent_rig``)."""

from __future__ import annotations

import os
import re
import signal
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest
from agent_rig import DT, Rig, cart_config, cart_hardware
from hilswarm.agents import bus
from hilswarm.agents.agent import AgentConfig, AgentHardware
from hilswarm.agents.errors import SimulatorError
from hilswarm.agents.link.serial_board import SerialBoard
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.link.simavr import SimavrBoard
from hilswarm.agents.link.wire_server import SocketWireServer
from swarm_harness import (
    RunProcess,
    agent_name_of,
    children_running,
    connect_spy,
    read_recording,
    wait_for,
)
from swarm_toys import FullBattery

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]

#: Output pins of the toy cart: direction pins and the two PWM enables.
DIRECTION_PINS = (4, 7, 8, 12)
PWM_PINS = (5, 6)


def simavr_board(**options: object) -> SimavrBoard:
    """The real firmware in the simulator, paced (real UART timing)."""
    try:
        board = SimavrBoard("uno", paced=True, **options)
    except SimulatorError as exc:
        pytest.skip(str(exc))
    return board


def driving(outputs: Mapping[int, int]) -> bool:
    return all(outputs.get(pin) == 200 for pin in PWM_PINS)


def safe(outputs: Mapping[int, int]) -> bool:
    return all(outputs.get(pin) == 0 for pin in (*PWM_PINS, *DIRECTION_PINS))


@pytest.fixture
def rigs() -> Iterator[list[Rig]]:
    started: list[Rig] = []
    yield started
    for rig in started:
        rig.close()


def start_on_simavr(rigs: list[Rig], board: SimavrBoard) -> Rig:
    def hardware(config: AgentConfig, **bus_options: object) -> AgentHardware:
        board.open()
        board.set_analog_input(14, 2.5)  # 7.5 V through the cart's 1:3 divider
        return cart_hardware(board)(config, **bus_options)

    rig = Rig(cart_config(link="simavr://uno"), hardware)
    rigs.append(rig)
    return rig


@pytest.mark.usefixtures("firmware_built")
def test_estop_reaches_the_pins_while_an_exchange_is_blocked_on_a_stalled_board(
    rigs: list[Rig],
) -> None:
    board = simavr_board(timeout_s=0.25, retries=3)
    rig = start_on_simavr(rigs, board)
    rig.run_ticks(0, 5)
    wait_for(lambda: driving(board.read_outputs()), 10, "the cart to drive")
    board.harness.command("mute 1")  # the firmware still executes requests, never answers
    serial = board.serial
    retries = serial.stats.retries
    rig.tick(6)
    wait_for(lambda: serial.stats.retries > retries, 10, "the exchange of tick 6 to hang")
    start = time.perf_counter()
    rig.control(bus.ControlCommand.ESTOP, "test e-stop")
    wait_for(lambda: safe(board.read_outputs()), 5, "the pins to go safe")
    latency = time.perf_counter() - start
    # The exchange of tick 6 is still waiting for its reply (4 x 0.25 s): the e-stop did not
    # wait behind it.
    assert 6 not in rig.answered(), rig.answered()
    assert latency < 0.5, latency  # the figure: benchmarks/estop_latency.py (<= 20 ms)
    wait_for(lambda: rig.state() == "safe", 5, "the agent's safe status")
    assert "e-stop: test e-stop" in rig.statuses[-1]["detail"]
    board.harness.command("mute 0")
    wait_for(lambda: 6 in rig.answered(), 15, "the answer to tick 6")
    assert safe(board.read_outputs())  # latched: reconnecting never un-stops the board
    assert rig.close() == 0


@pytest.mark.usefixtures("firmware_built")
def test_a_stalled_board_degrades_the_agent_which_reconnects_and_rejoins(
    rigs: list[Rig],
) -> None:
    board = simavr_board(timeout_s=0.1, retries=2, reconnect_timeout_s=5.0)
    rig = start_on_simavr(rigs, board)
    rig.run_ticks(0, 5)
    pid = board.harness.process.pid
    os.kill(pid, signal.SIGSTOP)
    try:
        rig.tick(6)
        wait_for(lambda: "degraded" in rig.states(), 10, "the degraded status")
        wait_for(lambda: rig.agent.link_faults == 1, 5, "the link fault to be counted")
        time.sleep(1.0)  # the board stays stalled a while; the agent must stay on the bus
        assert rig.thread.is_alive() and 6 not in rig.answered()
    finally:
        os.kill(pid, signal.SIGCONT)
    wait_for(lambda: 6 in rig.answered(), 15, "the answer to tick 6 once the board is back")
    rig.run_ticks(7, 20)
    assert rig.answered() == list(range(21))
    assert rig.states()[-3:] == ["running", "degraded", "running"], rig.states()
    assert driving(board.read_outputs())  # configuration re-applied, actuating again
    with rig.lock:
        assert rig.liveliness == ["PUT"], rig.liveliness  # never seen as gone
    assert rig.close() == 0
    assert rig.statuses[-1]["link_faults"] == 1, rig.statuses[-1]


@pytest.mark.usefixtures("firmware_built")
def test_a_killed_simulator_is_restarted_and_the_agent_rejoins(rigs: list[Rig]) -> None:
    board = simavr_board(timeout_s=0.1, retries=2, reconnect_timeout_s=2.0)
    rig = start_on_simavr(rigs, board)
    rig.run_ticks(0, 5)
    old_pid = board.harness.process.pid
    os.killpg(old_pid, signal.SIGKILL)
    rig.tick(6)
    wait_for(lambda: "degraded" in rig.states(), 10, "the degraded status")
    wait_for(lambda: 6 in rig.answered(), 20, "the answer to tick 6 on a new simulator")
    assert board.harness.process.pid != old_pid
    rig.run_ticks(7, 20)
    assert rig.answered() == list(range(21))
    assert driving(board.read_outputs())
    assert "safe" not in rig.states(), rig.states()
    assert rig.close() == 0


def socket_board(server: SocketWireServer, reconnect_timeout_s: float) -> SerialBoard:
    return SerialBoard(
        server.url, timeout_s=0.1, retries=1, reconnect_timeout_s=reconnect_timeout_s
    )


def test_an_unplugged_socket_board_coming_back_in_time_is_rejoined(rigs: list[Rig]) -> None:
    server = SocketWireServer(SimBoard(plant=FullBattery(), dt=DT)).start()
    try:
        board = socket_board(server, reconnect_timeout_s=5.0)
        rig = Rig(cart_config(link=server.url), cart_hardware(board))
        rigs.append(rig)
        rig.run_ticks(0, 5)
        server.stop()  # unplugged
        rig.tick(6)
        wait_for(lambda: "degraded" in rig.states(), 10, "the degraded status")
        server.start()  # plugged in again, same port
        wait_for(lambda: 6 in rig.answered(), 15, "the answer to tick 6")
        rig.run_ticks(7, 20)
        assert rig.answered() == list(range(21))
        assert rig.states()[-3:] == ["running", "degraded", "running"], rig.states()
        assert rig.close() == 0
    finally:
        server.stop()


def test_a_link_that_does_not_come_back_in_time_makes_the_agent_safe(rigs: list[Rig]) -> None:
    server = SocketWireServer(SimBoard(plant=FullBattery(), dt=DT)).start()
    board = socket_board(server, reconnect_timeout_s=0.5)
    rig = Rig(cart_config(link=server.url), cart_hardware(board))
    rigs.append(rig)
    rig.run_ticks(0, 5)
    server.stop()
    started = time.monotonic()
    rig.tick(6)
    wait_for(lambda: rig.state() == "safe", 15, "the safe status past the link's timeout")
    assert time.monotonic() - started >= 0.5
    assert rig.states()[-3:] == ["running", "degraded", "safe"], rig.states()
    assert "board link not back" in rig.statuses[-1]["detail"], rig.statuses[-1]
    # Safe, it still answers every tick (no data) at once, without waiting on the dead link.
    rig.run_ticks(6, 12, timeout_s=2.0)
    assert rig.close() == 0


@pytest.mark.usefixtures("firmware_built")
def test_a_stalled_simavr_board_does_not_end_a_realtime_run(
    tmp_path: Path, runs: list[RunProcess]
) -> None:
    """`hilswarm run` with the leader on the real firmware in simavr; its simulator is stopped
    (SIGSTOP) for 2 s mid-run. The leader goes degraded and comes back; nobody is lost; the
    run completes degraded (exit status 3) and its summary says so."""
    run = RunProcess(
        tmp_path,
        REPO / "graphs" / "lead_follow.toml",
        "--no-check",
        "--mode",
        "realtime",
        "--duration",
        "8",
        "--link",
        "leader=simavr://uno",
    )
    runs.append(run)
    spy = connect_spy(run, "lead_follow")
    try:
        pids = run.remember_agents(3)
        leader = next(p for p in pids if agent_name_of(p) == "leader")
        wait_for(lambda: children_running(leader, b"hilswarm-simavr"), 60, "the simulator")
        harness = children_running(leader, b"hilswarm-simavr")[0]
        wait_for(lambda: spy.last_tick() >= 40, 60, "tick 40")
        os.kill(harness, signal.SIGSTOP)
        try:
            time.sleep(2.0)  # the board is stalled for 2 s
        finally:
            os.kill(harness, signal.SIGCONT)
        code = run.wait(60)
    finally:
        spy.close()
    output = run.output()
    recording = read_recording(run.out)
    seen = [m["state"] for m in recording["/leader/status"]]
    leader_states = [s for i, s in enumerate(seen) if i == 0 or seen[i - 1] != s]
    assert "degraded" in leader_states, leader_states
    assert leader_states[leader_states.index("degraded") + 1] == "running", leader_states
    for name in ("leader", "f1", "f2"):
        states = [m["state"] for m in recording[f"/{name}/status"]]
        assert "lost" not in states and states[-2:] == ["safe", "stopped"], (name, states)
    assert recording["/leader/y"][-1]["k"] >= 150, output  # it rejoined and ran to the end
    # The run completed, but the leader went degraded: exit status 3 ("degraded", see
    # docs/running.md, Exit status), and the summary names the agent and its link fault.
    assert code == 3, output
    assert "outcome: degraded (exit status 3)" in output, output
    assert re.search(r"degraded: agent leader degraded \d+ times \(ticks \d+", output), output


@pytest.mark.parametrize("how", ["stop command", "SIGTERM"])
def test_stop_and_sigterm_stop_an_agent_whose_exchange_hangs(rigs: list[Rig], how: str) -> None:
    """A board that never answers (each exchange would wait 11 x 1 s): STOP, or the SIGTERM
    handler's request, still ends the agent within a couple of seconds, outputs safe."""
    sim = SimBoard(plant=FullBattery(), dt=DT)
    server = SocketWireServer(sim).start()
    try:
        board = SerialBoard(server.url, timeout_s=1.0, retries=10, reconnect_timeout_s=5.0)
        rig = Rig(cart_config(link=server.url), cart_hardware(board))
        rigs.append(rig)
        rig.run_ticks(0, 3)
        assert driving(sim.outputs)
        server.server.faults.drop_replies = 10**6
        seen = server.server.stats.requests
        rig.tick(4)
        wait_for(lambda: server.server.stats.requests > seen, 10, "the exchange of tick 4")
        started = time.monotonic()
        if how == "SIGTERM":
            rig.agent.request_stop("signal SIGTERM")  # what the agent's signal handler does
        else:
            rig.control(bus.ControlCommand.STOP, "test stop")
        rig.thread.join(10)
        assert not rig.thread.is_alive()
        assert time.monotonic() - started < 3.0
        assert rig.exit_status == [0]
        wait_for(lambda: rig.states()[-2:] == ["safe", "stopped"], 5, "safe, then stopped")
        assert safe(sim.outputs)  # the e-stop frame still reached the board
    finally:
        server.stop()

"""The gateway in broadcast mode, end to end: agents' boards -> bus -> gateway (packer) ->
simulated coordinator -> one BCAST on the simulated air -> every robot; decimated replies back.

Real Zenoh sessions on loopback, the real gateway on the simulated coordinator's pty, the
protocol-checking Python firmware (``WireServer`` around ``SimBoard``) behind each radio.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack

import pytest
import zenoh
from hilswarm.agents.errors import BoardTimeoutError
from hilswarm.agents.link.board import BoardInfo, BoardStatus, PinConfig, PinMode, TickReply
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.xbee.config import GatewayConfig
from hilswarm.agents.xbee.transport import XBeeBoard
from xbee_rig import Swarm, open_swarm, tick_all, wait_for

EXP = "xbee_bcast_test"
ADDRS = {f"r{i}": 0x0013A20040000010 + i for i in range(1, 4)}
PINS = [
    PinConfig(5, PinMode.PWM),
    PinConfig(7, PinMode.DIGITAL_OUT),
    PinConfig(9, PinMode.SERVO, 1500),
    PinConfig(14, PinMode.ANALOG_IN),
]


class ProtocolOneBoard(SimBoard):
    """A robot whose firmware speaks protocol 1 (no BCAST)."""

    def open(self) -> BoardInfo:
        return dataclasses.replace(super().open(), protocol_version=1)


def _swarm(
    stack: ExitStack,
    client_session: Callable[[], zenoh.Session],
    sims: Mapping[str, SimBoard],
    reply_every: Mapping[str, int],
    answer: str = "wait",
) -> Swarm:
    config = GatewayConfig(port="sim", api_mode=2, mode="broadcast", answer=answer)
    return open_swarm(
        stack,
        client_session,
        EXP,
        ADDRS,
        config,
        seed=5,
        pins=PINS,
        sims=sims,
        reply_every=reply_every,
    )


@pytest.fixture
def swarm(client_session: Callable[[], zenoh.Session]) -> Iterator[Swarm]:
    with ExitStack() as stack:
        sims = {name: SimBoard(dt=0.05) for name in ADDRS}
        yield _swarm(stack, client_session, sims, {"r1": 1, "r2": 2, "r3": 3})


def _tick(
    boards: Mapping[str, XBeeBoard], writes: Mapping[str, dict[int, int]]
) -> dict[str, TickReply | BaseException]:
    return tick_all(boards, writes, [14])


def _writes(k: int, names: list[str]) -> dict[str, dict[int, int]]:
    return {
        n: {5: (10 * k + i) % 256, 7: (k + i) % 2, 9: 1000 + 10 * k + i}
        for i, n in enumerate(names)
    }


def test_one_broadcast_per_tick_each_robot_its_own_outputs_replies_decimated(
    swarm: Swarm,
) -> None:
    _coordinator, gateway, boards, sims = swarm
    names = sorted(boards)
    for i, name in enumerate(names):
        sims[name].set_analog_input(14, 1.0 + i)
    frames_before = gateway.stats.broadcast_frames
    unicast_before = {n: r.tx_frames for n, r in gateway.stats.robots.items()}
    replies: dict[str, list[TickReply]] = {n: [] for n in names}
    ticks = 24
    for k in range(ticks):
        writes = _writes(k, names)
        for name, reply in _tick(boards, writes).items():
            assert isinstance(reply, TickReply), (k, name, reply)
            replies[name].append(reply)
        # every robot drives exactly its own agent's outputs of this tick
        wait_for(
            lambda w=writes: all({p: sims[n].outputs[p] for p in (5, 7, 9)} == w[n] for n in names),
            5.0,
            f"tick {k}'s outputs on every robot",
        )
    # one BCAST per tick (a straggler can make a second one), no unicast TICK
    sent = gateway.stats.broadcast_frames - frames_before
    assert ticks <= sent <= ticks + 4, sent
    assert all(gateway.stats.robots[n].tx_frames == unicast_before[n] for n in names)
    # replies: r1 every tick, r2 every 2nd, r3 every 3rd (round-robin); the rest stale
    for name, every in (("r1", 1), ("r2", 2), ("r3", 3)):
        fresh = [r for r in replies[name] if not r.status & BoardStatus.STALE]
        stale = [r for r in replies[name] if r.status & BoardStatus.STALE]
        assert len(fresh) + len(stale) == ticks
        assert abs(len(fresh) - ticks / every) <= 2, (name, len(fresh))
        for reply in stale:  # a stale reply repeats the last fresh samples and board time
            last = max(
                (r for r in fresh if r.board_time_s <= reply.board_time_s),
                key=lambda r: r.board_time_s,
            )
            assert reply.samples == last.samples and reply.board_time_s == last.board_time_s
        assert gateway.stats.robots[name].stale_replies == len(stale)
        assert boards[name].stats.stale_samples == len(stale)  # counted on the agent's side
    assert abs(replies["r3"][-1].samples[14] - 614) <= 3  # 3.0 V: the robot's own sample


def test_broadcast_robot_out_of_range_times_out_and_the_others_go_on(swarm: Swarm) -> None:
    coordinator, _gateway, boards, _sims = swarm
    names = sorted(boards)
    for k in range(3):
        assert all(isinstance(r, TickReply) for r in _tick(boards, _writes(k, names)).values())
    coordinator.set_loss(ADDRS["r3"], 1.0)  # no broadcast reaches it, its replies are lost
    failed_at = None
    for k in range(3, 20):
        results = _tick(boards, _writes(k, names))
        for name in ("r1", "r2"):
            assert isinstance(results[name], TickReply), (k, name, results[name])
        if isinstance(results["r3"], BoardTimeoutError):
            failed_at = k
            break
        assert isinstance(results["r3"], TickReply)
    assert failed_at is not None  # stale answers stop once r3 misses its reply
    assert failed_at <= 3 + 3  # within one round-robin cycle of reply_every = 3


def test_a_protocol_1_robot_stays_on_unicast(client_session: Callable[[], zenoh.Session]) -> None:
    with ExitStack() as stack:
        sims = {"r1": SimBoard(dt=0.05), "r2": ProtocolOneBoard(dt=0.05)}
        _, gateway, boards, _ = _swarm(stack, client_session, sims, {})
        for k in range(5):
            for reply in _tick(boards, _writes(k, ["r1", "r2"])).values():
                assert isinstance(reply, TickReply)
                assert not reply.status & BoardStatus.STALE  # reply_every 1: always fresh
        assert gateway.stats.robots["r2"].sections == 0
        assert gateway.stats.robots["r2"].tx_frames >= 2 + 5  # HELLO, CONFIG, the TICKs
        assert gateway.stats.robots["r1"].sections >= 5


def test_answer_at_once_every_sample_stale_refreshed_by_the_decimated_replies(
    client_session: Callable[[], zenoh.Session],
) -> None:
    with ExitStack() as stack:
        sims = {name: SimBoard(dt=0.05) for name in ADDRS}
        names = sorted(ADDRS)
        coordinator, _gateway, boards, _ = _swarm(
            stack, client_session, sims, dict.fromkeys(ADDRS, 2), answer="at_once"
        )

        def applied(writes: dict[str, dict[int, int]]) -> None:
            """Pace the ticks to the radio: each robot drives this tick's outputs (at once,
            nothing else would: the answers do not wait for the air)."""
            wait_for(
                lambda: all({p: sims[n].outputs[p] for p in (5, 7, 9)} == writes[n] for n in names),
                5.0,
                "the tick's outputs on every robot",
            )

        sims["r2"].set_analog_input(14, 1.0)
        first = _tick(boards, _writes(0, names))  # the first answer waits for the robot
        assert all(not r.status & BoardStatus.STALE for r in first.values())  # type: ignore[union-attr]
        sims["r2"].set_analog_input(14, 4.0)
        seen: list[int] = []
        for k in range(1, 12):
            replies = _tick(boards, _writes(k, names))
            applied(_writes(k, names))
            for name, reply in replies.items():
                assert isinstance(reply, TickReply), (k, name, reply)
                assert reply.status & BoardStatus.STALE  # never passed off as fresh
            seen.append(replies["r2"].samples[14])  # type: ignore[union-attr]
        assert abs(seen[0] - 205) <= 3  # 1.0 V, taken before the change
        assert abs(seen[-1] - 819) <= 3  # 4.0 V: a later decimated reply refreshed it
        # a robot whose replies stop: its agent is answered no more, times out
        coordinator.set_loss(ADDRS["r3"], 1.0)
        for k in range(12, 40):
            results = _tick(boards, _writes(k, names))
            assert isinstance(results["r1"], TickReply)
            wait_for(lambda k=k: sims["r1"].outputs[5] == _writes(k, names)["r1"][5], 5.0, "r1")
            if isinstance(results["r3"], BoardTimeoutError):
                break
        else:
            raise AssertionError("r3's agent was answered at once forever")


@pytest.mark.parametrize("answer", ["wait", "at_once"])
def test_broadcast_coordinator_unplugged_every_agent_times_out_then_back(
    client_session: Callable[[], zenoh.Session], answer: str
) -> None:
    with ExitStack() as stack:
        sims = {name: SimBoard(dt=0.05) for name in ADDRS}
        coordinator, gateway, boards, _ = _swarm(
            stack, client_session, sims, dict.fromkeys(ADDRS, 3), answer=answer
        )
        names = sorted(boards)
        for k in range(4):
            assert all(isinstance(r, TickReply) for r in _tick(boards, _writes(k, names)).values())
        for board in boards.values():
            board.timeout_s, board.retries = 0.1, 0
        coordinator.unplug()
        wait_for(lambda: not gateway.connected.is_set(), 5.0, "the gateway to notice the unplug")
        results = _tick(boards, _writes(4, names))  # no answers from old samples meanwhile
        assert all(isinstance(r, BoardTimeoutError) for r in results.values()), results
        coordinator.replug()
        wait_for(gateway.connected.is_set, 5.0, "the gateway to reconnect")
        for board in boards.values():
            board.timeout_s, board.retries = 0.3, 3
        for k in range(5, 8):
            assert all(isinstance(r, TickReply) for r in _tick(boards, _writes(k, names)).values())


def test_a_rebooted_robot_recovers_through_its_agents_unicast_retry(swarm: Swarm) -> None:
    coordinator, _gateway, boards, sims = swarm
    names = sorted(boards)
    for k in range(3):
        assert all(isinstance(r, TickReply) for r in _tick(boards, _writes(k, names)).values())
    events: list[str] = []
    boards["r2"].add_link_listener(lambda kind, _detail: events.append(kind))
    coordinator.remotes[ADDRS["r2"]].robot.server.reboot()  # type: ignore[attr-defined]
    for k in range(3, 12):  # its BCAST sections are ignored until it is configured again
        results = _tick(boards, _writes(k, names))
        assert all(isinstance(r, TickReply) for r in results.values()), (k, results)
        if "board_reset" in events:
            break
    assert "board_reset" in events  # the retry went by unicast: NOT_CONFIGURED, re-configured
    writes = _writes(20, names)
    _tick(boards, writes)
    wait_for(lambda: sims["r2"].outputs[5] == writes["r2"][5], 5.0, "r2 driven by broadcast again")

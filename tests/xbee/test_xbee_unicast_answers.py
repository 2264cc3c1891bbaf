"""Unicast answering at once (``[gateway] answer = "at_once"``, ``mode = "unicast"``).

The answerer on its own (pure), then end to end: agents' boards -> bus -> the real gateway ->
simulated coordinator -> air -> the protocol-checking Python firmware behind each radio.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack

import pytest
import zenoh
from hilswarm.agents.errors import BoardTimeoutError
from hilswarm.agents.link.board import BoardStatus, PinConfig, PinMode, TickReply
from hilswarm.agents.link.codec import (
    ConfigEntry,
    ConfigMsg,
    ErrorCode,
    ErrorMsg,
    FrameDecoder,
    PinWrite,
    TickMsg,
    TickReplyMsg,
    encode_message,
    parse_payload,
)
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.xbee.config import GatewayConfig
from hilswarm.agents.xbee.packer import ToAgent, Unicast
from hilswarm.agents.xbee.transport import XBeeBoard
from hilswarm.agents.xbee.unicast_answers import PATIENCE_TICKS, UnicastAnswers
from xbee_rig import Swarm, open_swarm, tick_all, wait_for

# ------------------------------------------------------------------ the answerer alone

WATCHDOG = int(BoardStatus.WATCHDOG_TRIPPED)


def _tick(seq: int, reads: int = 1 << 14, pwm: int = 7) -> bytes:
    return encode_message(TickMsg(seq, 1 << 4, reads, (PinWrite(5, pwm, PinMode.PWM),)))


def _reply(seq: int, samples: tuple[int, ...], status: int = 0, time_us: int = 1000) -> bytes:
    return encode_message(TickReplyMsg(seq, status, time_us, samples))


def _decoded(action: ToAgent | Unicast) -> object:
    (payload,) = FrameDecoder().feed(action.data)
    modes = [PinMode.UNUSED] * 24
    modes[5] = PinMode.PWM
    return parse_payload(payload, modes=modes)


def _answered(answers: UnicastAnswers, seq: int, samples: tuple[int, ...] = (300,)) -> None:
    """A TICK that goes through (its agent waits) and the robot's own reply, forwarded."""
    actions = answers.from_agent("r", _tick(seq), 0.0)
    assert [type(a) for a in actions] == [Unicast], actions
    (forwarded,) = answers.from_robot("r", _reply(seq, samples))
    assert isinstance(forwarded, ToAgent) and not forwarded.stale


def test_the_first_tick_waits_then_every_tick_is_answered_at_once_from_the_newest_samples() -> None:
    answers = UnicastAnswers(["r"])
    _answered(answers, 10, (300,))
    answer, out = answers.from_agent("r", _tick(11, pwm=99), 0.0)  # answered first, then sent
    assert isinstance(answer, ToAgent) and answer.stale
    reply = _decoded(answer)
    assert isinstance(reply, TickReplyMsg) and reply.seq == 11 and reply.samples == (300,)
    assert reply.status & BoardStatus.STALE and reply.board_time_us == 1000
    assert isinstance(out, Unicast) and _decoded(out) == TickMsg(  # the TICK, unchanged
        11, 1 << 4, 1 << 14, (PinWrite(5, 99, PinMode.PWM),)
    )
    assert answers.from_robot("r", _reply(11, (310,), time_us=2000)) == []  # kept, not passed on
    answer, _ = answers.from_agent("r", _tick(12), 0.0)
    reply = _decoded(answer)  # type: ignore[arg-type]
    assert reply.samples == (310,) and reply.board_time_us == 2000  # type: ignore[attr-defined]
    assert answers.stats() == {"r": {"fresh_replies": 2, "asked_again": 0}}


def test_an_event_of_a_reply_no_agent_saw_is_reported_once() -> None:
    answers = UnicastAnswers(["r"])
    _answered(answers, 1)
    answers.from_agent("r", _tick(2), 0.0)
    assert answers.from_robot("r", _reply(2, (300,), status=WATCHDOG)) == []
    first = _decoded(answers.from_agent("r", _tick(3), 0.0)[0])  # type: ignore[arg-type]
    assert first.status & BoardStatus.WATCHDOG_TRIPPED  # type: ignore[attr-defined]
    answers.from_robot("r", _reply(3, (300,)))
    second = _decoded(answers.from_agent("r", _tick(4), 0.0)[0])  # type: ignore[arg-type]
    assert not second.status & BoardStatus.WATCHDOG_TRIPPED  # type: ignore[attr-defined]


def test_a_retry_new_pins_and_a_silent_robot_make_the_agent_wait() -> None:
    answers = UnicastAnswers(["r"])
    _answered(answers, 1)
    assert len(answers.from_agent("r", _tick(2), 0.0)) == 2  # at once
    assert [type(a) for a in answers.from_agent("r", _tick(2), 0.0)] == [Unicast]  # a retry
    answers.from_robot("r", _reply(2, (300,)))  # the retry's reply: its agent's answer
    assert [type(a) for a in answers.from_agent("r", _tick(3, reads=1 << 15), 0.0)] == [Unicast]
    answers.from_robot("r", _reply(3, (5,)))  # now pin 15 is known too
    both = (1 << 14) | (1 << 15)
    answer = answers.from_agent("r", _tick(4, reads=both), 0.0)[0]
    assert _decoded(answer).samples == (300, 5)  # type: ignore[arg-type, attr-defined]
    # the robot goes silent: answered at once for its last PATIENCE_TICKS TICKs, then not
    at_once = [len(answers.from_agent("r", _tick(5 + i), 0.0)) == 2 for i in range(6)]
    assert at_once == [True] * (PATIENCE_TICKS - 1) + [False] * (7 - PATIENCE_TICKS)
    answers.from_robot("r", _reply(10, (301,)))  # a reply again: at once again
    assert len(answers.from_agent("r", _tick(11), 0.0)) == 2
    assert answers.stats()["r"]["asked_again"] == 2 + 7 - PATIENCE_TICKS


def test_a_config_or_an_error_drops_the_samples_and_the_error_reaches_the_agent() -> None:
    answers = UnicastAnswers(["r"])
    _answered(answers, 1)
    config = encode_message(ConfigMsg(2, 300, (ConfigEntry(14, PinMode.ANALOG_IN),)))
    assert [type(a) for a in answers.from_agent("r", config, 0.0)] == [Unicast]
    _answered(answers, 3)  # after a CONFIG the first TICK waits again
    answers.from_agent("r", _tick(4), 0.0)  # answered at once; the robot rebooted meanwhile:
    error = encode_message(ErrorMsg(4, ErrorCode.NOT_CONFIGURED, 0))
    assert answers.from_robot("r", error) == []  # an answered seq: its agent would drop it
    assert [type(a) for a in answers.from_agent("r", _tick(5), 0.0)] == [Unicast]
    (passed,) = answers.from_robot("r", encode_message(ErrorMsg(5, ErrorCode.NOT_CONFIGURED, 0)))
    assert isinstance(passed, ToAgent) and isinstance(_decoded(passed), ErrorMsg)


# ------------------------------------------------------------------ end to end

EXP = "xbee_at_once_test"
ADDRS = {f"r{i}": 0x0013A20040000020 + i for i in range(1, 4)}
PINS = [PinConfig(5, PinMode.PWM), PinConfig(7, PinMode.DIGITAL_OUT)]
PINS += [PinConfig(14, PinMode.ANALOG_IN)]


@pytest.fixture
def swarm(client_session: Callable[[], zenoh.Session]) -> Iterator[Swarm]:
    with ExitStack() as stack:
        config = GatewayConfig(port="sim", api_mode=2, answer="at_once")
        yield open_swarm(stack, client_session, EXP, ADDRS, config, seed=7, pins=PINS)


def _tick_all(
    boards: Mapping[str, XBeeBoard], writes: Mapping[str, dict[int, int]]
) -> dict[str, TickReply | BaseException]:
    return tick_all(boards, writes, [14])


def _writes(k: int, names: list[str]) -> dict[str, dict[int, int]]:
    return {n: {5: (10 * k + i) % 256, 7: (k + i) % 2} for i, n in enumerate(names)}


def _applied(sims: Mapping[str, SimBoard], writes: Mapping[str, dict[int, int]]) -> None:
    """Pace the ticks to the radio: each robot drives this tick's outputs (answered at once,
    nothing else would: the answers do not wait for the air)."""
    wait_for(
        lambda: all({p: sims[n].outputs[p] for p in (5, 7)} == writes[n] for n in writes),
        5.0,
        "the tick's outputs on every robot",
    )


def test_every_tick_answered_at_once_stale_refreshed_by_the_robots_own_replies(
    swarm: Swarm,
) -> None:
    coordinator, gateway, boards, sims = swarm
    names = sorted(boards)
    sims["r2"].set_analog_input(14, 1.0)
    first = _tick_all(boards, _writes(0, names))  # the first answer waits for the robot
    assert all(not r.status & BoardStatus.STALE for r in first.values())  # type: ignore[union-attr]
    sims["r2"].set_analog_input(14, 4.0)
    seen: list[int] = []
    for k in range(1, 8):
        replies = _tick_all(boards, _writes(k, names))
        _applied(sims, _writes(k, names))  # every TICK still reaches its robot
        for name, reply in replies.items():
            assert isinstance(reply, TickReply), (k, name, reply)
            assert reply.status & BoardStatus.STALE  # never passed off as fresh
        seen.append(replies["r2"].samples[14])  # type: ignore[union-attr]
    assert abs(seen[0] - 205) <= 3  # 1.0 V: the reply to tick 0, taken before the change
    assert abs(seen[-1] - 819) <= 3  # 4.0 V: the robot's reply to a later TICK refreshed it
    snapshot = gateway.snapshot()["robots"]
    for name in names:
        assert snapshot[name]["stale_replies"] == 7 and snapshot[name]["fresh_replies"] >= 7
    # a robot out of range: answered at once a few ticks more, then its agent times out
    coordinator.set_out_of_range(ADDRS["r3"])
    for k in range(8, 8 + 3 * PATIENCE_TICKS):
        results = _tick_all(boards, _writes(k, names))
        assert isinstance(results["r1"], TickReply)  # the others go on
        wait_for(lambda k=k: sims["r1"].outputs[5] == _writes(k, names)["r1"][5], 5.0, "r1")
        if isinstance(results["r3"], BoardTimeoutError):
            break
    else:
        raise AssertionError("r3's agent was answered at once forever")
    assert k - 8 <= PATIENCE_TICKS + 1  # (+1: the reply to tick 7 may come after tick 8)
    coordinator.set_out_of_range(ADDRS["r3"], False)
    assert isinstance(boards["r3"].exchange({5: 1, 7: 0}, [14]), TickReply)  # back in range


def test_a_rebooted_robot_is_configured_again_through_its_agents_board(swarm: Swarm) -> None:
    coordinator, _gateway, boards, sims = swarm
    names = sorted(boards)
    for k in range(3):
        assert all(isinstance(r, TickReply) for r in _tick_all(boards, _writes(k, names)).values())
    events: list[str] = []
    boards["r2"].add_link_listener(lambda kind, _detail: events.append(kind))
    coordinator.remotes[ADDRS["r2"]].robot.server.reboot()  # type: ignore[attr-defined]
    for k in range(3, 12):
        results = _tick_all(boards, _writes(k, names))
        assert all(isinstance(r, TickReply) for r in results.values()), (k, results)
        _applied(sims, {n: w for n, w in _writes(k, names).items() if n != "r2"})
        if "board_reset" in events:
            break
    assert "board_reset" in events  # NOT_CONFIGURED reached the board: configured again
    writes = _writes(20, names)
    _tick_all(boards, writes)
    _applied(sims, writes)  # r2 driven again


def test_coordinator_unplugged_no_answer_from_old_samples_then_back(swarm: Swarm) -> None:
    coordinator, gateway, boards, sims = swarm
    names = sorted(boards)
    for k in range(3):
        assert all(isinstance(r, TickReply) for r in _tick_all(boards, _writes(k, names)).values())
    for board in boards.values():
        board.timeout_s, board.retries = 0.1, 0
    coordinator.unplug()
    wait_for(lambda: not gateway.connected.is_set(), 5.0, "the gateway to notice the unplug")
    results = _tick_all(boards, _writes(3, names))  # no stale answers while it is away
    assert all(isinstance(r, BoardTimeoutError) for r in results.values()), results
    coordinator.replug()
    wait_for(gateway.connected.is_set, 5.0, "the gateway to reconnect")
    for board in boards.values():
        board.timeout_s, board.retries = 0.3, 3
    for k in range(4, 7):
        assert all(isinstance(r, TickReply) for r in _tick_all(boards, _writes(k, names)).values())
    _applied(sims, _writes(6, names))

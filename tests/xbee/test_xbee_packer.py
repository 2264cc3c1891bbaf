"""The broadcast packer on its own (pure): sections, rounds, frames, decimation, stale answers."""

from __future__ import annotations

from pathlib import Path

import pytest
from hilswarm.agents.errors import WireFormatError
from hilswarm.agents.link.board import BoardStatus, PinMode
from hilswarm.agents.link.broadcast import SectionLayout
from hilswarm.agents.link.codec import (
    MAX_PAYLOAD,
    BcastMsg,
    BcastReplyMsg,
    ConfigEntry,
    ConfigMsg,
    ConfigReplyMsg,
    FrameDecoder,
    HelloReplyMsg,
    PinWrite,
    TickMsg,
    TickReplyMsg,
    encode_message,
    parse_payload,
)
from hilswarm.agents.xbee.budget import bcast_frame_sizes
from hilswarm.agents.xbee.gateway_process import GatewayPlan, plan_for
from hilswarm.agents.xbee.packer import Broadcast, BroadcastPacker, ToAgent, Unicast
from hilswarm.orchestrator.experiment import load_experiment

FRISBEE = (
    ConfigEntry(4, PinMode.DIGITAL_OUT),
    ConfigEntry(5, PinMode.PWM),
    ConfigEntry(6, PinMode.PWM),
    ConfigEntry(7, PinMode.DIGITAL_OUT),
    ConfigEntry(8, PinMode.DIGITAL_OUT),
    ConfigEntry(12, PinMode.DIGITAL_OUT),
    ConfigEntry(14, PinMode.ANALOG_IN),
)
LAYOUT = SectionLayout.of({e.pin: e.mode for e in FRISBEE})


def test_section_layout_round_trip_and_errors() -> None:
    assert LAYOUT.dout_pins == (4, 7, 8, 12) and LAYOUT.wide_pins == (5, 6)
    assert LAYOUT.length == 3 and LAYOUT.input_pins == (14,)
    data = LAYOUT.encode((1 << 7) | (1 << 12), {5: 200, 6: 7})
    assert data == bytes((0b1010, 200, 7))
    assert LAYOUT.decode(data) == {4: 0, 7: 1, 8: 0, 12: 1, 5: 200, 6: 7}
    servo = SectionLayout.of({9: PinMode.SERVO, 3: PinMode.PWM})
    assert servo.encode(0, {9: 1500, 3: 1}) == bytes((1, 0xDC, 0x05))  # no levels byte
    with pytest.raises(WireFormatError):
        servo.encode(0, {9: 400, 3: 1})
    with pytest.raises(WireFormatError):
        LAYOUT.decode(data[:2])


def _packer(n: int, every: int = 1, answer: str = "wait") -> BroadcastPacker:
    names = [f"r{i:02d}" for i in range(n)]
    packer = BroadcastPacker(
        names, reply_every=dict.fromkeys(names, every), period_s=0.02, answer=answer
    )
    for name in names:  # HELLO reply (protocol 2), CONFIG out and accepted
        packer.from_robot(name, encode_message(HelloReplyMsg(0, 2, 1, 2, 0, 0, (0,) * 20)))
        (out,) = packer.from_agent(name, encode_message(ConfigMsg(1, 300, FRISBEE)), 0.0)
        assert isinstance(out, Unicast)
        config = parse_payload(FrameDecoder().feed(out.data)[0])
        assert isinstance(config, ConfigMsg) and config.bcast_id == names.index(name) + 1
        packer.from_robot(name, encode_message(ConfigReplyMsg(1, 0, len(FRISBEE))))
    return packer


def _tick(seq: int, k: int) -> bytes:
    writes = (PinWrite(5, k % 256, PinMode.PWM), PinWrite(6, 1, PinMode.PWM))
    return encode_message(TickMsg(seq, 1 << 4, 1 << 14, writes))


def _round(packer: BroadcastPacker, k: int, now: float) -> list:
    """Every robot's TICK of tick k at ``now``, then whatever the gathering time sends."""
    actions = []
    for name in packer.robots:
        actions += packer.from_agent(name, _tick(10 + k, k), now)
    return actions + packer.poll(now + packer.gather_s)


def _warm(packer: BroadcastPacker, now: float = 0.98) -> None:
    """A first tick: until every robot has ticked once, none is expected (rounds split)."""
    for action in _round(packer, 99, now):
        if isinstance(action, Broadcast):
            msg = parse_payload(FrameDecoder().feed(action.data)[0])
            for section in msg.sections:
                name = list(packer.robots)[section.board_id - 1]
                packer.from_robot(name, encode_message(BcastReplyMsg(msg.seq, 0, 1, (1,))))


def test_sixteen_frisbees_one_frame_twenty_two_frames() -> None:
    packer = _packer(16)
    _warm(packer)
    actions = _round(packer, 0, 1.0)
    frames = [a for a in actions if isinstance(a, Broadcast)]
    assert len(frames) == 1 and len(frames[0].data) == bcast_frame_sizes([3] * 16)[0] == 86
    msg = parse_payload(FrameDecoder().feed(frames[0].data)[0])
    assert isinstance(msg, BcastMsg) and [s.board_id for s in msg.sections] == list(range(1, 17))
    assert all(s.reply for s in msg.sections)  # reply_every = 1: everyone answers
    packer = _packer(22)
    _warm(packer)
    frames = [a for a in _round(packer, 0, 1.0) if isinstance(a, Broadcast)]
    assert len(frames) == 2 and sum(len(f.names) for f in frames) == 22
    assert all(len(FrameDecoder().feed(f.data)[0]) <= MAX_PAYLOAD for f in frames)


def test_round_robin_replies_and_stale_answers() -> None:
    packer = _packer(5, every=5)
    names = list(packer.robots)
    _warm(packer)
    asked: dict[str, list[int]] = {n: [] for n in names}
    answers: dict[str, list[TickReplyMsg]] = {n: [] for n in names}
    for k in range(10):
        for action in _round(packer, k, 1.0 + k * 0.02):
            if isinstance(action, Broadcast):
                msg = parse_payload(FrameDecoder().feed(action.data)[0])
                assert isinstance(msg, BcastMsg)
                for section in msg.sections:
                    if not section.reply:
                        continue
                    name = names[section.board_id - 1]
                    asked[name].append(k)
                    reply = BcastReplyMsg(msg.seq, 0, 1000 * k, (100 + k,))
                    for out in packer.from_robot(name, encode_message(reply)):
                        assert isinstance(out, ToAgent) and not out.stale
                        answers[name].append(parse_payload(FrameDecoder().feed(out.data)[0]))
            elif isinstance(action, ToAgent):
                assert action.stale
                answers[action.name].append(parse_payload(FrameDecoder().feed(action.data)[0]))
    for name in names:
        assert len(asked[name]) == 2 and asked[name][1] - asked[name][0] == 5  # every 5th
        assert len(answers[name]) == 10
        for reply in answers[name]:  # fresh, or a repeat of the last fresh one (warm-up: 1)
            assert isinstance(reply, TickReplyMsg)
            want = 1 if reply.board_time_us == 1 else 100 + reply.board_time_us // 1000
            assert reply.samples[0] == want
            assert bool(reply.status & BoardStatus.STALE) == (
                reply.board_time_us // 1000 != answers[name].index(reply)
                if reply.board_time_us != 1
                else True
            )
    assert sorted(asked[n][0] for n in names) == [0, 1, 2, 3, 4]  # one reply per tick
    stats = packer.stats()
    assert all(stats[n]["asked_again"] == 0 for n in names)  # every reply came: none re-asked
    assert all(stats[n]["fresh_replies"] == 3 for n in names)  # the warm-up's and two turns


def test_a_missed_reply_stops_the_stale_answers_until_the_robot_answers() -> None:
    packer = _packer(1, every=3)
    name = "r00"
    actions = _round(packer, 0, 1.0)
    (frame,) = [a for a in actions if isinstance(a, Broadcast)]
    seq = parse_payload(FrameDecoder().feed(frame.data)[0]).seq
    (fresh,) = packer.from_robot(
        name, encode_message(BcastReplyMsg(seq, BoardStatus.WATCHDOG_TRIPPED, 5, (7,)))
    )
    assert isinstance(fresh, ToAgent) and not fresh.stale
    stale = [a for a in _round(packer, 1, 1.02) if isinstance(a, ToAgent)]
    reply = parse_payload(FrameDecoder().feed(stale[0].data)[0])
    assert reply.status == BoardStatus.STALE  # the event is not repeated
    # round 3 is its turn (r + 0) % 3 == 0; it never answers: round 4 asks again, no answer
    for k in (2, 3, 4):
        actions = _round(packer, k, 1.0 + 0.02 * k)
    assert not [a for a in actions if isinstance(a, ToAgent)]
    (frame,) = [a for a in actions if isinstance(a, Broadcast)]
    assert parse_payload(FrameDecoder().feed(frame.data)[0]).sections[0].reply
    # rounds 4 and 5 asked it out of turn (counted), its own reply of round 1 the only one
    assert packer.stats()[name] == {"bcast_id": 1, "fresh_replies": 1, "asked_again": 2}


def test_a_tick_that_cannot_be_packed_goes_by_unicast() -> None:
    packer = _packer(2)
    odd = encode_message(TickMsg(3, 0, 0, (PinWrite(5, 1, PinMode.PWM),)))  # PWM 6 not written
    (action,) = packer.from_agent("r00", odd, 1.0)
    assert isinstance(action, Unicast) and action.data == odd


def test_a_straggler_waits_at_most_the_gathering_time() -> None:
    packer = _packer(2)
    _warm(packer, 1.0)  # both robots ticked: both expected now
    assert packer.from_agent("r00", _tick(20, 1), 1.02) == []  # waits for r01
    assert packer.due(1.02) == pytest.approx(1.03)
    assert packer.poll(1.025) == []
    (frame,) = [a for a in packer.poll(1.031) if isinstance(a, Broadcast)]
    assert frame.names == ("r00",)


def test_the_broadcast_demo_plans_its_gateway_with_mode_rate_and_reply_every() -> None:
    demo = Path(__file__).resolve().parents[2] / "graphs" / "xbee_swarm_broadcast.toml"
    plan = plan_for(load_experiment(demo))
    assert plan is not None and GatewayPlan.from_json(plan.to_json()) == plan
    assert plan.config["mode"] == "broadcast" and plan.rate_hz == 50.0
    assert set(plan.reply_every.values()) == {5} and len(plan.reply_every) == 6

"""The radio budget check: figures, thresholds and the messages of `hilswarm check`."""

from __future__ import annotations

from pathlib import Path

import pytest
from hilswarm.agents.link.board import PinConfig, PinMode
from hilswarm.agents.xbee.air import AirParams
from hilswarm.agents.xbee.budget import (
    HOST_ALLOWANCE_S,
    RobotTraffic,
    broadcast_budget,
    budget_messages,
    gateway_budget,
    latency_messages,
    section_size,
    tick_frame_sizes,
    tick_latency,
)
from hilswarm.orchestrator.checks import check_file

REPO = Path(__file__).resolve().parents[2]
FRISBEE = [
    PinConfig(7, PinMode.DIGITAL_OUT),
    PinConfig(8, PinMode.DIGITAL_OUT),
    PinConfig(4, PinMode.DIGITAL_OUT),
    PinConfig(12, PinMode.DIGITAL_OUT),
    PinConfig(5, PinMode.PWM),
    PinConfig(6, PinMode.PWM),
    PinConfig(14, PinMode.ANALOG_IN),
]


def test_frame_sizes_by_hand() -> None:
    # TICK: type, seq, dout u24, rmask u24, 2 x (pin, duty) = 12 B, CRC 2, COBS 1, delimiter 1
    # reply: type, seq, status, time u32, 1 sample u16 = 9 B + 4
    assert tick_frame_sizes(FRISBEE) == (16, 13)


def test_unicast_budget_matches_the_issue_figures() -> None:
    request, reply = tick_frame_sizes(FRISBEE)
    robots = [RobotTraffic(f"r{i}", request, reply) for i in range(6)]
    budget = gateway_budget(robots, rate_hz=20.0)
    p = AirParams()
    assert budget.air_s == pytest.approx(6 * (p.mean_unicast_s(16) + p.mean_unicast_s(13)))
    assert budget.uart_out_s == pytest.approx(6 * (15 + 16) * 10 / 115200)
    assert budget.uart_in_s == pytest.approx(6 * (15 + 13 + 7) * 10 / 115200)
    # about 6 robots at 20 Hz fit by unicast: 6 fit (with a warning), 8 do not
    errors, warnings = budget_messages(budget)
    assert not errors and len(warnings) == 1 and warnings[0].startswith("XBee air")
    errors, _ = budget_messages(gateway_budget(robots + robots[:2], rate_hz=20.0))
    assert errors and "at most 7 robots" in errors[0]


def test_overflow_message_says_what_by_how_much_and_what_to_change() -> None:
    robots = [RobotTraffic(f"r{i}", 16, 13) for i in range(16)]
    errors, _ = budget_messages(gateway_budget(robots, rate_hz=50.0, baud=9600))
    text = "\n".join(errors)
    assert "XBee air" in text and "XBee host UART out" in text and "XBee host UART in" in text
    assert "over by" in text and "rate_hz <=" in text and "robots on this coordinator" in text
    errors, _ = budget_messages(
        gateway_budget([RobotTraffic(f"r{i}", 16, 13) for i in range(4)], rate_hz=50, baud=57600)
    )
    assert any("UART" in e and "[gateway] baud = 115200" in e for e in errors), errors


def test_small_swarm_passes_quietly() -> None:
    assert budget_messages(gateway_budget([RobotTraffic("a", 16, 13)], rate_hz=20.0)) == ([], [])


def test_check_fails_an_experiment_over_budget(tmp_path: Path) -> None:
    text = (REPO / "graphs" / "xbee_swarm.toml").read_text()
    path = tmp_path / "fast.toml"
    path.write_text(text.replace("rate_hz = 20.0", "rate_hz = 50.0"))
    report = check_file(path)
    assert [p.key for p in report.problems] == ["gateway"]
    assert "XBee air" in report.problems[0].message
    assert check_file(REPO / "graphs" / "xbee_swarm.toml").ok


def test_check_reports_bad_xbee_links_and_shared_addresses(tmp_path: Path) -> None:
    text = (REPO / "graphs" / "xbee_swarm.toml").read_text()
    path = tmp_path / "bad.toml"
    path.write_text(
        text.replace("xbee://0013A20040000002", "xbee://0013A20040000001").replace(
            "xbee://0013A20040000003?sim=sim://duemilanove", "xbee://nothex"
        )
    )
    messages = [p.message for p in check_file(path).problems]
    assert any("also agent 'leader'" in m for m in messages)
    assert any("expected xbee://<64-bit address>" in m for m in messages)


def test_bad_gateway_table(tmp_path: Path) -> None:
    text = (REPO / "graphs" / "xbee_swarm.toml").read_text()
    path = tmp_path / "bad.toml"
    path.write_text(text.replace("api_mode = 2 ", "api_mode = 3 "))
    problems = check_file(path).problems
    assert any(
        p.key == "gateway.api_mode" and "3 is not one of 1, 2" in p.message for p in problems
    )


def test_broadcast_budget_of_sixteen_frisbees_at_50_hz() -> None:
    request, reply = tick_frame_sizes(FRISBEE)
    assert section_size(FRISBEE) == 3  # levels of 4 DIGITAL_OUT in one byte, 2 PWM duties
    robots = [RobotTraffic(f"r{i}", request, reply, 3, 5) for i in range(16)]
    budget = broadcast_budget(robots, rate_hz=50.0)
    p = AirParams()
    assert budget.frames == 1 and budget.replies == 4  # one 86 B frame; ceil(16 / 5) replies
    assert budget.air_s == pytest.approx(p.mean_broadcast_s(86) + 4 * p.mean_unicast_s(13))
    assert budget.uart_out_s == pytest.approx((15 + 86) * 10 / 115200)  # no TX Status back
    assert budget.uart_in_s == pytest.approx(4 * (15 + 13) * 10 / 115200)
    errors, warnings = budget_messages(budget)
    assert not errors and len(warnings) == 1 and "by packed broadcast" in warnings[0]
    assert budget.fractions()["air"] == pytest.approx(0.92, abs=0.01)
    # every robot answering every tick does not fit; the message says which reply_every does
    robots = [RobotTraffic(f"r{i}", request, reply, 3, 1) for i in range(16)]
    errors, _ = budget_messages(broadcast_budget(robots, rate_hz=50.0))
    assert errors and "a larger reply_every with reply_every = 5" in errors[0]


def test_unicast_overflow_suggests_the_packed_broadcast() -> None:
    request, reply = tick_frame_sizes(FRISBEE)
    robots = [RobotTraffic(f"r{i}", request, reply, 3) for i in range(16)]
    errors, _ = budget_messages(gateway_budget(robots, rate_hz=50.0))
    assert all('[gateway] mode = "broadcast" with reply_every = 5' in e for e in errors), errors


def test_check_broadcast_demo_and_reply_every_rules(tmp_path: Path) -> None:
    assert check_file(REPO / "graphs" / "xbee_swarm_broadcast.toml").ok
    text = (REPO / "graphs" / "xbee_swarm.toml").read_text()
    path = tmp_path / "decimated_unicast.toml"
    path.write_text(text.replace('vehicle = "frisbee"', 'vehicle = "frisbee"\nreply_every = 3'))
    report = check_file(path)
    keys = sorted(p.key for p in report.problems)
    assert keys == [f"agents.{n}.reply_every" for n in ("f1", "f2", "f3", "f4", "f5", "leader")]
    assert 'needs [gateway] mode = "broadcast"' in report.problems[0].message
    path = tmp_path / "not_xbee.toml"
    path.write_text(
        (REPO / "graphs" / "lead_follow.toml")
        .read_text()
        .replace("[agents.leader]", "[agents.leader]\nreply_every = 2", 1)
    )
    report = check_file(path)
    assert [p.key for p in report.problems] == ["agents.leader.reply_every"]
    assert "only for xbee:// links" in report.problems[0].message


def test_tick_latency_by_hand() -> None:
    """The stages one after the other (docs/xbee.md: 8.5 ms + 6.75 ms per robot by unicast)."""
    request, reply = tick_frame_sizes(FRISBEE)  # 16 B, 13 B
    p = AirParams()
    per_robot = p.mean_unicast_s(16) + p.mean_unicast_s(13)
    assert per_robot == pytest.approx(6.752e-3, abs=1e-6)  # 3.424 ms + 3.328 ms of air
    # first TX frame (15 + 16 B), the robot's UART both ways (16 B; 13 B + 3 quiet characters
    # of its radio's packetization), the last RX frame and its TX Status (15 + 13 + 7 B)
    fixed = (15 + 16 + 16 + 13 + 3 + 15 + 13 + 7) * 10 / 115200
    assert fixed == pytest.approx(8.507e-3, abs=1e-6)
    for n in (1, 4, 6):
        robots = [RobotTraffic(f"r{i}", request, reply) for i in range(n)]
        latency = tick_latency(gateway_budget(robots, rate_hz=20.0))
        assert latency.waits_for == "answers"
        assert latency.radio_s == pytest.approx(fixed + n * per_robot)
        assert latency.total_s == pytest.approx(latency.radio_s + HOST_ALLOWANCE_S)
        # answering at once: up to the last robot's TICK through its UART, every other
        # robot's reply on the air before it (the worst order)
        at_once = tick_latency(gateway_budget(robots, rate_hz=20.0), answer="at_once")
        outputs = (15 + 16 + 16) * 10 / 115200 + n * p.mean_unicast_s(16)
        outputs += (n - 1) * p.mean_unicast_s(13)
        assert at_once.waits_for == "outputs" and at_once.radio_s == pytest.approx(outputs)
    six = tick_latency(
        gateway_budget([RobotTraffic(f"r{i}", request, reply) for i in range(6)], rate_hz=20.0),
        answer="at_once",
    )
    assert six.radio_s == pytest.approx(41.3e-3, abs=0.05e-3)  # docs/xbee.md
    # 16 Frisbees by broadcast: one 86 B BCAST through the host UART, the air and a robot's UART
    robots = [RobotTraffic(f"r{i}", request, reply, 3, 5) for i in range(16)]
    budget = broadcast_budget(robots, rate_hz=50.0)
    outputs = (15 + 86) * 10 / 115200 + p.mean_broadcast_s(86) + 86 * 10 / 115200
    at_once = tick_latency(budget, answer="at_once")
    assert at_once.waits_for == "outputs" and at_once.radio_s == pytest.approx(outputs)
    assert at_once.radio_s == pytest.approx(21.35e-3, abs=0.01e-3)  # docs/xbee.md
    # waiting for the replies: then the reply's UART, the 4 replies of the busiest tick, an RX
    wait = tick_latency(budget)
    replies = (13 + 3) * 10 / 115200 + 4 * p.mean_unicast_s(13) + (15 + 13) * 10 / 115200
    assert wait.radio_s == pytest.approx(outputs + replies)
    assert wait.radio_s == pytest.approx(38.48e-3, abs=0.01e-3)  # docs/xbee.md


def test_latency_warns_what_to_change() -> None:
    request, reply = tick_frame_sizes(FRISBEE)
    unicast = [RobotTraffic(f"r{i}", request, reply, 3) for i in range(6)]
    (message,) = latency_messages(gateway_budget(unicast, rate_hz=20.0))
    assert "~51.0 ms" in message and "102% of the 50.0 ms period" in message, message
    assert "every tick will be late" in message, message
    assert '[gateway] mode = "broadcast" with reply_every = 5' in message, message
    assert "at most 4 robots on this coordinator" in message, message
    assert latency_messages(gateway_budget(unicast[:4], rate_hz=20.0)) == []  # 75 %: room
    # answering at once by unicast: 4 robots fit (27.8 + 2 ms: 60 %), so 5 waiting are told
    (message,) = latency_messages(gateway_budget(unicast[:5], rate_hz=20.0))
    assert message.count("at_once") == 1 and '[gateway] answer = "at_once" (' in message
    assert latency_messages(gateway_budget(unicast[:4], rate_hz=20.0), answer="at_once") == []
    (message,) = latency_messages(gateway_budget(unicast, rate_hz=20.0), answer="at_once")
    assert "for 6 robots by unicast answering at once" in message, message
    assert "expect some ticks' outputs to reach robots after the next tick" in message
    packed = [RobotTraffic(f"r{i}", request, reply, 3, 5) for i in range(16)]
    budget = broadcast_budget(packed, rate_hz=50.0)
    (message,) = latency_messages(budget)  # waiting for the replies: 38.5 ms of 20
    assert 'answer = "at_once"' not in message  # it does not fit either (21.4 ms)
    (message,) = latency_messages(budget, answer="at_once")
    assert "until every robot drives the tick's outputs" in message, message
    assert "outputs will reach the robots after the next tick is due" in message, message
    assert "at most 8 robots on this coordinator" in message, message
    six = broadcast_budget(packed[:6], rate_hz=50.0)
    (message,) = latency_messages(six)
    assert '[gateway] answer = "at_once" (65% of the period)' in message, message
    assert latency_messages(six, answer="at_once") == []


def test_check_warns_of_latency_in_realtime_only(tmp_path: Path) -> None:
    demo = REPO / "graphs" / "xbee_swarm.toml"  # 6 robots by unicast at 20 Hz, lockstep
    report = check_file(demo)
    assert report.ok and not [w for w in report.warnings if "XBee latency" in w.message]
    path = tmp_path / "xbee_swarm_realtime.toml"
    path.write_text(demo.read_text().replace('mode = "lockstep"', 'mode = "realtime"'))
    report = check_file(path)
    assert report.ok  # a warning, not a problem: the run goes, its late ticks are counted
    (latency,) = [w for w in report.warnings if "XBee latency" in w.message]
    assert latency.key == "gateway" and "every tick will be late" in latency.message

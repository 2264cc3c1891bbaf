"""The gateway's stage times in the latency ledger: each answer carries the gateway's own time
and the radio's (agents/xbee/stages.py); the agent's board keeps those of its last exchange.

Real Zenoh sessions on loopback, the real gateway on the simulated coordinator's pty, the
protocol-checking Python firmware (``WireServer`` around ``SimBoard``) behind each radio, in
unicast and in both broadcast answer modes.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack

import pytest
import zenoh
from hilswarm.agents.errors import BoardTimeoutError
from hilswarm.agents.link.board import BoardStatus, PinConfig, PinMode, TickReply
from hilswarm.agents.xbee.air import uart_s
from hilswarm.agents.xbee.config import GatewayConfig
from hilswarm.agents.xbee.gateway import Gateway
from hilswarm.agents.xbee.stages import decode_stages, encode_stages
from hilswarm.agents.xbee.transport import XBeeBoard
from xbee_rig import open_swarm

EXP = "xbee_ledger_test"
ADDRS = {f"r{i}": 0x0013A20040000020 + i for i in range(1, 3)}
PINS = [
    PinConfig(5, PinMode.PWM),
    PinConfig(7, PinMode.DIGITAL_OUT),
    PinConfig(14, PinMode.ANALOG_IN),
]
BAUD = 115200


def _swarm(
    stack: ExitStack,
    client_session: Callable[[], zenoh.Session],
    mode: str,
    answer: str = "wait",
) -> tuple[Gateway, dict[str, XBeeBoard]]:
    config = GatewayConfig(port="sim", api_mode=2, baud=BAUD, mode=mode, answer=answer)
    swarm = open_swarm(
        stack,
        client_session,
        EXP,
        ADDRS,
        config,
        seed=7,
        pins=PINS,
        reply_every=dict.fromkeys(ADDRS, 3),
        link_options="timeout_s=0.5&retries=2",
    )
    return swarm.gateway, swarm.boards


@pytest.fixture(params=["unicast", "unicast-at_once", "broadcast-wait", "broadcast-at_once"])
def swarm(
    client_session: Callable[[], zenoh.Session], request: pytest.FixtureRequest
) -> Iterator[tuple[str, Gateway, dict[str, XBeeBoard]]]:
    mode, _, answer = str(request.param).partition("-")
    with ExitStack() as stack:
        gateway, boards = _swarm(stack, client_session, mode, answer or "wait")
        yield str(request.param), gateway, boards


def _tick(
    boards: Mapping[str, XBeeBoard], k: int
) -> dict[str, tuple[TickReply, float, tuple[float, float]]]:
    """Every board's exchange of tick ``k`` at once (as the agents' processes do): per board
    its reply, the round trip measured around the exchange [s] and its stage times."""
    out: dict[str, tuple[TickReply, float, tuple[float, float]]] = {}
    errors: list[BaseException] = []

    def run(name: str) -> None:
        try:
            start = time.monotonic()
            reply = boards[name].exchange({5: (10 * k) % 256, 7: k % 2}, [14])
            elapsed = time.monotonic() - start
            out[name] = (reply, elapsed, boards[name].take_link_stages())
        except Exception as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(n,)) for n in boards]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=10.0)
    assert not errors, errors
    assert len(out) == len(boards), "an exchange did not finish"
    return out


def test_the_stage_attachment_round_trips() -> None:
    gateway_s, radio_s = decode_stages(encode_stages(0.0015, 0.0123)) or (0.0, 0.0)
    assert gateway_s == pytest.approx(0.0015, rel=1e-6)
    assert radio_s == pytest.approx(0.0123, rel=1e-6)
    assert decode_stages(None) is None
    assert decode_stages(b"\x00" * 3) is None  # another size: no stage times


def test_every_answer_carries_the_gateway_and_radio_time_within_the_round_trip(
    swarm: tuple[str, Gateway, dict[str, XBeeBoard]],
) -> None:
    kind, _gateway, boards = swarm
    for board in boards.values():
        assert board.take_link_stages() == (0.0, 0.0)  # HELLO, CONFIG: no exchange yet
    # the radio's least time for an answer it carries: the TICK (>= 10 B) and its reply
    # (>= 8 B) through the 115200-baud host UART alone
    least_radio_s = uart_s(10 + 8, BAUD)
    fresh = stale = 0
    for k in range(12):
        for name, (reply, elapsed, (gateway_s, radio_s)) in _tick(boards, k).items():
            where = (kind, k, name, reply.status, elapsed, gateway_s, radio_s)
            assert math.isfinite(gateway_s) and math.isfinite(radio_s), where
            assert gateway_s > 0.0, where
            assert gateway_s + radio_s <= elapsed, where  # the bus hops take the rest
            if reply.status & BoardStatus.STALE:  # the gateway's own answer: no radio
                stale += 1
                assert radio_s == 0.0, where
            else:
                fresh += 1
                assert radio_s >= least_radio_s, where
    if kind == "unicast":
        assert stale == 0 and fresh == 24
    elif kind == "broadcast-wait":  # reply_every = 3: a third answered by the robots
        assert fresh >= 6 and stale >= 12, (fresh, stale)
    elif kind == "unicast-at_once":  # ticks back to back, faster than the radio: every few
        # TICKs the robot's replies are behind and its agent waits for one (PATIENCE_TICKS)
        assert stale >= 12, (fresh, stale)
    else:  # broadcast at once: every answer the gateway's (after each robot's first reply)
        assert stale >= 20, (fresh, stale)
    for board in boards.values():
        assert board.take_link_stages() == (0.0, 0.0)  # taken: none until the next exchange


def test_an_exchange_without_an_answer_has_no_stage_times(
    client_session: Callable[[], zenoh.Session],
) -> None:
    with ExitStack() as stack:
        gateway, boards = _swarm(stack, client_session, "unicast")
        board = boards["r1"]
        board.exchange({5: 1, 7: 0}, [14])
        assert all(math.isfinite(s) for s in board.take_link_stages())
        gateway.stop()  # nobody answers any more
        board.timeout_s = 0.05
        board.retries = 0
        with pytest.raises(BoardTimeoutError):
            board.exchange({5: 2, 7: 0}, [14])
        assert all(math.isnan(s) for s in board.take_link_stages())

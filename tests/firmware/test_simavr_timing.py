"""Simulated-time facts of the simavr UART wire (``firmware/simavr/README.md``, "Timing").

The harness must behave like a real 115200-baud 8N1 line in both directions: every byte takes
at least 10 bits / 115200 baud = 86.8 µs of *simulated* time, and none is dropped. These tests
assert only simulated-time facts (the harness's ``state`` clock ``t_us`` and the firmware's own
``board_time_us``), never wall-clock speed, so a busy machine cannot make them fail. The one
wall-clock check is one-sided (paced simulated time is never *ahead* of the wall clock), which
load can only make easier to meet.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from hilswarm.agents.link.board import BoardStatus, PinMode
from hilswarm.agents.link.codec import (
    ConfigEntry,
    ConfigMsg,
    ConfigReplyMsg,
    FrameDecoder,
    HelloMsg,
    HelloReplyMsg,
    Message,
    PinWrite,
    TickMsg,
    TickReplyMsg,
    encode_message,
    parse_payload,
)
from hilswarm.agents.link.simavr import SimavrHarness

pytestmark = pytest.mark.firmware

#: Simulated time one 8N1 byte takes on the wire at 115200 baud [µs].
BYTE_US = 10 / 115200 * 1e6
#: The thesis Blimpduino-like pin set: 6 digital outputs, 2 PWM, 1 servo, 1 analog input.
DOUT = (2, 4, 7, 8, 12, 13)
CONFIG = ConfigMsg(
    1,
    0,
    (
        *(ConfigEntry(p, PinMode.DIGITAL_OUT) for p in DOUT),
        ConfigEntry(5, PinMode.PWM),
        ConfigEntry(6, PinMode.PWM),
        ConfigEntry(9, PinMode.SERVO, 1500),
        ConfigEntry(14, PinMode.ANALOG_IN),
    ),
)
#: Seconds a test waits for replies (wall clock; generous: the machine may be busy).
REPLY_TIMEOUT_S = 10.0


def tick(seq: int) -> bytes:
    """Wire frame of a Blimpduino-like TICK: 19 bytes, answered by a 13-byte reply."""
    writes = (
        PinWrite(5, (seq * 7) % 256, PinMode.PWM),
        PinWrite(6, 40, PinMode.PWM),
        PinWrite(9, 1000 + (seq * 11) % 1000, PinMode.SERVO),
    )
    dout = sum(1 << p for i, p in enumerate(DOUT) if (seq + i) % 2)
    return encode_message(TickMsg(seq, dout, 1 << 14, writes))


@pytest.fixture(params=[False, True], ids=["unpaced", "paced"])
def link(
    firmware_built: Path, request: pytest.FixtureRequest
) -> Iterator[tuple[SimavrHarness, serial.Serial]]:
    """A running harness and its pty, the Blimpduino-like pins configured."""
    harness = SimavrHarness("uno", paced=request.param)
    port = None
    try:
        port = serial.Serial(harness.start(), 115200, timeout=0.02)
        hello = read_replies(port, encode_message(HelloMsg(0)), 1)
        assert isinstance(hello[0], HelloReplyMsg)
        configured = read_replies(port, encode_message(CONFIG), 1)
        assert isinstance(configured[0], ConfigReplyMsg), configured
        yield harness, port
    finally:
        if port is not None:
            port.close()
        harness.stop()


def read_replies(port: serial.Serial, frames: bytes, count: int) -> list[Message]:
    """Write ``frames``; return the first ``count`` replies (fails after REPLY_TIMEOUT_S)."""
    port.write(frames)
    decoder = FrameDecoder()
    replies: list[Message] = []
    deadline = time.monotonic() + REPLY_TIMEOUT_S
    while len(replies) < count:
        assert time.monotonic() < deadline, f"only {len(replies)} of {count} replies arrived"
        replies += [parse_payload(p) for p in decoder.feed(port.read(256))]
    return replies


def test_a_tick_takes_at_least_its_wire_time(link: tuple[SimavrHarness, serial.Serial]) -> None:
    harness, port = link
    request = tick(2)
    assert len(request) == 19
    start_us = harness.state()["t_us"]
    port.write(request)
    decoder = FrameDecoder()
    received = 0
    replies: list[Message] = []
    samples: list[tuple[int, int]] = []  # (reply bytes read so far, simulated time after that)
    deadline = time.monotonic() + REPLY_TIMEOUT_S
    while not replies:
        assert time.monotonic() < deadline, "no reply"
        chunk = port.read(port.in_waiting or 1)
        received += len(chunk)
        replies += [parse_payload(p) for p in decoder.feed(chunk)]
        samples.append((received, harness.state()["t_us"]))
    assert isinstance(replies[0], TickReplyMsg) and replies[0].seq == 2
    assert replies[0].status == BoardStatus.OK
    assert received == len(encode_message(replies[0])) == 13
    # Every reply byte read by then must have been on the wire after the whole request: the
    # k-th byte cannot arrive before (19 + k) byte times after the request started.
    for count, t_us in samples:
        if count:
            assert t_us - start_us >= (len(request) + count) * BYTE_US, (count, t_us - start_us)


def test_a_burst_beyond_the_uart_fifo_arrives_whole_at_wire_speed(
    link: tuple[SimavrHarness, serial.Serial],
) -> None:
    harness, port = link
    burst = [tick(seq) for seq in range(10, 22)]  # 12 x 19 = 228 bytes, more than any FIFO
    start_us = harness.state()["t_us"]
    replies = read_replies(port, b"".join(burst), len(burst))
    end_us = harness.state()["t_us"]
    assert [r.seq for r in replies] == list(range(10, 22))
    assert all(isinstance(r, TickReplyMsg) and r.status == BoardStatus.OK for r in replies), (
        replies
    )  # no RX_ERRORS: not a byte lost or damaged
    assert end_us - start_us >= (sum(map(len, burst)) + 13) * BYTE_US
    # The firmware's own clock: a request is handled when its last byte is in, so consecutive
    # requests of 19 bytes are at least 19 byte times apart (one byte time of slack for the
    # firmware loop's jitter).
    board_times = [r.board_time_us for r in replies if isinstance(r, TickReplyMsg)]
    gaps = [b - a for a, b in itertools.pairwise(board_times)]
    assert min(gaps) >= 18 * BYTE_US, gaps


def test_paced_simulated_time_never_runs_ahead_of_the_wall_clock(firmware_built: Path) -> None:
    harness = SimavrHarness("uno", paced=True)
    before_start = time.monotonic()
    try:
        harness.start()
        for _ in range(200):
            t_us = harness.state()["t_us"]
            assert t_us <= (time.monotonic() - before_start) * 1e6
    finally:
        harness.stop()

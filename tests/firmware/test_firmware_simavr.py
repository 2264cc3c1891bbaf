"""The real firmware (the ELF flashed to an Uno) in simavr, over the wire protocol.

Needs avr-gcc and libsimavr (``scripts/setup.sh`` installs them); the firmware and harness are
built here with ``make -C firmware all`` when missing. Skipped, with the reason, only when the
toolchain itself is absent.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from hilswarm.agents.errors import BoardRequestError, SimulatorError
from hilswarm.agents.link.board import (
    PROTOCOL_VERSION,
    BoardStatus,
    Capability,
    ErrorCode,
    PinConfig,
    PinMode,
)
from hilswarm.agents.link.broadcast import SectionLayout
from hilswarm.agents.link.codec import (
    BcastMsg,
    BcastReplyMsg,
    BcastSection,
    ErrorMsg,
    FrameDecoder,
    HelloMsg,
    HelloReplyMsg,
    Message,
    encode_message,
    frame_payload,
    parse_payload,
)
from hilswarm.agents.link.simavr import SimavrBoard, SimavrHarness

pytestmark = pytest.mark.firmware

UNO_CAPS = (0x80, 0x80, 0x03, 0x07, 0x03, 0x07, 0x07, 0x03, 0x03, 0x0F, 0x0F, 0x07, 0x03,
            0x03, 0x13, 0x13, 0x13, 0x13, 0x13, 0x13)  # fmt: skip
BLIMP = [
    *(PinConfig(p, PinMode.DIGITAL_OUT, 0) for p in (2, 4, 7, 8, 12)),
    PinConfig(13, PinMode.DIGITAL_OUT, 1),
    PinConfig(5, PinMode.PWM, 0),
    PinConfig(6, PinMode.PWM, 0),
    PinConfig(9, PinMode.SERVO, 1500),
    PinConfig(3, PinMode.DIGITAL_IN),
    PinConfig(14, PinMode.ANALOG_IN),
]
BLIMP_WRITES = {2: 1, 4: 0, 7: 1, 8: 0, 12: 1, 13: 0, 5: 200, 6: 17, 9: 1800}
SAFE_OUTPUTS = {2: 0, 4: 0, 7: 0, 8: 0, 12: 0, 13: 1, 5: 0, 6: 0, 9: 1500}


@pytest.fixture
def board(firmware_built: Path) -> Iterator[SimavrBoard]:
    sim = SimavrBoard("uno", timeout_s=0.5, retries=2)
    try:
        sim.open()
        yield sim
    finally:
        sim.close()
    assert sim.harness.process is None


@pytest.fixture
def raw(firmware_built: Path) -> Iterator[tuple[SimavrHarness, serial.Serial]]:
    """The harness and its pty opened with plain pyserial, for byte-level tests."""
    harness = SimavrHarness("uno")
    port = None
    try:
        port = serial.Serial(harness.start(), 115200, timeout=0.05)
        yield harness, port
    finally:
        if port is not None:
            port.close()
        harness.stop()


def roundtrip(port: serial.Serial, frame: bytes, *, timeout_s: float = 2.0) -> list[Message]:
    """Write ``frame``; return every reply decoded until one arrives (or the timeout)."""
    port.write(frame)
    decoder = FrameDecoder()
    deadline = time.monotonic() + timeout_s
    replies: list[Message] = []
    while time.monotonic() < deadline and not replies:
        replies += [parse_payload(p) for p in decoder.feed(port.read(64))]
    return replies


def wait_sim_time(board: SimavrBoard, seconds: float, *, wall_limit_s: float = 20.0) -> None:
    """Let ``seconds`` of simulated time pass with no frame on the link (polls ``state``)."""
    start = board.harness.state()["t_us"]
    deadline = time.monotonic() + wall_limit_s
    while board.harness.state()["t_us"] - start < seconds * 1e6:
        assert time.monotonic() < deadline, "simulated time does not advance"


def test_hello_reports_version_capabilities_and_boot(board: SimavrBoard) -> None:
    info = board.info
    assert info.protocol_version == PROTOCOL_VERSION
    assert info.firmware_version >= (1, 0)
    assert tuple(int(c) for c in info.capabilities) == UNO_CAPS
    assert info.capabilities[0] == Capability.RESERVED
    serial_board = board.serial
    assert serial_board is not None
    assert serial_board.last_status & BoardStatus.RESET
    assert serial_board.last_status & BoardStatus.NOT_CONFIGURED
    again = serial_board.request(HelloMsg.msg_type)  # HELLO cleared RESET
    assert isinstance(again, HelloReplyMsg)
    assert not again.status & BoardStatus.RESET
    assert again.status & BoardStatus.NOT_CONFIGURED


def test_set_id_read_back(board: SimavrBoard) -> None:
    assert board.set_board_id(4242) == 4242
    assert board.info.board_id == 4242
    serial_board = board.serial
    assert serial_board is not None
    hello = serial_board.request(HelloMsg.msg_type)
    assert isinstance(hello, HelloReplyMsg) and hello.board_id == 4242
    assert board.set_board_id(0) == 0


def test_config_tick_writes_reads_and_pins(board: SimavrBoard) -> None:
    board.configure(BLIMP, watchdog_s=0)
    assert board.read_outputs() == SAFE_OUTPUTS  # CONFIG drives every output safe
    board.set_analog_input(14, 2.5)
    board.set_digital_input(3, 1)
    reply = board.exchange(BLIMP_WRITES, [3, 14])
    assert reply.status == BoardStatus.OK
    assert reply.samples[3] == 1
    assert abs(reply.samples[14] - 511) <= 2  # 2.5 V of 5 V
    assert board.read_outputs() == BLIMP_WRITES  # digital levels, PWM duty, servo µs
    state = board.harness.state()
    assert state["pwm"] == {"5": 200, "6": 17}
    assert state["servo"] == {"9": 1800}
    later = board.exchange({9: 500, 5: 1}, [14])
    assert later.board_time_s > reply.board_time_s
    outputs = board.read_outputs()
    assert outputs[9] == 500 and outputs[5] == 1 and outputs[2] == 1  # D2 kept its level


@pytest.mark.parametrize(
    ("pins", "code", "pin"),
    [
        ([PinConfig(0, PinMode.DIGITAL_OUT)], ErrorCode.BAD_PIN, 0),
        ([PinConfig(20, PinMode.DIGITAL_OUT)], ErrorCode.BAD_PIN, 20),
        ([PinConfig(4, PinMode.PWM)], ErrorCode.BAD_MODE, 4),
        ([PinConfig(13, PinMode.ANALOG_IN)], ErrorCode.BAD_MODE, 13),
        (
            [PinConfig(9, PinMode.SERVO, 1500), PinConfig(10, PinMode.PWM)],
            ErrorCode.PIN_CONFLICT,
            10,
        ),
        (
            [PinConfig(10, PinMode.SERVO, 1500), PinConfig(9, PinMode.PWM)],
            ErrorCode.PIN_CONFLICT,
            9,
        ),
        ([PinConfig(9, PinMode.SERVO, 3000)], ErrorCode.BAD_VALUE, 9),
    ],
)
def test_bad_config_gets_error_frame(
    board: SimavrBoard, pins: list[PinConfig], code: ErrorCode, pin: int
) -> None:
    with pytest.raises(BoardRequestError, match=code.name) as info:
        board.configure(pins, watchdog_s=0)
    assert (info.value.code, info.value.pin) == (code, pin)


def test_bad_requests_get_error_frames(board: SimavrBoard) -> None:
    serial_board = board.serial
    assert serial_board is not None
    cases: list[tuple[int, bytes, ErrorCode]] = [
        (0x03, bytes(6), ErrorCode.NOT_CONFIGURED),  # TICK before CONFIG
        (0x42, b"", ErrorCode.UNKNOWN_TYPE),
        (0x02, b"\x00", ErrorCode.BAD_LENGTH),
        (0x02, b"\x00\x00\x02\x02\x00", ErrorCode.BAD_LENGTH),
        (0x05, b"\x01", ErrorCode.BAD_LENGTH),
    ]
    for msg_type, body, code in cases:
        with pytest.raises(BoardRequestError) as info:
            serial_board.request(msg_type, body)
        assert info.value.code == code, (hex(msg_type), body.hex())
    board.configure(BLIMP, watchdog_s=0)
    with pytest.raises(BoardRequestError) as info:
        board.exchange({9: 2600}, [])
    assert (info.value.code, info.value.pin) == (ErrorCode.BAD_VALUE, 9)
    tick_cases: list[tuple[bytes, ErrorCode, int]] = [
        ((1 << 3).to_bytes(3, "little") + bytes(3), ErrorCode.BAD_PIN, 3),  # dout on an input
        (bytes(3) + (1 << 2).to_bytes(3, "little"), ErrorCode.BAD_PIN, 2),  # read an output
        (bytes(6) + b"\x02\x01", ErrorCode.BAD_PIN, 2),  # PWM write to a digital output
        (bytes(6) + b"\x05\x10\x05\x20", ErrorCode.BAD_PIN, 5),  # PWM pin written twice
        (bytes(6) + b"\x09\xdc", ErrorCode.BAD_LENGTH, 0x03),  # servo value truncated
        (bytes(5), ErrorCode.BAD_LENGTH, 0x03),
    ]
    for body, code, detail in tick_cases:
        with pytest.raises(BoardRequestError) as info:
            serial_board.request(0x03, body)
        assert info.value.code == code, body.hex()
        if info.value.pin is not None:
            assert info.value.pin == detail
    assert board.exchange(BLIMP_WRITES, [14]).status == BoardStatus.OK  # still fine


def test_damaged_and_too_long_frames(raw: tuple[SimavrHarness, serial.Serial]) -> None:
    _, port = raw
    hello = roundtrip(port, encode_message(HelloMsg(1)))
    assert isinstance(hello[0], HelloReplyMsg)
    # A CRC-bad frame is never answered; the next reply carries RX_ERRORS.
    bad = bytearray(encode_message(HelloMsg(2)))
    bad[1] ^= 0x40
    assert roundtrip(port, bytes(bad), timeout_s=0.3) == []
    after = roundtrip(port, encode_message(HelloMsg(3)))
    assert isinstance(after[0], HelloReplyMsg) and after[0].seq == 3
    assert after[0].status & BoardStatus.RX_ERRORS
    # A frame longer than 96 bytes is answered with ERROR FRAME_TOO_LONG, seq 0.
    too_long = frame_payload(bytes([0x01, 4]) + bytes(range(1, 96)))
    replies = roundtrip(port, too_long)
    assert replies == [ErrorMsg(0, ErrorCode.FRAME_TOO_LONG, replies[0].detail)]
    # Garbage without a delimiter, then a delimiter: the link resynchronises.
    port.write(b"\x13\x37\xff" * 40 + b"\x00")
    final = roundtrip(port, encode_message(HelloMsg(5)))
    assert isinstance(final[-1], HelloReplyMsg) and final[-1].seq == 5


def test_watchdog_drives_outputs_safe_after_silence(board: SimavrBoard) -> None:
    board.configure(BLIMP, watchdog_s=0.1)
    board.exchange(BLIMP_WRITES, [])
    assert board.read_outputs() == BLIMP_WRITES
    wait_sim_time(board, 0.3)
    assert board.read_outputs() == SAFE_OUTPUTS
    tripped = board.exchange(BLIMP_WRITES, [])
    assert tripped.status & BoardStatus.WATCHDOG_TRIPPED
    assert board.read_outputs() == BLIMP_WRITES  # the TICK after a trip applies normally
    assert not board.exchange(BLIMP_WRITES, []).status & BoardStatus.WATCHDOG_TRIPPED
    assert "watchdog_tripped" in [e.kind for e in board.events]


def test_estop_latches_until_configure(board: SimavrBoard) -> None:
    board.configure(BLIMP, watchdog_s=0)
    board.exchange(BLIMP_WRITES, [])
    reply = board.estop()
    assert reply.status & BoardStatus.ESTOPPED
    assert board.read_outputs() == SAFE_OUTPUTS
    held = board.exchange(BLIMP_WRITES, [14])
    assert held.status & BoardStatus.ESTOPPED
    assert 14 in held.samples  # samples still taken
    assert board.read_outputs() == SAFE_OUTPUTS
    board.configure(BLIMP, watchdog_s=0)
    assert not board.exchange(BLIMP_WRITES, []).status & BoardStatus.ESTOPPED
    assert board.read_outputs() == BLIMP_WRITES


def test_recovery_after_host_reconnects(board: SimavrBoard) -> None:
    board.configure(BLIMP, watchdog_s=0)
    board.exchange(BLIMP_WRITES, [])
    serial_board = board.serial
    assert serial_board is not None
    serial_board.close()  # the host closes the pty ...
    info = serial_board.open()  # ... and opens it again: same board, no reboot
    assert info.protocol_version == PROTOCOL_VERSION
    assert not serial_board.last_status & BoardStatus.RESET
    assert not serial_board.last_status & BoardStatus.NOT_CONFIGURED
    reply = board.exchange({**BLIMP_WRITES, 9: 2000}, [14])
    assert reply.status == BoardStatus.OK
    assert board.read_outputs()[9] == 2000


def test_simavr_url_options(firmware_built: Path) -> None:
    from hilswarm.agents.link.url import board_for_url

    board = board_for_url("simavr://uno?paced=1&board_id=0")
    assert isinstance(board, SimavrBoard) and board.paced
    with board:
        assert board.info.board_id == 0
    assert board.harness.process is None
    with pytest.raises(ValueError, match="unknown option 'speed'"):
        board_for_url("simavr://uno?speed=3")
    with pytest.raises(ValueError, match="unknown board profile 'mega'"):
        board_for_url("simavr://mega")


def test_a_stalled_harness_times_out_and_its_late_reply_goes_to_no_other_command(
    firmware_built: Path,
) -> None:
    harness = SimavrHarness("uno")
    harness.start()
    harness.command_timeout_s = 0.3
    try:
        os.kill(harness.process.pid, signal.SIGSTOP)
        try:
            with pytest.raises(SimulatorError, match="no answer"):
                harness.command("ping")  # its "ok" comes after SIGCONT
        finally:
            os.kill(harness.process.pid, signal.SIGCONT)
        assert harness.command("state").startswith("{")  # not the late "ok" of the ping
        assert harness.command("mute 1") == "ok"
        with pytest.raises(SimulatorError, match="expected 0 or 1"):
            harness.command("mute 2")
    finally:
        harness.stop()


# ------------------------------------------------------------------ packed broadcast (protocol 2)

FRISBEE = [
    *(PinConfig(p, PinMode.DIGITAL_OUT, 0) for p in (4, 7, 8, 12)),
    PinConfig(5, PinMode.PWM, 0),
    PinConfig(6, PinMode.PWM, 0),
    PinConfig(14, PinMode.ANALOG_IN),
]
FRISBEE_SAFE = {4: 0, 7: 0, 8: 0, 12: 0, 5: 0, 6: 0}
#: Outputs of three robots (broadcast id -> pin -> value) in one BCAST.
BCAST_OUTPUTS = {
    1: {4: 1, 7: 0, 8: 1, 12: 0, 5: 10, 6: 20},
    2: {4: 0, 7: 1, 8: 0, 12: 1, 5: 200, 6: 3},
    3: {4: 1, 7: 1, 8: 1, 12: 1, 5: 255, 6: 1},
}


def _bcast_frame(seq: int, reply_ids: set[int], outputs: dict[int, dict[int, int]]) -> bytes:
    layout = SectionLayout.of({p.pin: p.mode for p in FRISBEE})
    sections = tuple(
        BcastSection(
            i,
            i in reply_ids,
            layout.encode(sum(v << p for p, v in out.items() if p in (4, 7, 8, 12)), out),
        )
        for i, out in outputs.items()
    )
    return encode_message(BcastMsg(seq, sections))


@pytest.fixture
def two_boards(firmware_built: Path) -> Iterator[list[SimavrBoard]]:
    boards = [SimavrBoard("uno", timeout_s=0.5, retries=2) for _ in range(2)]
    try:
        for board in boards:
            board.open()
        yield boards
    finally:
        for board in boards:
            board.close()


def _read_reply(board: SimavrBoard, timeout_s: float = 2.0) -> list[Message]:
    """Replies on ``board``'s link until one arrives or ``timeout_s`` passes."""
    serial_board = board.serial
    assert serial_board is not None
    port = serial_board._port
    assert port is not None
    decoder = FrameDecoder()
    deadline = time.monotonic() + timeout_s
    replies: list[Message] = []
    while time.monotonic() < deadline and not replies:
        replies += [parse_payload(p) for p in decoder.feed(port.read(64))]
    return replies


def test_broadcast_each_board_applies_only_its_own_section(
    two_boards: list[SimavrBoard],
) -> None:
    for board_id, board in zip((1, 2), two_boards, strict=True):
        assert board.info.protocol_version == 2
        serial_board = board.serial
        assert serial_board is not None
        serial_board.bcast_id = board_id
        board.configure(FRISBEE, watchdog_s=0)
        assert board.read_outputs() == FRISBEE_SAFE
        board.set_analog_input(14, 1.0 + board_id)
    frame = _bcast_frame(50, {2}, BCAST_OUTPUTS)  # the same bytes on both links, as on the air
    for board in two_boards:
        board.serial.write_raw(frame)  # type: ignore[union-attr]
    replies = _read_reply(two_boards[1])
    assert len(replies) == 1 and isinstance(replies[0], BcastReplyMsg), replies
    assert replies[0].seq == 50 and replies[0].status == 0
    assert abs(replies[0].samples[0] - 614) <= 3  # 3.0 V on A0 of board 2
    assert _read_reply(two_boards[0], timeout_s=0.3) == []  # board 1 was not asked
    for board_id, board in zip((1, 2), two_boards, strict=True):
        assert board.read_outputs() == BCAST_OUTPUTS[board_id], board_id
    # a TICK still works as before on the same boards (protocol 1 requests unchanged)
    assert two_boards[0].exchange({5: 77}, [14]).samples[14] > 0
    assert two_boards[0].read_outputs()[5] == 77


def test_broadcast_without_our_section_trips_the_watchdog(board: SimavrBoard) -> None:
    serial_board = board.serial
    assert serial_board is not None
    serial_board.bcast_id = 2
    board.configure(FRISBEE, watchdog_s=0.5)
    serial_board.write_raw(_bcast_frame(60, set(), {2: BCAST_OUTPUTS[2]}))
    wait_for_outputs(board, BCAST_OUTPUTS[2])  # (well within 0.5 s of simulated time)
    # broadcasts for the others only: our watchdog is not fed, the outputs go safe
    others = {1: BCAST_OUTPUTS[1], 3: BCAST_OUTPUTS[3]}
    start = board.harness.state()["t_us"]
    deadline = time.monotonic() + 20.0
    seq = 61
    while board.harness.state()["t_us"] - start < 1.0e6:
        assert time.monotonic() < deadline, "simulated time does not advance"
        serial_board.write_raw(_bcast_frame(seq, {2}, others))
        seq += 1
        wait_sim_time(board, 0.05)
    assert board.read_outputs() == FRISBEE_SAFE
    serial_board.write_raw(_bcast_frame(seq, {2}, {2: BCAST_OUTPUTS[2]}))
    replies = _read_reply(board)
    assert replies and isinstance(replies[0], BcastReplyMsg), replies
    assert replies[0].status & BoardStatus.WATCHDOG_TRIPPED  # reported in the next reply
    # (the outputs it applied may be safe again by now: the simulation runs unpaced)


def test_broadcast_garbage_and_bad_sections_resync(board: SimavrBoard) -> None:
    serial_board = board.serial
    assert serial_board is not None
    serial_board.bcast_id = 3
    board.configure(FRISBEE, watchdog_s=0)
    bad = encode_message(BcastMsg(70, (BcastSection(3, True, b"\x01\x02"),)))  # section too short
    serial_board.write_raw(b"\x11\x22\x33" + bad + b"\x05\x99")  # garbage around a bad section
    # the next frame after a delimiter that ends the garbage (the protocol's resync rule)
    serial_board.write_raw(b"\x00" + _bcast_frame(71, {3}, {3: BCAST_OUTPUTS[3]}))
    replies = _read_reply(board)
    assert len(replies) == 1 and isinstance(replies[0], BcastReplyMsg), replies
    assert replies[0].seq == 71
    assert replies[0].status & BoardStatus.RX_ERRORS  # the bad frames were counted
    assert board.read_outputs() == BCAST_OUTPUTS[3]


def wait_for_outputs(board: SimavrBoard, want: dict[int, int], wall_limit_s: float = 20.0) -> None:
    """Poll the pins until they show ``want``."""
    deadline = time.monotonic() + wall_limit_s
    while board.read_outputs() != want:
        assert time.monotonic() < deadline, board.read_outputs()

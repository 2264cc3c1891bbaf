"""Wire codec: message round trips, the byte-fed decoder under garbage and corruption, checks."""

from __future__ import annotations

import pytest
from hilswarm.agents.errors import WireFormatError
from hilswarm.agents.link.board import PIN_COUNT, ErrorCode, PinMode
from hilswarm.agents.link.codec import (
    MAX_ENCODED,
    MAX_PAYLOAD,
    ConfigEntry,
    ConfigMsg,
    ConfigReplyMsg,
    DropReason,
    ErrorMsg,
    EstopMsg,
    EstopReplyMsg,
    FrameDecoder,
    HelloMsg,
    HelloReplyMsg,
    Message,
    PinWrite,
    SetIdMsg,
    SetIdReplyMsg,
    TickMsg,
    TickReplyMsg,
    check_config,
    check_tick,
    encode_message,
    encode_payload,
    frame_payload,
    mask_of_pins,
    parse_payload,
    pins_of_mask,
)
from hypothesis import given
from hypothesis import strategies as st

UNO_CAPS = (0x80, 0x80, 0x03, 0x07, 0x03, 0x07, 0x07, 0x03, 0x03, 0x0F, 0x0F, 0x07, 0x03,
            0x03, 0x13, 0x13, 0x13, 0x13, 0x13, 0x13)  # fmt: skip

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u24 = st.integers(0, 0xFFFFFF)


@st.composite
def tick_messages(draw: st.DrawFn) -> tuple[TickMsg, list[int]]:
    """A TICK and the pin modes it was encoded for."""
    modes = [int(PinMode.UNUSED)] * PIN_COUNT
    writes = []
    for pin in draw(st.lists(st.integers(0, PIN_COUNT - 1), max_size=20)):
        if modes[pin] == PinMode.UNUSED:
            modes[pin] = int(draw(st.sampled_from([PinMode.PWM, PinMode.SERVO])))
        value = draw(u8 if modes[pin] == PinMode.PWM else u16)
        writes.append(PinWrite(pin, value, PinMode(modes[pin])))
    return TickMsg(draw(u8), draw(u24), draw(u24), tuple(writes)), modes


messages: st.SearchStrategy[Message] = st.one_of(
    st.builds(HelloMsg, u8),
    st.builds(HelloReplyMsg, u8, u8, u8, u8, u16, u8, st.lists(u8, max_size=87).map(tuple)),
    st.builds(
        ConfigMsg, u8, u16, st.lists(st.builds(ConfigEntry, u8, u8, u16), max_size=23).map(tuple)
    ),
    st.builds(ConfigReplyMsg, u8, u8, u8),
    st.builds(
        TickReplyMsg, u8, u8, st.integers(0, 2**32 - 1), st.lists(u16, max_size=44).map(tuple)
    ),
    st.builds(EstopMsg, u8),
    st.builds(EstopReplyMsg, u8, u8),
    st.builds(SetIdMsg, u8, u16),
    st.builds(SetIdReplyMsg, u8, u16),
    st.builds(ErrorMsg, u8, u8, u8),
)


@given(messages)
def test_round_trip_of_every_message(msg: Message) -> None:
    payload = encode_payload(msg)
    assert len(payload) <= MAX_PAYLOAD
    assert parse_payload(payload) == msg
    assert FrameDecoder().feed(encode_message(msg)) == [payload]


@given(tick_messages())
def test_round_trip_of_tick_with_modes(case: tuple[TickMsg, list[int]]) -> None:
    msg, modes = case
    assert parse_payload(encode_payload(msg), modes=modes) == msg


def test_tick_needs_modes() -> None:
    with pytest.raises(TypeError, match="pin modes"):
        parse_payload(encode_payload(TickMsg(1)))


@given(st.lists(messages, min_size=1, max_size=6), st.data())
def test_decoder_any_chunking(msgs: list[Message], data: st.DataObject) -> None:
    stream = b"".join(encode_message(m) for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    decoder = FrameDecoder()
    out: list[bytes] = []
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        out += decoder.feed(stream[start:end])
    assert out == [encode_payload(m) for m in msgs]
    assert decoder.counters.dropped == 0


@given(messages, st.binary(max_size=300), messages)
def test_garbage_between_frames_then_next_good_frame(
    first: Message, garbage: bytes, second: Message
) -> None:
    # A receiver discards garbage up to the next delimiter, so the frame after it is decoded.
    decoder = FrameDecoder()
    out = decoder.feed(encode_message(first) + garbage + b"\x00" + encode_message(second))
    assert out[0] == encode_payload(first)
    assert out[-1] == encode_payload(second)


@given(st.binary(max_size=2000))
def test_decoder_never_raises_and_stays_bounded(garbage: bytes) -> None:
    decoder = FrameDecoder()
    decoder.feed(garbage)
    assert len(decoder._buffer) <= MAX_ENCODED


@given(messages, messages, st.data())
def test_single_corrupted_byte_is_rejected(
    msg: Message, after: Message, data: st.DataObject
) -> None:
    wire = bytearray(encode_message(msg))
    index = data.draw(st.integers(0, len(wire) - 2), label="index")  # not the delimiter
    wire[index] ^= data.draw(st.integers(1, 255), label="xor")
    reasons: list[DropReason] = []
    decoder = FrameDecoder(on_drop=reasons.append)
    out = decoder.feed(bytes(wire) + encode_message(after))
    assert out == [encode_payload(after)]
    assert reasons, "the corrupted frame must be counted as dropped"


def test_corrupted_delimiter_loses_two_frames_only() -> None:
    frames = [encode_message(SetIdMsg(i, i)) for i in range(3)]
    merged = bytearray(frames[0])
    merged[-1] = 0x01
    decoder = FrameDecoder()
    assert decoder.feed(bytes(merged) + frames[1] + frames[2]) == [encode_payload(SetIdMsg(2, 2))]
    assert decoder.counters.dropped == 1


def test_empty_frames_are_idle_line_not_errors() -> None:
    decoder = FrameDecoder()
    assert decoder.feed(b"\x00\x00\x00" + encode_message(HelloMsg(1)) + b"\x00") == [b"\x01\x01"]
    assert decoder.counters.dropped == 0


def test_too_long_frame_dropped_once_delimiter_arrives() -> None:
    reasons: list[DropReason] = []
    decoder = FrameDecoder(on_drop=reasons.append)
    long_payload = bytes([0x81, 0]) + bytes(range(1, 96))  # 97 bytes
    assert decoder.feed(frame_payload(long_payload)[:-1] + b"\x07" * 500) == []
    assert reasons == []
    assert decoder.feed(b"\x00") == []
    assert reasons == [DropReason.TOO_LONG]


def test_encode_rejects_unencodable_values() -> None:
    with pytest.raises(WireFormatError, match="PWM duty of pin 5") as info:
        encode_payload(TickMsg(1, 0, 0, (PinWrite(5, 256, PinMode.PWM),)))
    assert info.value.code == ErrorCode.BAD_VALUE
    with pytest.raises(WireFormatError, match="maximum is 96"):
        encode_payload(HelloReplyMsg(0, 1, 1, 0, 0, 0, (1,) * 88))


@pytest.mark.parametrize(
    ("payload", "code", "detail"),
    [
        (b"\x42\x01", ErrorCode.UNKNOWN_TYPE, 0x42),
        (b"\x01\x01\x00", ErrorCode.BAD_LENGTH, 0x01),
        (b"\x04\x01\x00", ErrorCode.BAD_LENGTH, 0x04),
        (b"\x02\x01\x00\x00\x05\x06", ErrorCode.BAD_LENGTH, 0x02),
        (b"\x06\x01\x01\x83\x00", ErrorCode.BAD_LENGTH, 0x06),
        (b"\x06\x01\x01\x40", ErrorCode.BAD_LENGTH, 0x06),
        (b"\x06\x01\x01", ErrorCode.BAD_LENGTH, 0x06),
        (b"\x05\x01\x03", ErrorCode.BAD_LENGTH, 0x05),
        (b"\x03\x01\x00\x00\x00\x00\x00", ErrorCode.BAD_LENGTH, 0x03),
        (b"\x03\x01\x00\x00\x00\x00\x00\x00\x09\xdc", ErrorCode.BAD_LENGTH, 0x03),
        (b"\x03\x01\x00\x00\x00\x00\x00\x00\x0d\x01", ErrorCode.BAD_PIN, 13),
        (b"\x03\x01\x00\x00\x00\x00\x00\x00\xc8\x01", ErrorCode.BAD_PIN, 200),
    ],
)
def test_parse_errors(payload: bytes, code: ErrorCode, detail: int) -> None:
    modes = [int(PinMode.UNUSED)] * PIN_COUNT
    modes[9] = int(PinMode.SERVO)
    with pytest.raises(WireFormatError) as info:
        parse_payload(payload, modes=modes)
    assert (info.value.code, info.value.detail) == (code, detail)


@pytest.mark.parametrize(
    ("entries", "code", "detail"),
    [
        ([(0, PinMode.DIGITAL_OUT, 0)], ErrorCode.BAD_PIN, 0),
        ([(20, PinMode.DIGITAL_OUT, 0)], ErrorCode.BAD_PIN, 20),
        ([(2, PinMode.DIGITAL_OUT, 0), (2, PinMode.DIGITAL_IN, 0)], ErrorCode.BAD_PIN, 2),
        ([(4, 9, 0)], ErrorCode.BAD_MODE, 4),
        ([(4, PinMode.PWM, 0)], ErrorCode.BAD_MODE, 4),
        ([(3, PinMode.SERVO, 1500)], ErrorCode.BAD_MODE, 3),
        ([(13, PinMode.ANALOG_IN, 0)], ErrorCode.BAD_MODE, 13),
        ([(9, PinMode.SERVO, 1500), (10, PinMode.PWM, 0)], ErrorCode.PIN_CONFLICT, 10),
        ([(9, PinMode.PWM, 0), (10, PinMode.SERVO, 1500)], ErrorCode.PIN_CONFLICT, 9),
        ([(9, PinMode.SERVO, 400)], ErrorCode.BAD_VALUE, 9),
        ([(5, PinMode.PWM, 256)], ErrorCode.BAD_VALUE, 5),
        ([(7, PinMode.DIGITAL_OUT, 2)], ErrorCode.BAD_VALUE, 7),
    ],
)
def test_check_config_errors(
    entries: list[tuple[int, int, int]], code: ErrorCode, detail: int
) -> None:
    msg = ConfigMsg(1, 100, tuple(ConfigEntry(p, int(m), s) for p, m, s in entries))
    with pytest.raises(WireFormatError) as info:
        check_config(msg, UNO_CAPS)
    assert (info.value.code, info.value.detail) == (code, detail)


def test_check_config_accepts_servo_pair_and_blimp() -> None:
    check_config(
        ConfigMsg(
            1, 0, (ConfigEntry(9, PinMode.SERVO, 1500), ConfigEntry(10, PinMode.SERVO, 1000))
        ),
        UNO_CAPS,
    )
    check_config(
        ConfigMsg(
            1,
            500,
            (
                ConfigEntry(2, PinMode.DIGITAL_OUT, 1),
                ConfigEntry(14, PinMode.ANALOG_IN),
                ConfigEntry(15, PinMode.DIGITAL_OUT),
            ),
        ),
        UNO_CAPS,
    )


def test_check_tick() -> None:
    modes = [int(PinMode.UNUSED)] * PIN_COUNT
    modes[2], modes[3], modes[9], modes[14] = (
        PinMode.DIGITAL_OUT,
        PinMode.DIGITAL_IN,
        PinMode.SERVO,
        PinMode.ANALOG_IN,
    )
    check_tick(
        TickMsg(1, mask_of_pins([2]), mask_of_pins([3, 14]), (PinWrite(9, 1500, PinMode.SERVO),)),
        modes,
    )
    cases = [
        (TickMsg(1, dout=mask_of_pins([3])), ErrorCode.BAD_PIN, 3),
        (TickMsg(1, dout=1 << 22), ErrorCode.BAD_PIN, 22),
        (TickMsg(1, rmask=mask_of_pins([2])), ErrorCode.BAD_PIN, 2),
        (TickMsg(1, writes=(PinWrite(9, 2501, PinMode.SERVO),)), ErrorCode.BAD_VALUE, 9),
    ]
    for msg, code, detail in cases:
        with pytest.raises(WireFormatError) as info:
            check_tick(msg, modes)
        assert (info.value.code, info.value.detail) == (code, detail)


@given(st.lists(st.integers(0, 23), unique=True))
def test_masks(pins: list[int]) -> None:
    assert pins_of_mask(mask_of_pins(pins)) == sorted(pins)

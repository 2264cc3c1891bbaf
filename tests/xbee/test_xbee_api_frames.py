"""XBee API frame codec: layout, checksum, escaping (modes 1 and 2), both frame families, fuzz."""

from __future__ import annotations

import random

import pytest
from hilswarm.agents.xbee.api_frames import (
    ApiFrameDecoder,
    ApiFrameError,
    ApiMode,
    AtCommand,
    AtQueuedCommand,
    AtResponse,
    DropReason,
    ModemStatus,
    ReceivePacket,
    RemoteAtCommand,
    RemoteAtResponse,
    Rx64Packet,
    TransmitRequest,
    TransmitStatus,
    Tx64Request,
    TxStatus,
    checksum,
    encode_frame,
    escape,
    parse_frame,
    wrap,
)

ADDR = 0x0013A20040A1B2C3

ALL_FRAMES = [
    Tx64Request(1, ADDR, b"\x00\x7e\x7d\x11\x13hello"),
    Rx64Packet(ADDR, -40, b"reply\x7e"),
    TxStatus(1, 0),
    TransmitRequest(2, ADDR, b"data"),
    ReceivePacket(ADDR, b"zb", 0x1234),
    TransmitStatus(2, 0x21, retries=3, dest16=0x1234),
    AtCommand(3, "CH", b"\x0c"),
    AtQueuedCommand(5, "AP", b""),
    AtResponse(3, "SH", 0, b"\x00\x13\xa2\x00"),
    RemoteAtCommand(4, ADDR, "BD", b"\x07"),
    RemoteAtResponse(4, ADDR, "BD", 0),
    ModemStatus(6),
]


def test_digi_manual_example_tx64() -> None:
    # TX Request 64-bit, frame id 1, to 0x0013A20040A1B2C3, payload "Hi": checksum by hand.
    frame = encode_frame(Tx64Request(1, ADDR, b"Hi"))
    data = bytes.fromhex("00 01 0013A20040A1B2C3 00") + b"Hi"
    assert frame[:3] == bytes((0x7E, 0x00, len(data)))
    assert frame[3:-1] == data
    assert (sum(data) + frame[-1]) & 0xFF == 0xFF
    # The manual's AT command example: 7E 00 04 08 52 4E 4A 0D (AT "NJ", frame id 0x52).
    assert wrap(bytes.fromhex("08 52 4E 4A")) == bytes.fromhex("7E 00 04 08 52 4E 4A 0D")


def test_sizes_match_the_budget_figures() -> None:
    # 802.15.4: TX64 = 15 B + payload, RX64 = 15 B + payload, TX status = 7 B (issue figures).
    assert len(encode_frame(Tx64Request(1, ADDR, b"x" * 20))) == 15 + 20
    assert len(encode_frame(Rx64Packet(ADDR, -40, b"x" * 20))) == 15 + 20
    assert len(encode_frame(TxStatus(1, 0))) == 7
    assert len(encode_frame(TransmitRequest(1, ADDR, b"x" * 20))) == 18 + 20
    assert len(encode_frame(ReceivePacket(ADDR, b"x" * 20))) == 16 + 20
    assert len(encode_frame(TransmitStatus(1, 0))) == 11


@pytest.mark.parametrize("frame", ALL_FRAMES, ids=lambda f: type(f).__name__)
@pytest.mark.parametrize("mode", list(ApiMode))
def test_round_trip(frame: object, mode: ApiMode) -> None:
    wire = encode_frame(frame, mode)  # type: ignore[arg-type]
    assert parse_frame(frame.encode()) == frame  # type: ignore[attr-defined]
    decoder = ApiFrameDecoder(mode)
    assert decoder.feed(wire) == [frame]
    # byte by byte too
    decoder = ApiFrameDecoder(mode)
    out = []
    for byte in wire:
        out += decoder.feed(bytes((byte,)))
    assert out == [frame]


def test_escaping_mode_2() -> None:
    wire = encode_frame(Tx64Request(0x11, 0x7D7E111300000000, b"\x7e"), ApiMode.ESCAPED)
    body = wire[1:]
    assert 0x7E not in body and 0x11 not in body and 0x13 not in body
    assert escape(b"\x7e\x7d\x11\x13\x00") == b"\x7d\x5e\x7d\x5d\x7d\x31\x7d\x33\x00"
    assert checksum(b"\x08\x52\x4e\x4a") == 0x0D


def test_bad_frames_raise_domain_errors() -> None:
    with pytest.raises(ApiFrameError):
        parse_frame(b"\x42\x00")
    with pytest.raises(ValueError):  # the builtin it subclasses
        parse_frame(b"\x80\x00")
    with pytest.raises(ApiFrameError):
        wrap(b"")


def _garble(rng: random.Random, wire: bytes, mode: ApiMode) -> bytes:
    """One damaged copy of ``wire`` that no decoder may accept."""
    kind = rng.choice(["flip", "truncate", "replace"])
    raw = bytearray(wire)
    if kind == "truncate":
        return bytes(raw[: rng.randrange(1, len(raw) - 1)])
    # change one byte of the frame data or checksum (never delimiter/length): the checksum,
    # a sum mod 256, always catches a single changed byte
    index = rng.randrange(3, len(raw))
    if mode == ApiMode.ESCAPED:
        # operate on the unescaped frame and re-escape, so the damage is a data change
        frame_data = bytearray(wire_unescaped(wire))
        i = rng.randrange(3, len(frame_data))
        frame_data[i] ^= 1 << rng.randrange(8) if kind == "flip" else rng.randrange(1, 256)
        return bytes((0x7E,)) + escape(bytes(frame_data[1:]))
    raw[index] ^= 1 << rng.randrange(8) if kind == "flip" else rng.randrange(1, 256)
    return bytes(raw)


def wire_unescaped(wire: bytes) -> bytes:
    out = bytearray((wire[0],))
    it = iter(wire[1:])
    for b in it:
        out.append(next(it) ^ 0x20 if b == 0x7D else b)
    return bytes(out)


@pytest.mark.parametrize("mode", list(ApiMode))
def test_seeded_fuzz_every_garbled_frame_rejected_next_good_one_decoded(mode: ApiMode) -> None:
    rng = random.Random(1234 + mode)
    decoder = ApiFrameDecoder(mode)
    for _ in range(2000):
        good = rng.choice(ALL_FRAMES)
        bad = _garble(rng, encode_frame(rng.choice(ALL_FRAMES), mode), mode)
        noise = (
            bytes(rng.randrange(256) for _ in range(rng.randrange(3)))
            if rng.random() < 0.2
            else b""
        )
        stream = noise + bad + encode_frame(good, mode)
        cut = rng.randrange(len(stream) + 1)
        out = decoder.feed(stream[:cut]) + decoder.feed(stream[cut:])
        if decoder.pending:  # mode 1, truncated frame: the line goes quiet, the rest is decoded
            out += decoder.idle()
        assert out == [good], (bad.hex(), out)
    assert sum(decoder.drops.values()) >= 1
    assert decoder.drops[DropReason.CHECKSUM] + decoder.drops[DropReason.LENGTH] > 0

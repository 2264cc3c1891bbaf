"""CRC-16/CCITT-FALSE and COBS: catalogue values, hand-worked examples, properties."""

from __future__ import annotations

import binascii
import contextlib

import pytest
from hilswarm.agents.errors import CobsDecodeError
from hilswarm.agents.link.cobs import cobs_decode, cobs_encode
from hilswarm.agents.link.crc import CRC16_CHECK, crc16_bytes, crc16_ccitt_false
from hypothesis import given
from hypothesis import strategies as st


def bitwise_crc(data: bytes) -> int:
    """Textbook bit-at-a-time CRC-16/CCITT-FALSE, independent of the table."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = (crc << 1) ^ 0x1021 if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def test_crc_catalogue_check_value() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1 == CRC16_CHECK


def test_crc_of_empty_is_init() -> None:
    assert crc16_ccitt_false(b"") == 0xFFFF


def test_crc_hand_values() -> None:
    # Catalogue value for a single 'A' (CRC-16/CCITT-FALSE): 0xB915.
    assert crc16_ccitt_false(b"A") == 0xB915
    assert crc16_bytes(b"123456789") == bytes([0xB1, 0x29])  # little-endian on the wire


@given(st.binary(max_size=200))
def test_crc_matches_bitwise_and_binascii(data: bytes) -> None:
    assert crc16_ccitt_false(data) == bitwise_crc(data) == binascii.crc_hqx(data, 0xFFFF)


@given(st.binary(max_size=100), st.binary(max_size=100))
def test_crc_incremental(a: bytes, b: bytes) -> None:
    assert crc16_ccitt_false(b, crc16_ccitt_false(a)) == crc16_ccitt_false(a + b)


@pytest.mark.parametrize(
    ("raw", "encoded"),
    [
        # Examples from Cheshire & Baker's COBS paper / the Wikipedia table.
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255)) + b"\x01"),
        (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255)) + b"\x01"),
        (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
    ],
)
def test_cobs_known_examples(raw: bytes, encoded: bytes) -> None:
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


@given(st.binary(max_size=600))
def test_cobs_round_trip_and_no_zero(data: bytes) -> None:
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert len(encoded) <= len(data) + 1 + len(data) // 254
    assert cobs_decode(encoded) == data


@pytest.mark.parametrize(
    ("bad", "culprit"),
    [(b"", "empty"), (b"\x05\x01\x02", "past the end"), (b"\x02\x00", "0x00")],
)
def test_cobs_decode_rejects_malformed(bad: bytes, culprit: str) -> None:
    with pytest.raises(CobsDecodeError, match=culprit):
        cobs_decode(bad)


@given(st.binary(max_size=300))
def test_cobs_decode_never_raises_anything_else(data: bytes) -> None:
    with contextlib.suppress(CobsDecodeError):
        cobs_decode(data)

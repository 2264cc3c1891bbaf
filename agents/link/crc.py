"""CRC-16/CCITT-FALSE of the wire protocol (``docs/protocol.md``).

Polynomial 0x1021, initial value 0xFFFF, no reflection, no final xor. Check value of the ASCII
bytes ``b"123456789"`` is 0x29B1. Table driven (one table lookup per byte).
"""

from __future__ import annotations

#: Generator polynomial (x^16 + x^12 + x^5 + 1, MSB first).
CRC16_POLY = 0x1021
#: Register value before the first byte.
CRC16_INIT = 0xFFFF
#: CRC of b"123456789" (the catalogue's check value).
CRC16_CHECK = 0x29B1


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ CRC16_POLY) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
        table.append(crc)
    return tuple(table)


_TABLE: tuple[int, ...] = _make_table()


def crc16_ccitt_false(data: bytes | bytearray | memoryview, crc: int = CRC16_INIT) -> int:
    """Return the CRC-16/CCITT-FALSE of ``data`` (continue from ``crc`` to checksum in parts)."""
    table = _TABLE
    for byte in bytes(data):
        crc = ((crc << 8) & 0xFF00) ^ table[(crc >> 8) ^ byte]
    return crc


def crc16_bytes(data: bytes | bytearray | memoryview) -> bytes:
    """Return the CRC of ``data`` as the two bytes appended on the wire (little-endian)."""
    return crc16_ccitt_false(data).to_bytes(2, "little")

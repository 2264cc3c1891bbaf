"""CRC-16/CCITT-FALSE of the wire protocol (``docs/protocol.md``).

Polynomial 0x1021, initial value 0xFFFF, no reflection, no final xor. Check value of the ASCII
bytes ``b"123456789"`` is 0x29B1.

The work is done by :func:`binascii.crc_hqx` (C, table driven): it computes exactly this CRC
(polynomial 0x1021, MSB first, caller-given initial value, no final xor), about 30 times faster
than a Python loop (``tests/link/test_crc_cobs.py`` checks it against the bit-serial definition).
"""

from __future__ import annotations

from binascii import crc_hqx

#: Generator polynomial (x^16 + x^12 + x^5 + 1, MSB first).
CRC16_POLY = 0x1021
#: Register value before the first byte.
CRC16_INIT = 0xFFFF
#: CRC of b"123456789" (the catalogue's check value).
CRC16_CHECK = 0x29B1


def crc16_ccitt_false(data: bytes | bytearray | memoryview, crc: int = CRC16_INIT) -> int:
    """Return the CRC-16/CCITT-FALSE of ``data`` (continue from ``crc`` to checksum in parts)."""
    return crc_hqx(data, crc)


def crc16_bytes(data: bytes | bytearray | memoryview) -> bytes:
    """Return the CRC of ``data`` as the two bytes appended on the wire (little-endian)."""
    return crc_hqx(data, CRC16_INIT).to_bytes(2, "little")

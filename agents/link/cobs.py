"""Consistent Overhead Byte Stuffing (COBS), as used by the wire protocol framing.

:func:`cobs_encode` turns any bytes into bytes without 0x00 (overhead: one byte per started block
of 254 non-zero bytes, at least one); the wire appends the 0x00 delimiter itself.
:func:`cobs_decode` reverses it and raises :class:`~hilswarm.agents.errors.CobsDecodeError` on
input that no encoder could have produced.
"""

from __future__ import annotations

from hilswarm.agents.errors import CobsDecodeError

#: Largest block: a code byte of 0xFF announces 254 data bytes and no implied zero.
_MAX_BLOCK = 0xFF


def cobs_encode(data: bytes | bytearray | memoryview) -> bytes:
    """Return the COBS encoding of ``data`` (no 0x00 in the result, no trailing delimiter)."""
    out = bytearray()
    block = bytearray()
    for byte in bytes(data):
        if byte == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
            continue
        block.append(byte)
        if len(block) == _MAX_BLOCK - 1:
            out.append(_MAX_BLOCK)
            out += block
            block.clear()
    out.append(len(block) + 1)
    out += block
    return bytes(out)


def cobs_decode(encoded: bytes | bytearray | memoryview) -> bytes:
    """Return the data whose COBS encoding is ``encoded`` (given without the 0x00 delimiter).

    Raises:
        CobsDecodeError: if ``encoded`` is empty, contains 0x00, or a code byte points past the
            end of the input.
    """
    src = bytes(encoded)
    if not src:
        raise CobsDecodeError("COBS frame is empty (expected at least one code byte)")
    out = bytearray()
    index = 0
    end = len(src)
    while index < end:
        code = src[index]
        if code == 0:
            raise CobsDecodeError(f"COBS frame has a 0x00 at offset {index} (delimiter inside)")
        block_end = index + code
        if block_end > end:
            raise CobsDecodeError(
                f"COBS code byte {code} at offset {index} points past the end of the "
                f"{end}-byte frame"
            )
        block = src[index + 1 : block_end]
        if 0 in block:
            raise CobsDecodeError(f"COBS frame has a 0x00 inside the block at offset {index}")
        out += block
        index = block_end
        if code != _MAX_BLOCK and index < end:
            out.append(0)
    return bytes(out)

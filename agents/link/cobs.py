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
    # Each run of non-zero bytes between zeros is one block (runs of 254 or more are cut into
    # 0xFF blocks of 254 bytes, which carry no implied zero); split() does the scanning in C.
    for run in bytes(data).split(b"\x00"):
        start = 0
        while len(run) - start >= _MAX_BLOCK - 1:
            out.append(_MAX_BLOCK)
            out += run[start : start + _MAX_BLOCK - 1]
            start += _MAX_BLOCK - 1
        out.append(len(run) - start + 1)
        out += run[start:]
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
    if 0 in src:
        _raise_zero(src)
    out = bytearray()
    index = 0
    end = len(src)
    while index < end:
        code = src[index]
        block_end = index + code
        if block_end > end:
            raise CobsDecodeError(
                f"COBS code byte {code} at offset {index} points past the end of the "
                f"{end}-byte frame"
            )
        out += src[index + 1 : block_end]
        index = block_end
        if code != _MAX_BLOCK and index < end:
            out.append(0)
    return bytes(out)


def _raise_zero(src: bytes) -> None:
    """Raise the CobsDecodeError for the first 0x00 of ``src`` (as a code byte or in a block)."""
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
        if 0 in src[index + 1 : block_end]:
            raise CobsDecodeError(f"COBS frame has a 0x00 inside the block at offset {index}")
        index = block_end
    raise CobsDecodeError("COBS frame has a 0x00")  # not reached: the caller found one

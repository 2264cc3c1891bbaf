"""Pure codec of the wire protocol (``docs/protocol.md``): messages, framing, byte-fed decoder.

No I/O happens here. A *payload* is ``type:u8 seq:u8 body...``; a *wire frame* is
``COBS(payload || crc16_le(payload)) || 0x00``.

* One frozen dataclass per message (``HelloMsg`` ... ``ErrorMsg``); ``msg.payload()`` encodes it,
  :func:`encode_message` makes the wire frame, :func:`parse_payload` decodes a payload back into a
  message (a TICK request needs the configured pin modes, because the width of each write follows
  the pin's mode).
* :func:`check_config` and :func:`check_tick` apply the protocol's semantic rules in a fixed order
  and raise :class:`~hilswarm.agents.errors.WireFormatError` carrying the ``ErrorCode`` and
  detail byte a board answers with.
* :class:`FrameDecoder` is fed bytes in chunks of any size and returns complete, CRC-checked
  payloads. It drops damaged frames with counters and never raises on garbage.

Check order used for CONFIG (the first problem found wins): body length, then every pin
(range, reserved, listed twice), then every mode (known, capability), then the Timer1 conflict,
then every safe value. For TICK: not configured, body length (< 6), every dout bit, every rmask
bit, then the writes in wire order (pin, truncation, value).
"""

from __future__ import annotations

import enum
import logging
import struct
from binascii import crc_hqx
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

from hilswarm.agents.errors import CobsDecodeError, WireFormatError
from hilswarm.agents.link.board import (
    MODE_CAPABILITY,
    PIN_COUNT,
    PWM_MAX,
    SERVO_MAX_US,
    SERVO_MIN_US,
    Capability,
    ErrorCode,
    PinMode,
)
from hilswarm.agents.link.cobs import cobs_decode, cobs_encode
from hilswarm.agents.link.crc import CRC16_INIT, crc16_bytes

_log = logging.getLogger(__name__)

#: Largest payload (type + seq + body) [bytes].
MAX_PAYLOAD = 96
#: Size of the CRC appended to the payload [bytes].
CRC_SIZE = 2
#: Smallest decoded frame: type, seq and the CRC [bytes].
MIN_FRAME = 4
#: Largest decoded frame (payload + CRC) [bytes].
MAX_FRAME = MAX_PAYLOAD + CRC_SIZE
#: Largest COBS-encoded frame without its delimiter [bytes] (one overhead byte below 254).
MAX_ENCODED = MAX_FRAME + 1
#: Frame delimiter.
DELIMITER = 0x00
#: Reply type = request type | REPLY_BIT.
REPLY_BIT = 0x80
#: Bit mask of the 24-bit pin masks (dout, rmask).
PIN_MASK_BITS = 24
#: The two Timer1 pins: a servo on one of them takes PWM away from the other.
TIMER1_PINS = (9, 10)


class MsgType(enum.IntEnum):
    """Message type byte."""

    HELLO = 0x01
    CONFIG = 0x02
    TICK = 0x03
    ESTOP = 0x04
    SET_ID = 0x05
    BCAST = 0x06  # protocol 2: every robot's outputs in one broadcast frame
    ERROR = 0x7F
    HELLO_REPLY = 0x81
    CONFIG_REPLY = 0x82
    TICK_REPLY = 0x83
    ESTOP_REPLY = 0x84
    SET_ID_REPLY = 0x85
    BCAST_REPLY = 0x86


#: Request types a board accepts.
REQUEST_TYPES = frozenset(
    {MsgType.HELLO, MsgType.CONFIG, MsgType.TICK, MsgType.ESTOP, MsgType.SET_ID, MsgType.BCAST}
)
#: BCAST section header: bit 0x80 asks the board for a BCAST_REPLY; 0x40 is reserved (0); the
#: low six bits are the length of the section's data [B].
BCAST_REPLY_FLAG = 0x80
BCAST_RESERVED_FLAG = 0x40
BCAST_LENGTH_MASK = 0x3F


def _u8(value: int, what: str, detail: int) -> bytes:
    if not 0 <= value <= 0xFF:
        raise WireFormatError(
            f"{what} = {value} does not fit in a u8 (0-255)",
            code=ErrorCode.BAD_VALUE,
            detail=detail & 0xFF,
        )
    return bytes((value,))


def _u16(value: int, what: str, detail: int) -> bytes:
    if not 0 <= value <= 0xFFFF:
        raise WireFormatError(
            f"{what} = {value} does not fit in a u16 (0-65535)",
            code=ErrorCode.BAD_VALUE,
            detail=detail & 0xFF,
        )
    return value.to_bytes(2, "little")


def _u24(value: int, what: str, detail: int) -> bytes:
    if not 0 <= value < (1 << PIN_MASK_BITS):
        raise WireFormatError(
            f"{what} = {value:#x} does not fit in a u24",
            code=ErrorCode.BAD_VALUE,
            detail=detail & 0xFF,
        )
    return value.to_bytes(3, "little")


def _bad_length(msg_type: int, expected: str, got: int) -> WireFormatError:
    name = MsgType(msg_type).name if msg_type in MsgType._value2member_map_ else hex(msg_type)
    return WireFormatError(
        f"{name} body is {got} bytes; expected {expected}",
        code=ErrorCode.BAD_LENGTH,
        detail=msg_type & 0xFF,
    )


def pins_of_mask(mask: int) -> list[int]:
    """Pin numbers whose bit is set in a pin mask, ascending (bit i = pin i)."""
    return [bit for bit in range(PIN_MASK_BITS) if mask >> bit & 1]


def mask_of_pins(pins: Sequence[int]) -> int:
    """Pin mask with bit ``pin`` set for every pin in ``pins`` (0-23)."""
    mask = 0
    for pin in pins:
        if not 0 <= pin < PIN_MASK_BITS:
            raise WireFormatError(
                f"pin {pin} cannot be put in a 24-bit pin mask",
                code=ErrorCode.BAD_PIN,
                detail=pin & 0xFF,
            )
        mask |= 1 << pin
    return mask


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class HelloMsg:
    """HELLO request: ask for protocol version, firmware version, id, status, capabilities."""

    msg_type: ClassVar[MsgType] = MsgType.HELLO
    seq: int

    def body(self) -> bytes:
        """Encoded body (empty)."""
        return b""


@dataclass(frozen=True, slots=True)
class HelloReplyMsg:
    """HELLO reply. ``capabilities[i]`` = capability bits of pin i; ``board_id`` 0-65535."""

    msg_type: ClassVar[MsgType] = MsgType.HELLO_REPLY
    seq: int
    protocol_version: int
    fw_major: int
    fw_minor: int
    board_id: int
    status: int
    capabilities: tuple[int, ...]

    def body(self) -> bytes:
        """Encoded body."""
        t = self.msg_type
        return (
            _u8(self.protocol_version, "protocol_version", t)
            + _u8(self.fw_major, "fw_major", t)
            + _u8(self.fw_minor, "fw_minor", t)
            + _u16(self.board_id, "board_id", t)
            + _u8(self.status, "status", t)
            + _u8(len(self.capabilities), "n_pins", t)
            + b"".join(_u8(c, f"capability of pin {i}", t) for i, c in enumerate(self.capabilities))
        )


@dataclass(frozen=True, slots=True)
class ConfigEntry:
    """One pin of a CONFIG request; ``safe`` is in wire units of ``mode`` (µs for a servo)."""

    pin: int
    mode: int
    safe: int = 0


@dataclass(frozen=True, slots=True)
class ConfigMsg:
    """CONFIG request: link watchdog [ms] (0 = off), the whole pin configuration and (protocol
    2) the board's broadcast id (1-255; 0 = not in broadcasts, and then not on the wire)."""

    msg_type: ClassVar[MsgType] = MsgType.CONFIG
    seq: int
    watchdog_ms: int
    entries: tuple[ConfigEntry, ...] = ()
    bcast_id: int = 0

    def body(self) -> bytes:
        """Encoded body."""
        out = bytearray(_u16(self.watchdog_ms, "watchdog_ms", self.msg_type))
        for e in self.entries:
            out += _u8(e.pin, "pin", e.pin)
            out += _u8(int(e.mode), f"mode of pin {e.pin}", e.pin)
            out += _u16(e.safe, f"safe value of pin {e.pin}", e.pin)
        if self.bcast_id:
            out += _u8(self.bcast_id, "bcast_id", self.msg_type)
        return bytes(out)


@dataclass(frozen=True, slots=True)
class ConfigReplyMsg:
    """CONFIG reply: status flags and how many pins are now configured."""

    msg_type: ClassVar[MsgType] = MsgType.CONFIG_REPLY
    seq: int
    status: int
    n_configured: int

    def body(self) -> bytes:
        """Encoded body."""
        t = self.msg_type
        return _u8(self.status, "status", t) + _u8(self.n_configured, "n_configured", t)


@dataclass(frozen=True, slots=True)
class PinWrite:
    """A PWM (u8 duty 0-255) or SERVO (u16 pulse width [µs]) write inside a TICK."""

    pin: int
    value: int
    mode: PinMode

    def encode(self) -> bytes:
        """``pin:u8`` followed by the value in the width of the mode."""
        if self.mode == PinMode.PWM:
            return _u8(self.pin, "pin", self.pin) + _u8(
                self.value, f"PWM duty of pin {self.pin}", self.pin
            )
        if self.mode == PinMode.SERVO:
            return _u8(self.pin, "pin", self.pin) + _u16(
                self.value, f"servo pulse [µs] of pin {self.pin}", self.pin
            )
        raise WireFormatError(
            f"pin {self.pin}: a TICK write needs mode PWM or SERVO, got {self.mode!r}",
            code=ErrorCode.BAD_PIN,
            detail=self.pin & 0xFF,
        )


@dataclass(frozen=True, slots=True)
class TickMsg:
    """TICK request: digital output levels, pins to sample, PWM/servo writes (in wire order)."""

    msg_type: ClassVar[MsgType] = MsgType.TICK
    seq: int
    dout: int = 0
    rmask: int = 0
    writes: tuple[PinWrite, ...] = ()

    def body(self) -> bytes:
        """Encoded body."""
        t = self.msg_type
        return (
            _u24(self.dout, "dout", t)
            + _u24(self.rmask, "rmask", t)
            + b"".join(w.encode() for w in self.writes)
        )


@dataclass(frozen=True, slots=True)
class TickReplyMsg:
    """TICK reply: status, board clock [µs, wraps at 2^32], samples in ascending pin order."""

    msg_type: ClassVar[MsgType] = MsgType.TICK_REPLY
    seq: int
    status: int
    board_time_us: int
    samples: tuple[int, ...] = ()

    def body(self) -> bytes:
        """Encoded body."""
        t = self.msg_type
        if not 0 <= self.board_time_us < 1 << 32:
            raise WireFormatError(
                f"board_time_us = {self.board_time_us} does not fit in a u32",
                code=ErrorCode.BAD_VALUE,
                detail=t,
            )
        return (
            _u8(self.status, "status", t)
            + self.board_time_us.to_bytes(4, "little")
            + b"".join(_u16(s, "sample", t) for s in self.samples)
        )


@dataclass(frozen=True, slots=True)
class EstopMsg:
    """ESTOP request: drive every output safe now and latch."""

    msg_type: ClassVar[MsgType] = MsgType.ESTOP
    seq: int

    def body(self) -> bytes:
        """Encoded body (empty)."""
        return b""


@dataclass(frozen=True, slots=True)
class EstopReplyMsg:
    """ESTOP reply: status flags."""

    msg_type: ClassVar[MsgType] = MsgType.ESTOP_REPLY
    seq: int
    status: int

    def body(self) -> bytes:
        """Encoded body."""
        return _u8(self.status, "status", self.msg_type)


@dataclass(frozen=True, slots=True)
class SetIdMsg:
    """SET_ID request: store ``board_id`` (0-65535) in EEPROM."""

    msg_type: ClassVar[MsgType] = MsgType.SET_ID
    seq: int
    board_id: int

    def body(self) -> bytes:
        """Encoded body."""
        return _u16(self.board_id, "board_id", self.msg_type)


@dataclass(frozen=True, slots=True)
class SetIdReplyMsg:
    """SET_ID reply: the id read back from EEPROM."""

    msg_type: ClassVar[MsgType] = MsgType.SET_ID_REPLY
    seq: int
    board_id: int

    def body(self) -> bytes:
        """Encoded body."""
        return _u16(self.board_id, "board_id", self.msg_type)


@dataclass(frozen=True, slots=True)
class BcastSection:
    """One robot's part of a BCAST: its broadcast id, whether it answers, its section data
    (the layout of :class:`~.broadcast.SectionLayout`: levels, then PWM/servo values)."""

    board_id: int
    reply: bool
    data: bytes

    def encode(self) -> bytes:
        """``id:u8 hdr:u8 data`` (hdr = length | 0x80 when a reply is asked for)."""
        if len(self.data) > BCAST_LENGTH_MASK:
            raise WireFormatError(
                f"BCAST section of board {self.board_id}: {len(self.data)} B of data, at most "
                f"{BCAST_LENGTH_MASK}",
                code=ErrorCode.BAD_LENGTH,
                detail=MsgType.BCAST,
            )
        hdr = len(self.data) | (BCAST_REPLY_FLAG if self.reply else 0)
        return _u8(self.board_id, "board id", MsgType.BCAST) + bytes((hdr,)) + self.data


@dataclass(frozen=True, slots=True)
class BcastMsg:
    """BCAST request (protocol 2, to every board at once): one section per robot."""

    msg_type: ClassVar[MsgType] = MsgType.BCAST
    seq: int
    sections: tuple[BcastSection, ...] = ()

    def body(self) -> bytes:
        """Encoded body: the sections back to back."""
        return b"".join(s.encode() for s in self.sections)


@dataclass(frozen=True, slots=True)
class BcastReplyMsg:
    """BCAST reply of the boards whose section asked for one: status, board clock [µs] and a
    sample of every input pin, ascending (the layout of a TICK reply)."""

    msg_type: ClassVar[MsgType] = MsgType.BCAST_REPLY
    seq: int
    status: int
    board_time_us: int
    samples: tuple[int, ...] = ()

    def body(self) -> bytes:
        """Encoded body."""
        return TickReplyMsg(self.seq, self.status, self.board_time_us, self.samples).body()


@dataclass(frozen=True, slots=True)
class ErrorMsg:
    """ERROR (board to host): ``code`` (ErrorCode) and ``detail`` (pin or request type)."""

    msg_type: ClassVar[MsgType] = MsgType.ERROR
    seq: int
    code: int
    detail: int

    def body(self) -> bytes:
        """Encoded body."""
        t = self.msg_type
        return _u8(self.code, "code", t) + _u8(self.detail, "detail", t)


Message = (
    HelloMsg
    | HelloReplyMsg
    | ConfigMsg
    | ConfigReplyMsg
    | TickMsg
    | TickReplyMsg
    | EstopMsg
    | EstopReplyMsg
    | SetIdMsg
    | SetIdReplyMsg
    | BcastMsg
    | BcastReplyMsg
    | ErrorMsg
)


# --------------------------------------------------------------------------- encoding


def encode_payload(msg: Message) -> bytes:
    """``type:u8 seq:u8 body`` of ``msg`` (raises WireFormatError if it exceeds 96 bytes)."""
    payload = _u8(int(msg.msg_type), "type", 0) + _u8(msg.seq, "seq", msg.msg_type) + msg.body()
    if len(payload) > MAX_PAYLOAD:
        raise WireFormatError(
            f"{msg.msg_type.name} payload is {len(payload)} bytes; the maximum is {MAX_PAYLOAD}",
            code=ErrorCode.FRAME_TOO_LONG,
            detail=int(msg.msg_type),
        )
    return payload


def frame_payload(payload: bytes) -> bytes:
    """Wire frame of a payload: ``COBS(payload || crc16_le(payload)) || 0x00`` (no length check)."""
    return cobs_encode(payload + crc16_bytes(payload)) + b"\x00"


def encode_message(msg: Message) -> bytes:
    """Wire frame of ``msg``."""
    return frame_payload(encode_payload(msg))


@dataclass(frozen=True, slots=True)
class TickLayout:
    """The wire layout of TICK requests that write and read the same pins (one configuration).

    Built once per (written pins, read pins) and reused every tick: :meth:`payload` is a single
    :meth:`struct.Struct.pack` instead of a message object per tick.

    Attributes:
        digital_pins: written DIGITAL_OUT pins (their levels travel in ``dout``).
        digital_mask: ``dout`` bits of ``digital_pins``.
        wide_pins: written PWM and SERVO pins, ascending (wire order).
        rmask: bits of the sampled pins.
        read_pins: sampled pins, ascending without duplicates (the order of the reply's samples).
        packer: ``type seq dout:u24 rmask:u24 (pin value)...`` with u8 PWM and u16 servo values.
    """

    digital_pins: tuple[int, ...]
    digital_mask: int
    wide_pins: tuple[int, ...]
    rmask: int
    read_pins: tuple[int, ...]
    packer: struct.Struct

    @classmethod
    def build(
        cls, modes: Mapping[int, int], write_pins: Iterable[int], read_pins: Iterable[int]
    ) -> TickLayout | None:
        """Layout for ``modes`` (pin -> PinMode); None if a written pin is not an output or a
        read pin does not fit the 24-bit mask (the caller reports those)."""
        digital: list[int] = []
        wide: list[int] = []
        for pin in write_pins:
            mode = modes.get(pin, PinMode.UNUSED)
            if mode == PinMode.DIGITAL_OUT:
                digital.append(pin)
            elif mode in (PinMode.PWM, PinMode.SERVO):
                wide.append(pin)
            else:
                return None
        reads = sorted(set(read_pins))
        if any(not 0 <= pin < PIN_MASK_BITS for pin in reads):
            return None
        wide.sort()
        fields = "".join("BB" if modes[pin] == PinMode.PWM else "BH" for pin in wide)
        return cls(
            tuple(digital),
            sum(1 << pin for pin in digital),
            tuple(wide),
            sum(1 << pin for pin in reads),
            tuple(reads),
            struct.Struct("<BBHBHB" + fields),
        )

    def payload(self, seq: int, dout: int, writes: Mapping[int, int]) -> bytes:
        """TICK payload with ``dout`` and the values of ``wide_pins`` taken from ``writes``.

        Raises:
            struct.error: a value does not fit its field (u8 PWM duty, u16 servo pulse).
        """
        values: list[int] = [
            MsgType.TICK,
            seq,
            dout & 0xFFFF,
            dout >> 16,
            self.rmask & 0xFFFF,
            self.rmask >> 16,
        ]
        for pin in self.wide_pins:
            values += (pin, writes[pin])
        return self.packer.pack(*values)


# --------------------------------------------------------------------------- parsing


def _expect_len(msg_type: int, body: bytes, size: int) -> None:
    if len(body) != size:
        raise _bad_length(msg_type, f"{size}", len(body))


def _parse_config(seq: int, body: bytes) -> ConfigMsg:
    if len(body) < 2 or (len(body) - 2) % 4 > 1:
        raise _bad_length(
            MsgType.CONFIG, "2 + 4n [+ 1] (watchdog_ms, pin/mode/safe, bcast_id)", len(body)
        )
    end = len(body) - (len(body) - 2) % 4
    entries = tuple(
        ConfigEntry(body[i], body[i + 1], int.from_bytes(body[i + 2 : i + 4], "little"))
        for i in range(2, end, 4)
    )
    bcast_id = body[end] if end < len(body) else 0
    return ConfigMsg(seq, int.from_bytes(body[0:2], "little"), entries, bcast_id)


def parse_bcast_body(seq: int, body: bytes) -> BcastMsg:
    """Decode a BCAST body into its sections.

    Raises:
        WireFormatError: BAD_LENGTH (a section runs past the body, or a reserved header bit).
    """
    sections: list[BcastSection] = []
    index = 0
    while index < len(body):
        if index + 2 > len(body) or body[index + 1] & BCAST_RESERVED_FLAG:
            raise _bad_length(MsgType.BCAST, "sections of id:u8 hdr:u8 data", len(body))
        hdr = body[index + 1]
        end = index + 2 + (hdr & BCAST_LENGTH_MASK)
        if end > len(body):
            raise _bad_length(
                MsgType.BCAST, f"{end - index - 2} data bytes in a section", len(body)
            )
        sections.append(
            BcastSection(body[index], bool(hdr & BCAST_REPLY_FLAG), bytes(body[index + 2 : end]))
        )
        index = end
    return BcastMsg(seq, tuple(sections))


def parse_tick_body(seq: int, body: bytes, modes: Sequence[int]) -> TickMsg:
    """Decode a TICK body; ``modes[pin]`` (PinMode) gives each write's width.

    Raises:
        WireFormatError: BAD_LENGTH (body < 6 bytes or a write truncated), BAD_PIN (a write to a
            pin that is not PWM/SERVO).
    """
    if len(body) < 6:
        raise _bad_length(MsgType.TICK, "at least 6 (dout:u24, rmask:u24)", len(body))
    dout = int.from_bytes(body[0:3], "little")
    rmask = int.from_bytes(body[3:6], "little")
    writes: list[PinWrite] = []
    index = 6
    while index < len(body):
        pin = body[index]
        mode = modes[pin] if pin < len(modes) else PinMode.UNUSED
        if mode not in (PinMode.PWM, PinMode.SERVO):
            raise WireFormatError(
                f"TICK writes pin {pin}, which is configured {PinMode(mode).name}, "
                "not PWM or SERVO",
                code=ErrorCode.BAD_PIN,
                detail=pin,
            )
        width = 1 if mode == PinMode.PWM else 2
        if index + 1 + width > len(body):
            raise _bad_length(MsgType.TICK, f"{width} more value byte(s) for pin {pin}", len(body))
        value = int.from_bytes(body[index + 1 : index + 1 + width], "little")
        writes.append(PinWrite(pin, value, PinMode(mode)))
        index += 1 + width
    return TickMsg(seq, dout, rmask, tuple(writes))


def parse_payload(payload: bytes, *, modes: Sequence[int] | None = None) -> Message:
    """Decode one CRC-checked payload into a message.

    Args:
        payload: ``type seq body`` (CRC already removed).
        modes: configured mode of every pin, index = pin; needed only for TICK requests.

    Raises:
        WireFormatError: UNKNOWN_TYPE, BAD_LENGTH, or (TICK) BAD_PIN; ``detail`` as on the wire.
    """
    if len(payload) < 2:
        raise WireFormatError(
            f"payload of {len(payload)} bytes has no type and seq",
            code=ErrorCode.BAD_LENGTH,
            detail=0,
        )
    if payload[0] == MsgType.TICK_REPLY and len(payload) >= 7 and not (len(payload) - 7) % 2:
        return parse_tick_reply(payload)  # the reply of every control tick: the short way
    raw_type, seq, body = payload[0], payload[1], bytes(payload[2:])
    if raw_type not in MsgType._value2member_map_:
        raise WireFormatError(
            f"unknown message type {raw_type:#04x}", code=ErrorCode.UNKNOWN_TYPE, detail=raw_type
        )
    t = MsgType(raw_type)
    if t in (MsgType.HELLO, MsgType.ESTOP):
        _expect_len(t, body, 0)
        return HelloMsg(seq) if t == MsgType.HELLO else EstopMsg(seq)
    if t == MsgType.CONFIG:
        return _parse_config(seq, body)
    if t == MsgType.TICK:
        if modes is None:
            raise TypeError("parse_payload needs the pin modes to decode a TICK request")
        return parse_tick_body(seq, body, modes)
    if t == MsgType.SET_ID:
        _expect_len(t, body, 2)
        return SetIdMsg(seq, int.from_bytes(body, "little"))
    if t == MsgType.BCAST:
        return parse_bcast_body(seq, body)
    return _parse_reply(t, seq, body)


def parse_tick_reply(payload: bytes | bytearray) -> TickReplyMsg:
    """Decode a TICK_REPLY payload whose type and length (7 + 2n bytes) the caller checked."""
    count = (len(payload) - 7) >> 1
    samples = (
        _SAMPLES[count].unpack_from(payload, 7)
        if count < len(_SAMPLES)
        else tuple(int.from_bytes(payload[i : i + 2], "little") for i in range(7, len(payload), 2))
    )
    return TickReplyMsg(payload[1], payload[2], _U32.unpack_from(payload, 3)[0], samples)


#: Little-endian u32, and n little-endian u16 samples for every possible sample count.
_U32 = struct.Struct("<I")
_SAMPLES = tuple(struct.Struct(f"<{n}H") for n in range(PIN_MASK_BITS + 1))


def _parse_reply(t: MsgType, seq: int, body: bytes) -> Message:
    if t == MsgType.HELLO_REPLY:
        if len(body) < 7 or len(body) != 7 + body[6]:
            raise _bad_length(t, "7 + n_pins", len(body))
        return HelloReplyMsg(
            seq,
            body[0],
            body[1],
            body[2],
            int.from_bytes(body[3:5], "little"),
            body[5],
            tuple(body[7:]),
        )
    if t == MsgType.CONFIG_REPLY:
        _expect_len(t, body, 2)
        return ConfigReplyMsg(seq, body[0], body[1])
    if t in (MsgType.TICK_REPLY, MsgType.BCAST_REPLY):
        if len(body) < 5 or (len(body) - 5) % 2:
            raise _bad_length(t, "5 + 2n (status, board_time_us, samples)", len(body))
        samples = tuple(int.from_bytes(body[i : i + 2], "little") for i in range(5, len(body), 2))
        cls = TickReplyMsg if t == MsgType.TICK_REPLY else BcastReplyMsg
        return cls(seq, body[0], int.from_bytes(body[1:5], "little"), samples)
    if t == MsgType.ESTOP_REPLY:
        _expect_len(t, body, 1)
        return EstopReplyMsg(seq, body[0])
    if t == MsgType.SET_ID_REPLY:
        _expect_len(t, body, 2)
        return SetIdReplyMsg(seq, int.from_bytes(body, "little"))
    _expect_len(t, body, 2)
    return ErrorMsg(seq, body[0], body[1])


# --------------------------------------------------------------------------- semantic checks


def _safe_value_ok(mode: int, value: int) -> bool:
    if mode == PinMode.DIGITAL_OUT:
        return value in (0, 1)
    if mode == PinMode.PWM:
        return 0 <= value <= PWM_MAX
    if mode == PinMode.SERVO:
        return SERVO_MIN_US <= value <= SERVO_MAX_US
    return value == 0 or mode in (
        PinMode.UNUSED,
        PinMode.DIGITAL_IN,
        PinMode.ANALOG_IN,
        PinMode.DIGITAL_IN_PULLUP,
    )


def check_config(msg: ConfigMsg, capabilities: Sequence[int]) -> None:
    """Apply the CONFIG rules of the protocol; raise WireFormatError for the first problem.

    Args:
        msg: the decoded CONFIG request.
        capabilities: capability bits of every pin (index = pin), as HELLO reports them.
    """
    seen: set[int] = set()
    for e in msg.entries:
        reserved = e.pin < len(capabilities) and capabilities[e.pin] & Capability.RESERVED
        if e.pin >= min(PIN_COUNT, len(capabilities)) or reserved or e.pin in seen:
            why = (
                "listed twice"
                if e.pin in seen
                else "reserved (serial link)"
                if reserved
                else f"not a pin (0-{PIN_COUNT - 1})"
            )
            raise WireFormatError(
                f"CONFIG pin {e.pin} is {why}", code=ErrorCode.BAD_PIN, detail=e.pin
            )
        seen.add(e.pin)
    for e in msg.entries:
        if e.mode not in PinMode._value2member_map_:
            raise WireFormatError(
                f"CONFIG pin {e.pin}: unknown mode {e.mode}", code=ErrorCode.BAD_MODE, detail=e.pin
            )
        need = MODE_CAPABILITY.get(PinMode(e.mode), Capability.NONE)
        if need and not capabilities[e.pin] & need:
            raise WireFormatError(
                f"CONFIG pin {e.pin}: mode {PinMode(e.mode).name} needs capability "
                f"{need.name}, the pin has {Capability(capabilities[e.pin])!r}",
                code=ErrorCode.BAD_MODE,
                detail=e.pin,
            )
    modes = {e.pin: e.mode for e in msg.entries}
    for servo_pin, pwm_pin in (TIMER1_PINS, TIMER1_PINS[::-1]):
        if modes.get(servo_pin) == PinMode.SERVO and modes.get(pwm_pin) == PinMode.PWM:
            raise WireFormatError(
                f"CONFIG: SERVO on pin {servo_pin} uses Timer1, so pin {pwm_pin} cannot be PWM",
                code=ErrorCode.PIN_CONFLICT,
                detail=pwm_pin,
            )
    for e in msg.entries:
        if not _safe_value_ok(e.mode, e.safe):
            raise WireFormatError(
                f"CONFIG pin {e.pin}: safe value {e.safe} out of range for {PinMode(e.mode).name}",
                code=ErrorCode.BAD_VALUE,
                detail=e.pin,
            )


def check_tick(msg: TickMsg, modes: Sequence[int]) -> None:
    """Apply the TICK rules (dout/rmask bits, servo range); raise WireFormatError if broken."""
    for pin in pins_of_mask(msg.dout):
        if pin >= len(modes) or modes[pin] != PinMode.DIGITAL_OUT:
            raise WireFormatError(
                f"TICK dout sets pin {pin}, which is not DIGITAL_OUT",
                code=ErrorCode.BAD_PIN,
                detail=pin,
            )
    for pin in pins_of_mask(msg.rmask):
        if pin >= len(modes) or not PinMode(modes[pin]).is_input:
            raise WireFormatError(
                f"TICK samples pin {pin}, which is not an input", code=ErrorCode.BAD_PIN, detail=pin
            )
    written: set[int] = set()
    for w in msg.writes:
        if w.pin in written:
            raise WireFormatError(
                f"TICK writes pin {w.pin} twice (one write per pin)",
                code=ErrorCode.BAD_PIN,
                detail=w.pin,
            )
        written.add(w.pin)
        if w.mode == PinMode.SERVO and not SERVO_MIN_US <= w.value <= SERVO_MAX_US:
            raise WireFormatError(
                f"TICK servo pin {w.pin}: {w.value} µs outside {SERVO_MIN_US}-{SERVO_MAX_US}",
                code=ErrorCode.BAD_VALUE,
                detail=w.pin,
            )


# --------------------------------------------------------------------------- decoder


class DropReason(enum.Enum):
    """Why :class:`FrameDecoder` dropped a frame."""

    COBS = "cobs"  # not a valid COBS encoding
    SHORT = "short"  # decoded frame shorter than type + seq + crc
    TOO_LONG = "too_long"  # decoded frame longer than 96 + 2 bytes
    CRC = "crc"  # CRC mismatch


@dataclass
class DecoderCounters:
    """Frame counters of a :class:`FrameDecoder` (monotonically increasing)."""

    frames: int = 0
    cobs_errors: int = 0
    short_frames: int = 0
    too_long: int = 0
    crc_errors: int = 0

    @property
    def dropped(self) -> int:
        """Total frames dropped for any reason."""
        return self.cobs_errors + self.short_frames + self.too_long + self.crc_errors


@dataclass
class FrameDecoder:
    """Byte-fed frame decoder: ``feed(chunk)`` returns the complete, CRC-valid payloads.

    Bytes up to each 0x00 form one frame; an empty frame (consecutive delimiters) is idle line and
    not counted. A frame that grows past the largest legal size is discarded up to the next
    delimiter (memory stays bounded). Never raises on any input.

    Attributes:
        on_drop: called with the reason of every dropped frame, in stream order.
        counters: frame counters.
    """

    on_drop: Callable[[DropReason], None] | None = None
    counters: DecoderCounters = field(default_factory=DecoderCounters)
    _buffer: bytearray = field(default_factory=bytearray, repr=False)
    _overflow: bool = field(default=False, repr=False)

    def reset(self) -> None:
        """Forget any partial frame (e.g. after a reconnection)."""
        self._buffer.clear()
        self._overflow = False

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        """Consume ``data``; return the payloads (type, seq, body; no CRC) completed by it."""
        chunk = bytes(data)
        if 0 not in chunk:  # the middle of a frame (bytes trickle in at line speed)
            if not self._overflow:
                self._buffer += chunk
                if len(self._buffer) > MAX_ENCODED:
                    self._overflow = True
                    self._buffer.clear()
            return []
        out: list[bytes] = []
        start = 0
        while start <= len(chunk):
            end = chunk.find(b"\x00", start)
            piece = chunk[start:] if end < 0 else chunk[start:end]
            if not self._overflow:
                self._buffer += piece
                if len(self._buffer) > MAX_ENCODED:
                    self._overflow = True
                    self._buffer.clear()
            if end < 0:
                break
            self._finish_frame(out)
            start = end + 1
        return out

    def _finish_frame(self, out: list[bytes]) -> None:
        if self._overflow:
            self._overflow = False
            self._drop(DropReason.TOO_LONG)
            return
        if not self._buffer:
            return
        encoded = bytes(self._buffer)
        self._buffer.clear()
        try:
            frame = cobs_decode(encoded)
        except CobsDecodeError:
            self._drop(DropReason.COBS)
            return
        if len(frame) < MIN_FRAME:
            self._drop(DropReason.SHORT)
        elif len(frame) > MAX_FRAME:
            self._drop(DropReason.TOO_LONG)
        elif crc_hqx(frame[:-CRC_SIZE], CRC16_INIT) != frame[-2] | frame[-1] << 8:
            self._drop(DropReason.CRC)
        else:
            self.counters.frames += 1
            out.append(frame[:-CRC_SIZE])

    def _drop(self, reason: DropReason) -> None:
        c = self.counters
        if reason is DropReason.COBS:
            c.cobs_errors += 1
        elif reason is DropReason.SHORT:
            c.short_frames += 1
        elif reason is DropReason.TOO_LONG:
            c.too_long += 1
        else:
            c.crc_errors += 1
        _log.debug("frame dropped: %s", reason.value)
        if self.on_drop is not None:
            self.on_drop(reason)

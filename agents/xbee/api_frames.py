"""XBee API frames: encoding, escaping, checksum and a byte-fed decoder (pure, no I/O).

Layout (Digi, *XBee/XBee-PRO 802.15.4 RF Modules* product manual, "API Operation"; the same in
the *XBee/XBee-PRO ZigBee* and *DigiMesh* manuals)::

    0x7E | length (uint16, big-endian) | frame data (API id + fields) | checksum

``length`` counts the frame data only. ``checksum = 0xFF - (sum of the frame data & 0xFF)``, so
the frame data plus the checksum sum to 0xFF. In API mode 2 (``AP=2``) every byte after the
start delimiter that is 0x7E, 0x7D, 0x11 or 0x13 is sent as 0x7D followed by the byte XOR 0x20;
``length`` and the checksum are computed on the unescaped bytes.

Two frame families are supported:

* 802.15.4 (XBee 802.15.4 firmware): TX Request 64-bit address (0x00), RX Packet 64-bit address
  (0x80, with RSSI), TX Status (0x89).
* ZigBee / DigiMesh: Transmit Request (0x10), Receive Packet (0x90), Transmit Status (0x8B).

and, common to both: AT Command (0x08), AT Command - Queue Parameter Value (0x09), AT Command
Response (0x88), Remote AT Command Request (0x17), Remote AT Command Response (0x97),
Modem Status (0x8A).

:class:`ApiFrameDecoder` follows the Firmata style of the wire codec: it is fed bytes in chunks
of any size, never raises and never blocks, drops frames with a bad checksum, length or
structure (counted by reason) and resynchronises at the next start delimiter, *including one
inside a frame it just rejected*, so a garbled frame never hides the good one after it.
"""

from __future__ import annotations

import enum
import struct
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

from hilswarm.agents.errors import HilswarmError

#: Start delimiter of every API frame.
START = 0x7E
#: Escape byte of API mode 2.
ESCAPE = 0x7D
#: XOR applied to an escaped byte.
ESCAPE_XOR = 0x20
#: Bytes escaped in API mode 2: start delimiter, escape, XON, XOFF.
ESCAPED = frozenset((0x7E, 0x7D, 0x11, 0x13))
#: Largest frame data accepted by the decoder [bytes] (a 802.15.4 RF payload is <= 100 B; AT
#: responses such as node discovery are far below this).
MAX_FRAME_DATA = 512
#: 64-bit broadcast address (802.15.4 and ZigBee).
BROADCAST_64 = 0x000000000000FFFF
#: 16-bit "unknown" address of the ZigBee Transmit Request.
UNKNOWN_16 = 0xFFFE
#: Bytes an API frame adds around its frame data: delimiter, 2 length bytes, checksum.
FRAME_OVERHEAD = 4


class ApiFrameError(HilswarmError, ValueError):
    """A frame's bytes do not follow the XBee API layout (bad id, too short, bad field)."""


class ApiMode(enum.IntEnum):
    """The coordinator's ``AP`` setting: 1 = API, 2 = API with escaping."""

    API = 1
    ESCAPED = 2


class FrameFamily(enum.Enum):
    """Which transmit/receive frames a radio speaks (detected from its firmware)."""

    IEEE_802_15_4 = "802.15.4"
    ZIGBEE = "zigbee"  # ZigBee and DigiMesh share the 0x10/0x90/0x8B frames


class TxStatusCode(enum.IntEnum):
    """Delivery status of a TX Status (0x89) / Transmit Status (0x8B)."""

    SUCCESS = 0x00
    NO_ACK = 0x01  # 802.15.4: all MAC retries spent without an acknowledgement
    CCA_FAILURE = 0x02  # channel never clear
    PURGED = 0x03  # 802.15.4: indirect message purged
    ZB_MAC_ACK_FAILURE = 0x21  # ZigBee / DigiMesh
    ZB_ADDRESS_NOT_FOUND = 0x24
    ZB_PAYLOAD_TOO_LARGE = 0x74

    @property
    def delivered(self) -> bool:
        """True for SUCCESS."""
        return self is TxStatusCode.SUCCESS


def checksum(frame_data: bytes | bytearray | memoryview) -> int:
    """The API checksum of ``frame_data``: ``0xFF - (sum & 0xFF)``."""
    return 0xFF - (sum(frame_data) & 0xFF)


def escape(data: bytes | bytearray) -> bytes:
    """API-mode-2 escaping of ``data`` (everything after the start delimiter)."""
    if not any(b in ESCAPED for b in data):
        return bytes(data)
    out = bytearray()
    for byte in data:
        if byte in ESCAPED:
            out += bytes((ESCAPE, byte ^ ESCAPE_XOR))
        else:
            out.append(byte)
    return bytes(out)


def wrap(frame_data: bytes | bytearray, mode: ApiMode = ApiMode.API) -> bytes:
    """The complete API frame (delimiter, length, data, checksum), escaped in mode 2.

    Raises:
        ApiFrameError: empty frame data or longer than :data:`MAX_FRAME_DATA`.
    """
    size = len(frame_data)
    if not 0 < size <= MAX_FRAME_DATA:
        raise ApiFrameError(f"frame data of {size} bytes; expected 1..{MAX_FRAME_DATA}")
    body = struct.pack(">H", size) + bytes(frame_data) + bytes((checksum(frame_data),))
    if mode == ApiMode.ESCAPED:
        body = escape(body)
    return bytes((START,)) + body


def frame_size(frame_data_size: int, mode: ApiMode = ApiMode.API) -> int:
    """Bytes on the UART of an unescaped frame with ``frame_data_size`` bytes of frame data.

    In mode 2 escaping adds one byte per escaped byte: this is the minimum (no escapes).
    """
    del mode  # escaping depends on the content; budgets use the unescaped size
    return frame_data_size + FRAME_OVERHEAD


# ---------------------------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Tx64Request:
    """TX Request, 64-bit address (0x00, 802.15.4).

    Attributes:
        frame_id: 1-255 asks for a TX Status with this id; 0 asks for none.
        dest: 64-bit destination address (:data:`BROADCAST_64` for a broadcast).
        data: RF payload (<= 100 bytes on 802.15.4).
        options: 0x01 disables the MAC ACK (and so the retries), 0x04 sends with the
            broadcast PAN id.
    """

    api_id: ClassVar[int] = 0x00
    frame_id: int
    dest: int
    data: bytes
    options: int = 0

    def encode(self) -> bytes:
        """Frame data (API id and fields)."""
        return struct.pack(">BBQB", 0x00, self.frame_id, self.dest, self.options) + self.data


@dataclass(frozen=True, slots=True)
class Rx64Packet:
    """RX Packet, 64-bit source address (0x80, 802.15.4).

    Attributes:
        source: 64-bit source address.
        rssi_dbm: received signal strength [dBm] (the frame carries ``-rssi_dbm``).
        data: RF payload.
        options: 0x02 address broadcast, 0x04 PAN broadcast.
    """

    api_id: ClassVar[int] = 0x80
    source: int
    rssi_dbm: int
    data: bytes
    options: int = 0

    def encode(self) -> bytes:
        """Frame data."""
        rssi = min(max(-self.rssi_dbm, 0), 0xFF)
        return struct.pack(">BQBB", 0x80, self.source, rssi, self.options) + self.data


@dataclass(frozen=True, slots=True)
class TxStatus:
    """TX Status (0x89, 802.15.4): the fate of the TX Request with ``frame_id``."""

    api_id: ClassVar[int] = 0x89
    frame_id: int
    status: int

    def encode(self) -> bytes:
        """Frame data."""
        return bytes((0x89, self.frame_id, self.status))


@dataclass(frozen=True, slots=True)
class TransmitRequest:
    """Transmit Request (0x10, ZigBee/DigiMesh).

    Attributes:
        frame_id: 1-255 asks for a Transmit Status; 0 for none.
        dest: 64-bit destination address.
        data: RF payload.
        dest16: 16-bit network address (:data:`UNKNOWN_16` when not known).
        radius: broadcast radius (0 = maximum hops).
        options: transmit options.
    """

    api_id: ClassVar[int] = 0x10
    frame_id: int
    dest: int
    data: bytes
    dest16: int = UNKNOWN_16
    radius: int = 0
    options: int = 0

    def encode(self) -> bytes:
        """Frame data."""
        head = struct.pack(
            ">BBQHBB", 0x10, self.frame_id, self.dest, self.dest16, self.radius, self.options
        )
        return head + self.data


@dataclass(frozen=True, slots=True)
class ReceivePacket:
    """Receive Packet (0x90, ZigBee/DigiMesh). It carries no RSSI (ask ``DB`` for that)."""

    api_id: ClassVar[int] = 0x90
    source: int
    data: bytes
    source16: int = UNKNOWN_16
    options: int = 0x01  # packet acknowledged

    def encode(self) -> bytes:
        """Frame data."""
        return struct.pack(">BQHB", 0x90, self.source, self.source16, self.options) + self.data


@dataclass(frozen=True, slots=True)
class TransmitStatus:
    """Transmit Status (0x8B, ZigBee/DigiMesh).

    Attributes:
        frame_id: id of the Transmit Request.
        status: delivery status (:class:`TxStatusCode`).
        retries: MAC transmit retries spent.
        dest16: 16-bit address the packet went to.
        discovery: discovery status.
    """

    api_id: ClassVar[int] = 0x8B
    frame_id: int
    status: int
    retries: int = 0
    dest16: int = UNKNOWN_16
    discovery: int = 0

    def encode(self) -> bytes:
        """Frame data."""
        return struct.pack(
            ">BBHBBB", 0x8B, self.frame_id, self.dest16, self.retries, self.status, self.discovery
        )


@dataclass(frozen=True, slots=True)
class AtCommand:
    """AT Command (0x08) to the local radio: ``command`` is two ASCII letters (``"CH"``)."""

    api_id: ClassVar[int] = 0x08
    frame_id: int
    command: str
    parameter: bytes = b""

    def encode(self) -> bytes:
        """Frame data."""
        return bytes((0x08, self.frame_id)) + _at_name(self.command) + self.parameter


@dataclass(frozen=True, slots=True)
class AtQueuedCommand:
    """AT Command - Queue Parameter Value (0x09): like 0x08, applied at the next ``AC``."""

    api_id: ClassVar[int] = 0x09
    frame_id: int
    command: str
    parameter: bytes = b""

    def encode(self) -> bytes:
        """Frame data."""
        return bytes((0x09, self.frame_id)) + _at_name(self.command) + self.parameter


@dataclass(frozen=True, slots=True)
class AtResponse:
    """AT Command Response (0x88): status 0 OK, 1 error, 2 bad command, 3 bad parameter."""

    api_id: ClassVar[int] = 0x88
    frame_id: int
    command: str
    status: int
    value: bytes = b""

    def encode(self) -> bytes:
        """Frame data."""
        return (
            bytes((0x88, self.frame_id))
            + _at_name(self.command)
            + bytes((self.status,))
            + (self.value)
        )


@dataclass(frozen=True, slots=True)
class RemoteAtCommand:
    """Remote AT Command Request (0x17): ``options`` 0x02 applies the change at once."""

    api_id: ClassVar[int] = 0x17
    frame_id: int
    dest: int
    command: str
    parameter: bytes = b""
    dest16: int = UNKNOWN_16
    options: int = 0x02

    def encode(self) -> bytes:
        """Frame data."""
        head = struct.pack(">BBQHB", 0x17, self.frame_id, self.dest, self.dest16, self.options)
        return head + _at_name(self.command) + self.parameter


@dataclass(frozen=True, slots=True)
class RemoteAtResponse:
    """Remote AT Command Response (0x97); status 4 = no response from the remote."""

    api_id: ClassVar[int] = 0x97
    frame_id: int
    source: int
    command: str
    status: int
    value: bytes = b""
    source16: int = UNKNOWN_16

    def encode(self) -> bytes:
        """Frame data."""
        head = struct.pack(">BBQH", 0x97, self.frame_id, self.source, self.source16)
        return head + _at_name(self.command) + bytes((self.status,)) + self.value


@dataclass(frozen=True, slots=True)
class ModemStatus:
    """Modem Status (0x8A): 0 hardware reset, 1 watchdog reset, 6 coordinator started."""

    api_id: ClassVar[int] = 0x8A
    status: int

    def encode(self) -> bytes:
        """Frame data."""
        return bytes((0x8A, self.status))


ApiFrame = (
    Tx64Request
    | Rx64Packet
    | TxStatus
    | TransmitRequest
    | ReceivePacket
    | TransmitStatus
    | AtCommand
    | AtQueuedCommand
    | AtResponse
    | RemoteAtCommand
    | RemoteAtResponse
    | ModemStatus
)


def _at_name(command: str) -> bytes:
    name = command.encode("ascii", errors="replace")
    if len(name) != 2:
        raise ApiFrameError(f"AT command {command!r}: expected two ASCII letters")
    return name


def _need(data: bytes, size: int, what: str) -> None:
    if len(data) < size:
        raise ApiFrameError(f"{what} frame of {len(data)} bytes; needs at least {size}")


def _parse_tx64(d: bytes) -> Tx64Request:
    _need(d, 11, "TX64")
    _, fid, dest, opt = struct.unpack_from(">BBQB", d)
    return Tx64Request(fid, dest, d[11:], opt)


def _parse_rx64(d: bytes) -> Rx64Packet:
    _need(d, 11, "RX64")
    _, src, rssi, opt = struct.unpack_from(">BQBB", d)
    return Rx64Packet(src, -rssi, d[11:], opt)


def _parse_tx_status(d: bytes) -> TxStatus:
    if len(d) != 3:
        raise ApiFrameError(f"TX Status frame of {len(d)} bytes; expected 3")
    return TxStatus(d[1], d[2])


def _parse_transmit_request(d: bytes) -> TransmitRequest:
    _need(d, 14, "Transmit Request")
    _, fid, dest, d16, radius, opt = struct.unpack_from(">BBQHBB", d)
    return TransmitRequest(fid, dest, d[14:], d16, radius, opt)


def _parse_receive_packet(d: bytes) -> ReceivePacket:
    _need(d, 12, "Receive Packet")
    _, src, s16, opt = struct.unpack_from(">BQHB", d)
    return ReceivePacket(src, d[12:], s16, opt)


def _parse_transmit_status(d: bytes) -> TransmitStatus:
    if len(d) != 7:
        raise ApiFrameError(f"Transmit Status frame of {len(d)} bytes; expected 7")
    _, fid, d16, retries, status, disc = struct.unpack(">BBHBBB", d)
    return TransmitStatus(fid, status, retries, d16, disc)


def _parse_at(d: bytes) -> AtCommand:
    _need(d, 4, "AT Command")
    return AtCommand(d[1], d[2:4].decode("ascii", errors="replace"), d[4:])


def _parse_at_queued(d: bytes) -> AtQueuedCommand:
    _need(d, 4, "AT Queued Command")
    return AtQueuedCommand(d[1], d[2:4].decode("ascii", errors="replace"), d[4:])


def _parse_at_response(d: bytes) -> AtResponse:
    _need(d, 5, "AT Response")
    return AtResponse(d[1], d[2:4].decode("ascii", errors="replace"), d[4], d[5:])


def _parse_remote_at(d: bytes) -> RemoteAtCommand:
    _need(d, 15, "Remote AT Command")
    _, fid, dest, d16, opt = struct.unpack_from(">BBQHB", d)
    return RemoteAtCommand(fid, dest, d[13:15].decode("ascii", errors="replace"), d[15:], d16, opt)


def _parse_remote_at_response(d: bytes) -> RemoteAtResponse:
    _need(d, 15, "Remote AT Response")
    _, fid, src, s16 = struct.unpack_from(">BBQH", d)
    name = d[12:14].decode("ascii", errors="replace")
    return RemoteAtResponse(fid, src, name, d[14], d[15:], s16)


def _parse_modem_status(d: bytes) -> ModemStatus:
    if len(d) != 2:
        raise ApiFrameError(f"Modem Status frame of {len(d)} bytes; expected 2")
    return ModemStatus(d[1])


_PARSERS: dict[int, Callable[[bytes], ApiFrame]] = {
    0x00: _parse_tx64,
    0x80: _parse_rx64,
    0x89: _parse_tx_status,
    0x10: _parse_transmit_request,
    0x90: _parse_receive_packet,
    0x8B: _parse_transmit_status,
    0x08: _parse_at,
    0x09: _parse_at_queued,
    0x88: _parse_at_response,
    0x17: _parse_remote_at,
    0x97: _parse_remote_at_response,
    0x8A: _parse_modem_status,
}


def parse_frame(frame_data: bytes | bytearray) -> ApiFrame:
    """Decode checksum-checked frame data into its frame dataclass.

    Raises:
        ApiFrameError: unknown API id or a frame too short for its fields.
    """
    data = bytes(frame_data)
    if not data:
        raise ApiFrameError("empty frame data")
    parser = _PARSERS.get(data[0])
    if parser is None:
        raise ApiFrameError(f"unknown API frame id {data[0]:#04x}")
    return parser(data)


def encode_frame(frame: ApiFrame, mode: ApiMode = ApiMode.API) -> bytes:
    """``frame`` as complete API frame bytes in ``mode``."""
    return wrap(frame.encode(), mode)


# ---------------------------------------------------------------------------------------------
# Decoder
# ---------------------------------------------------------------------------------------------


class DropReason(enum.Enum):
    """Why the decoder dropped bytes."""

    CHECKSUM = "checksum"  # length and bytes complete, checksum wrong
    LENGTH = "length"  # zero or larger than MAX_FRAME_DATA
    STRUCTURE = "structure"  # checksum good, but an unknown id or too short for its fields
    NOISE = "noise"  # bytes before a start delimiter
    BAD_ESCAPE = "bad_escape"  # mode 2: an escape followed by a byte that cannot be escaped


class ApiFrameDecoder:
    """Byte-fed API frame decoder (see the module docstring). Never raises, never blocks.

    Mode 1: a 0x7E may also occur inside a frame, so after a rejected frame the search for the
    next delimiter starts right after the rejected one's delimiter. Mode 2: a raw 0x7E is always
    a delimiter (data bytes are escaped), so it ends any unfinished frame.

    Args:
        mode: API mode 1 or 2 of the stream.
        on_drop: called with the reason of every dropped frame (for counters or logs).
    """

    def __init__(
        self,
        mode: ApiMode = ApiMode.API,
        *,
        on_drop: Callable[[DropReason], None] | None = None,
    ) -> None:
        self.mode = ApiMode(mode)
        self.on_drop = on_drop
        self.drops: Counter[DropReason] = Counter()
        self.frames = 0
        self._buffer = bytearray()  # mode 1: raw bytes; mode 2: unescaped bytes of one frame
        self._escape_pending = False

    def reset(self) -> None:
        """Forget any partial frame."""
        self._buffer.clear()
        self._escape_pending = False

    def idle(self) -> list[ApiFrame]:
        """The line went quiet: an unfinished frame is given up (its length was damaged, or
        its end was lost), and any frame behind its delimiter is decoded. Return those frames.

        Mode 1 needs this to recover a frame that follows a truncated one without waiting for
        later traffic; call it when a read times out with bytes pending.
        """
        frames: list[ApiFrame] = []
        if not self._buffer:
            return frames
        self._drop(DropReason.LENGTH)
        if self.mode == ApiMode.ESCAPED:
            self.reset()
            return frames
        del self._buffer[:1]
        self._extract_raw(frames)
        while self._buffer:  # still unfinished: give those up too, one delimiter at a time
            self._drop(DropReason.LENGTH)
            del self._buffer[:1]
            self._extract_raw(frames)
        return frames

    @property
    def pending(self) -> bool:
        """True while part of a frame is buffered."""
        return bool(self._buffer)

    def _drop(self, reason: DropReason) -> None:
        self.drops[reason] += 1
        if self.on_drop is not None:
            self.on_drop(reason)

    def feed(self, data: bytes | bytearray) -> list[ApiFrame]:
        """Consume ``data``; return the frames completed by it, in order."""
        frames: list[ApiFrame] = []
        if self.mode == ApiMode.ESCAPED:
            self._feed_escaped(data, frames)
        else:
            self._buffer += data
            self._extract_raw(frames)
        return frames

    def _check(self, frame_data: bytes, check: int) -> ApiFrame | None:
        """The frame, or ``None`` (counted) when its checksum or structure is bad."""
        if (sum(frame_data) + check) & 0xFF != 0xFF:
            self._drop(DropReason.CHECKSUM)
            return None
        try:
            frame = parse_frame(frame_data)
        except ApiFrameError:
            self._drop(DropReason.STRUCTURE)
            return None
        self.frames += 1
        return frame

    def _extract_raw(self, frames: list[ApiFrame]) -> None:
        buffer = self._buffer
        while buffer:
            if buffer[0] != START:
                start = buffer.find(START)
                self._drop(DropReason.NOISE)
                if start < 0:
                    buffer.clear()
                    return
                del buffer[:start]
            if len(buffer) < 3:
                return
            size = (buffer[1] << 8) | buffer[2]
            if not 0 < size <= MAX_FRAME_DATA:
                self._drop(DropReason.LENGTH)
                del buffer[:1]  # resync at the next delimiter after this one
                continue
            if len(buffer) < size + 4:
                return
            frame = self._check(bytes(buffer[3 : 3 + size]), buffer[3 + size])
            if frame is None:
                del buffer[:1]  # the good frame may start inside the rejected one
                continue
            del buffer[: size + 4]
            frames.append(frame)

    def _feed_escaped(self, data: bytes | bytearray, frames: list[ApiFrame]) -> None:
        buffer = self._buffer
        for raw in data:
            byte = raw
            if byte == START:
                if buffer:
                    self._drop(DropReason.LENGTH)  # a frame cut short by the next delimiter
                buffer[:] = b"\x7e"
                self._escape_pending = False
                continue
            if not buffer:
                self._drop(DropReason.NOISE)
                continue
            if self._escape_pending:
                self._escape_pending = False
                byte = raw ^ ESCAPE_XOR
                if byte not in ESCAPED:
                    self._drop(DropReason.BAD_ESCAPE)
                    buffer.clear()
                    continue
            elif byte == ESCAPE:
                self._escape_pending = True
                continue
            buffer.append(byte)
            if len(buffer) < 3:
                continue
            size = (buffer[1] << 8) | buffer[2]
            if not 0 < size <= MAX_FRAME_DATA:
                self._drop(DropReason.LENGTH)
                buffer.clear()
            elif len(buffer) == size + 4:
                frame = self._check(bytes(buffer[3 : 3 + size]), buffer[3 + size])
                buffer.clear()
                if frame is not None:
                    frames.append(frame)

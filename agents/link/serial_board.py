"""A board running the hilswarm firmware behind any pyserial URL.

``SerialBoard("/dev/ttyUSB0")``, ``SerialBoard("socket://127.0.0.1:5000")``, ``loop://``,
``rfc2217://host:port``: anything :func:`serial.serial_for_url` opens. The link speaks the wire
protocol of ``docs/protocol.md`` through the pure codec (:mod:`.codec`).

Reliability:

* **Timeouts and retries.** Every request waits ``timeout_s`` for its reply and is re-sent with
  the *same* seq up to ``retries`` times; a late reply to an earlier attempt, or to an earlier
  request, carries an old seq and is discarded. No reply at all: :class:`BoardTimeoutError`.
* **Reconnection.** When the port fails (USB unplugged, socket closed, simulator restarted) the
  board re-opens it for up to ``reconnect_timeout_s``, repeats the HELLO handshake (same checks)
  and re-applies the last configuration, then repeats the interrupted request. A board that
  rebooted behind an open port (a TICK refused with NOT_CONFIGURED) is re-configured the same
  way. Every such event is a :class:`LinkEvent` in :attr:`SerialBoard.events`, passed to the
  ``on_event`` callback and logged.
* **From another thread.** :meth:`SerialBoard.request_estop` sends ESTOP without waiting for
  the link (its own path: it never waits behind a request in progress) and keeps the e-stop
  latched across reconnections; :meth:`SerialBoard.abort` makes a blocked request or
  reconnection give up within one poll period. Everything else is for one thread at a time.
* **Handshake.** HELLO is repeated for up to ``open_timeout_s`` (an Arduino resets when its port
  is opened and its bootloader runs first); the protocol version must be one of
  :data:`~.board.SUPPORTED_PROTOCOL_VERSIONS` and, if ``board_id`` is given, the board's id
  must match, else :class:`ProtocolError` names both.

Speed: a TICK round trip is the protocol's hot path. Its request is packed by a
:class:`~.codec.TickLayout` cached per (written pins, read pins), the bytes go straight through
the port's file descriptor when it is a POSIX serial port (one ``select`` + one ``read`` of
whatever is waiting; pyserial's ``read``/``write`` otherwise), and its reply is unpacked with
``struct``: a few tens of microseconds of host time per tick (``benchmarks/link_throughput.py``).

All time keeping uses a monotonic clock.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import select
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol
from urllib.parse import parse_qsl, urlencode, urlsplit

import serial
from hilswarm.agents.errors import (
    BoardConnectionError,
    BoardRequestError,
    BoardTimeoutError,
    LinkUrlError,
    ProtocolError,
    WireFormatError,
)
from hilswarm.agents.link.board import (
    SUPPORTED_PROTOCOL_VERSIONS,
    Board,
    BoardInfo,
    BoardStatus,
    Capability,
    ErrorCode,
    PinConfig,
    PinMode,
    TickReply,
    pin_name,
)
from hilswarm.agents.link.codec import (
    ConfigEntry,
    ConfigMsg,
    ConfigReplyMsg,
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
    TickLayout,
    TickMsg,
    TickReplyMsg,
    encode_payload,
    frame_payload,
    parse_payload,
)

_log = logging.getLogger(__name__)

#: Default serial speed [baud] (8N1).
DEFAULT_BAUDRATE = 115200
#: Options a link URL may carry in its query string (the rest goes to pyserial).
URL_OPTIONS = {
    "board_id": int,
    "baudrate": int,
    "timeout_s": float,
    "retries": int,
    "open_timeout_s": float,
    "reconnect_timeout_s": float,
}
#: Longest single blocking read [s]; reads return early as soon as bytes arrive.
_POLL_S = 0.02
#: Pause between two attempts to re-open a vanished port [s].
_REOPEN_PAUSE_S = 0.05
#: Longest wait of the e-stop path for a frame being written to finish [s]; past it the ESTOP
#: frame goes out anyway, after a delimiter that ends the partial frame.
_ESTOP_LOCK_WAIT_S = 0.002
#: Most TICK layouts kept per configuration (one per distinct set of written and read pins).
_MAX_TICK_LAYOUTS = 64
#: Largest single read from a port's file descriptor [bytes].
_READ_CHUNK = 4096
#: The pyserial class whose file descriptor may be used directly (POSIX serial ports and ptys).
_PosixSerial: type | None = getattr(getattr(serial, "serialposix", None), "Serial", None)


_STALE = int(BoardStatus.STALE)


class SerialPort(Protocol):
    """The part of :class:`serial.SerialBase` the board uses."""

    timeout: float | None
    """Read timeout [s] (pyserial's meaning: ``None`` blocks, ``0`` never waits)."""

    def read(self, size: int = 1) -> bytes: ...
    def write(self, data: bytes) -> int | None: ...
    def close(self) -> None: ...

    @property
    def in_waiting(self) -> int: ...


PortFactory = Callable[[str, int, float], SerialPort]


def open_pyserial_port(url: str, baudrate: int, poll_s: float) -> SerialPort:
    """Open ``url`` with :func:`serial.serial_for_url` (8N1, reads time out after ``poll_s``)."""
    port: SerialPort = serial.serial_for_url(
        url, baudrate=baudrate, timeout=poll_s, write_timeout=1.0
    )
    return port


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """Something that happened to the link.

    Attributes:
        kind: ``opened``, ``retry``, ``stale_reply``, ``disconnected``, ``reconnected``,
            ``board_reset``, ``watchdog_tripped``, ``rx_errors``, ``closed``.
        time_s: when it happened [s, host monotonic clock].
        detail: human-readable detail.
    """

    kind: str
    time_s: float
    detail: str


@dataclass
class LinkStats:
    """Counters of a :class:`SerialBoard` (monotonically increasing)."""

    requests: int = 0
    retries: int = 0
    stale_replies: int = 0  # replies with an old seq, discarded
    stale_samples: int = 0  # TICK replies marked STALE (a gateway's repeat of older samples)
    malformed_replies: int = 0
    reconnections: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0


class _PortLostError(Exception):
    """Internal: the port failed; carries the cause."""


class SerialBoard(Board):
    """The hilswarm firmware behind a pyserial URL (see the module docstring).

    Args:
        url: pyserial URL or device path (``/dev/ttyUSB0``, ``socket://127.0.0.1:5000``).
        baudrate: serial speed [baud].
        board_id: expected board id (0-65535); ``None`` accepts any.
        timeout_s: time to wait for one reply before re-sending [s].
        retries: re-sends of a request before :class:`BoardTimeoutError`.
        open_timeout_s: how long :meth:`open` keeps trying HELLO (board boot) [s].
        reconnect_timeout_s: how long a lost port is re-opened before giving up [s]; 0
            disables reconnection.
        on_event: called with every :class:`LinkEvent`.
        clock: monotonic clock [s] (injectable for tests).
        port_factory: opens the port (default :func:`open_pyserial_port`).
        port_url: what is opened, when ``url`` carries hilswarm query options
            (:func:`board_from_url` sets it).
    """

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        board_id: int | None = None,
        timeout_s: float = 0.25,
        retries: int = 3,
        open_timeout_s: float = 3.0,
        reconnect_timeout_s: float = 5.0,
        on_event: Callable[[LinkEvent], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        port_factory: PortFactory = open_pyserial_port,
        port_url: str | None = None,
    ) -> None:
        if port_url is None:
            port_url, url_options = split_url_options(url)
            if url_options:
                raise LinkUrlError(
                    f"serial board {url!r}: URL options {sorted(url_options)} are read by "
                    "board_from_url(); pass them as keyword arguments to SerialBoard"
                )
        if board_id is not None and not 0 <= board_id <= 0xFFFF:
            raise LinkUrlError(f"serial board {url!r}: board_id must be 0-65535, got {board_id}")
        for name, value in (("timeout_s", timeout_s), ("open_timeout_s", open_timeout_s)):
            if not value > 0:
                raise LinkUrlError(f"serial board {url!r}: {name} must be > 0 [s], got {value}")
        if retries < 0 or reconnect_timeout_s < 0:
            raise LinkUrlError(
                f"serial board {url!r}: retries and reconnect_timeout_s must be "
                f">= 0, got {retries}, {reconnect_timeout_s}"
            )
        self.url = url
        self.port_url = port_url
        self.link_timeout_s = reconnect_timeout_s
        self.baudrate = baudrate
        self.expected_board_id = board_id
        #: Broadcast id sent with every CONFIG (protocol 2; 0 = none, a protocol-1 CONFIG). A
        #: gateway in broadcast mode adds it itself; set it to send packed broadcasts directly.
        self.bcast_id = 0
        self.timeout_s = timeout_s
        self.retries = retries
        self.open_timeout_s = open_timeout_s
        self.reconnect_timeout_s = reconnect_timeout_s
        self.on_event = on_event
        self.events: list[LinkEvent] = []
        self.stats = LinkStats()
        self.last_status = BoardStatus.OK
        self._clock = clock
        self._port_factory = port_factory
        self._port: SerialPort | None = None
        self._fd: int | None = None  # the port's file descriptor, when it can be used directly
        self._poll_s = min(_POLL_S, timeout_s)
        self._decoder = FrameDecoder()
        self._inbox: deque[bytes] = deque()  # decoded payloads not yet looked at
        self._seq = 0
        self._info: BoardInfo | None = None
        self._config: tuple[tuple[PinConfig, ...], int] | None = None
        self._modes: dict[int, PinMode] = {}
        self._dout_word = 0  # level of every DIGITAL_OUT pin (bit i = pin i), as last sent
        self._tick_layouts: dict[tuple[tuple[int, ...], tuple[int, ...]], TickLayout | None] = {}
        self._statuses: dict[int, BoardStatus] = {}
        self._time_offset_us = 0
        self._last_time_us: int | None = None
        # Frames are written whole under this lock: the e-stop path writes from another thread.
        self._write_lock = threading.Lock()
        self._aborted = threading.Event()
        self._estop_requested = False
        self._link_listeners: list[Callable[[str, str], None]] = []

    # ------------------------------------------------------------------ events
    def _event(self, kind: str, detail: str) -> None:
        event = LinkEvent(kind, self._clock(), detail)
        self.events.append(event)
        level = logging.DEBUG if kind in ("retry", "stale_reply") else logging.INFO
        _log.log(level, "%s: %s: %s", self.url, kind, detail)
        if self.on_event is not None:
            self.on_event(event)
        for listener in self._link_listeners:
            listener(kind, detail)

    # ------------------------------------------------------------------ port
    def _open_port(self) -> None:
        try:
            self._port = self._port_factory(self.port_url, self.baudrate, self._poll_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise BoardConnectionError(f"cannot open serial link {self.url!r}: {exc}") from exc
        self._fd = (
            self._port.fileno()
            if _PosixSerial is not None and isinstance(self._port, _PosixSerial)
            else None
        )
        self._decoder.reset()
        self._inbox.clear()

    def _close_port(self) -> None:
        port, self._port = self._port, None
        self._fd = None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError) as exc:
                _log.debug("%s: closing the port failed: %s", self.url, exc)

    def _write(self, frame: bytes) -> None:
        if self._port is None:
            raise _PortLostError("port is closed")
        with self._write_lock:
            self._write_locked(frame)

    def _write_locked(self, frame: bytes) -> None:
        try:
            written = 0
            if self._fd is not None:
                try:
                    written = os.write(self._fd, frame)
                except BlockingIOError:
                    written = 0
            if written < len(frame):  # not a POSIX port, or its buffer is full: pyserial waits
                self._port.write(frame[written:])
        except (serial.SerialException, OSError) as exc:
            raise _PortLostError(str(exc)) from exc
        self.stats.bytes_sent += len(frame)

    def _read_payloads(self) -> list[bytes]:
        """Block up to one poll period for bytes; return completed payloads."""
        port = self._port
        if port is None:
            raise _PortLostError("port is closed")
        try:
            if self._fd is not None:
                data = self._read_fd(self._fd)
            else:
                data = port.read(1)
                if data:
                    waiting = port.in_waiting
                    if waiting:
                        data += port.read(waiting)
        except (serial.SerialException, OSError) as exc:
            raise _PortLostError(str(exc)) from exc
        self.stats.bytes_received += len(data)
        return self._decoder.feed(data) if data else []

    def _read_fd(self, fd: int) -> bytes:
        """Wait up to one poll period for the port's descriptor; read all that is waiting."""
        if not select.select((fd,), (), (), self._poll_s)[0]:
            return b""
        try:
            data = os.read(fd, _READ_CHUNK)
        except BlockingIOError:
            return b""
        if not data:  # as pyserial: readable but empty means the device went away
            raise serial.SerialException(
                "device reports readiness to read but returned no data (device disconnected?)"
            )
        return data

    # ------------------------------------------------------------------ one request
    def _next_seq(self) -> int:
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFF
        return seq

    def _await_reply(self, seq: int, reply_type: int, deadline: float) -> Message | None:
        while self._inbox or self._clock() < deadline:
            if self._aborted.is_set():
                raise BoardConnectionError(f"{self.url}: request aborted")
            if not self._inbox:
                self._inbox.extend(self._read_payloads())
            while self._inbox:
                payload = self._inbox.popleft()
                try:
                    reply = parse_payload(payload)
                except (WireFormatError, TypeError) as exc:
                    self.stats.malformed_replies += 1
                    _log.warning("%s: malformed reply %s dropped: %s", self.url, payload.hex(), exc)
                    continue
                # FRAME_TOO_LONG (seq 0) can only answer a frame this host never sent.
                too_long = isinstance(reply, ErrorMsg) and reply.code == ErrorCode.FRAME_TOO_LONG
                if (
                    reply.seq != seq
                    or too_long
                    or (reply.msg_type != reply_type and not isinstance(reply, ErrorMsg))
                ):
                    self.stats.stale_replies += 1
                    self._event(
                        "stale_reply",
                        f"discarded {reply.msg_type.name} seq "
                        f"{reply.seq} while waiting for seq {seq}",
                    )
                    continue
                return reply
        return None

    def _transact_once(self, payload: bytes) -> Message:
        """Send ``payload`` and wait for its reply, re-sending on timeout. Raises _PortLostError."""
        frame = frame_payload(payload)
        seq, reply_type = payload[1], payload[0] | 0x80
        self.stats.requests += 1
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats.retries += 1
                self._event(
                    "retry",
                    f"no reply to type {payload[0]:#04x} seq {seq} within "
                    f"{self.timeout_s} s; re-sending (attempt {attempt + 1})",
                )
            self._write(frame)
            reply = self._await_reply(seq, reply_type, self._clock() + self.timeout_s)
            if reply is not None:
                return reply
        raise BoardTimeoutError(
            f"{self.url}: no reply to request type {payload[0]:#04x} seq {seq} after "
            f"{self.retries + 1} attempts of {self.timeout_s} s"
        )

    def _transact(self, payload: bytes) -> Message:
        """Like :meth:`_transact_once`, reconnecting (and retrying once) if the port fails."""
        if self._port is None:
            raise BoardConnectionError(f"serial link {self.url!r} is not open: call open() first")
        try:
            reply = self._transact_once(payload)
        except _PortLostError as exc:
            self._reconnect(str(exc))
            try:
                reply = self._transact_once(payload)
            except _PortLostError as again:
                raise BoardConnectionError(
                    f"{self.url}: link lost again right after reconnecting: {again}"
                ) from again
        if isinstance(reply, ErrorMsg):
            raise self._request_error(reply, payload[0])
        return reply

    def _request_error(self, reply: ErrorMsg, request_type: int) -> BoardRequestError:
        try:
            code_name = ErrorCode(reply.code).name
        except ValueError:
            code_name = f"code {reply.code}"
        pin_codes = (
            ErrorCode.BAD_PIN,
            ErrorCode.BAD_MODE,
            ErrorCode.PIN_CONFLICT,
            ErrorCode.BAD_VALUE,
        )
        pin = reply.detail if reply.code in pin_codes else None
        where = f" on pin {pin_name(pin)}" if pin is not None else f" (detail {reply.detail})"
        return BoardRequestError(
            f"{self.url}: board refused request type {request_type:#04x}: {code_name}{where}",
            code=reply.code,
            pin=pin,
        )

    # ------------------------------------------------------------------ handshake / reconnection
    def _handshake(self, deadline: float) -> BoardInfo:
        """HELLO until it is answered or ``deadline``; check version and id."""
        while True:
            try:
                reply = self._transact_once(encode_payload(HelloMsg(self._next_seq())))
                break
            except BoardTimeoutError:
                if self._clock() >= deadline:
                    raise
        if isinstance(reply, ErrorMsg):
            raise self._request_error(reply, HelloMsg.msg_type)
        if not isinstance(reply, HelloReplyMsg):
            raise ProtocolError(f"{self.url}: HELLO answered with {reply!r}")
        if reply.protocol_version not in SUPPORTED_PROTOCOL_VERSIONS:
            raise ProtocolError(
                f"{self.url}: board speaks protocol version {reply.protocol_version}, this host "
                f"speaks versions {sorted(SUPPORTED_PROTOCOL_VERSIONS)} (update the firmware "
                "or hilswarm)"
            )
        if self.expected_board_id is not None and reply.board_id != self.expected_board_id:
            raise ProtocolError(
                f"{self.url}: expected board id {self.expected_board_id}, the board reports id "
                f"{reply.board_id} (wrong port, or set the id with SET_ID)"
            )
        self.last_status = BoardStatus(reply.status)
        self._last_time_us = None
        return BoardInfo(
            reply.protocol_version,
            (reply.fw_major, reply.fw_minor),
            reply.board_id,
            tuple(Capability(c) for c in reply.capabilities),
        )

    def _reconnect(self, cause: str) -> None:
        self._close_port()
        self._event("disconnected", cause)
        if self.reconnect_timeout_s <= 0:
            raise BoardConnectionError(f"{self.url}: link lost ({cause}); reconnection disabled")
        deadline = self._clock() + self.reconnect_timeout_s
        last_error = cause
        attempts = 0
        while True:
            attempts += 1
            try:
                self._open_port()
                self._info = self._handshake(deadline)
                self._reapply_config()
                break
            except (BoardConnectionError, BoardTimeoutError, _PortLostError) as exc:
                last_error = str(exc)
                self._close_port()
            if self._clock() >= deadline:
                raise BoardConnectionError(
                    f"{self.url}: link lost ({cause}) and not re-established within "
                    f"{self.reconnect_timeout_s} s after {attempts} attempts: {last_error}"
                )
            if self._aborted.wait(_REOPEN_PAUSE_S):  # back-off while the device is away
                raise BoardConnectionError(f"{self.url}: reconnection aborted ({cause})")
        self.stats.reconnections += 1
        self._event(
            "reconnected",
            f"after {attempts} attempt(s); configuration "
            f"{'re-applied' if self._config else 'none to re-apply'}",
        )

    def _reapply_config(self) -> None:
        if self._config is None:
            return
        pins, watchdog_ms = self._config
        reply = self._transact_once(self._config_payload(pins, watchdog_ms))
        if isinstance(reply, ErrorMsg):
            raise self._request_error(reply, ConfigMsg.msg_type)
        if self._estop_requested:  # configuring clears the latch: an e-stop stays an e-stop
            reply = self._transact_once(encode_payload(EstopMsg(self._next_seq())))
            if isinstance(reply, ErrorMsg):
                raise self._request_error(reply, EstopMsg.msg_type)

    def reconnect(self) -> BoardInfo:
        """Re-open the port, handshake and re-apply the configuration: one attempt.

        For a caller that supervises a faulty link itself (the agent, between ticks): bounded by
        ``open_timeout_s`` for the handshake plus one request's retries.

        Raises:
            BoardConnectionError: the port cannot be opened or fails again (or aborted).
            BoardTimeoutError: the board does not answer.
            ProtocolError: the board that answers is not the expected one.
        """
        self._close_port()
        try:
            self._open_port()
            self._info = self._handshake(self._clock() + self.open_timeout_s)
            self._reapply_config()
        except _PortLostError as exc:
            self._close_port()
            raise BoardConnectionError(
                f"{self.url}: link failed while reconnecting: {exc}"
            ) from exc
        except BaseException:
            self._close_port()
            raise
        self.stats.reconnections += 1
        self._event("reconnected", "by the caller; configuration re-applied")
        return self._info

    def request_estop(self) -> bool:
        """Send ESTOP now, from any thread, without waiting for the link or for a reply.

        The e-stop's own path: it never waits behind a request in progress (a blocked exchange
        keeps waiting for its own reply and discards the ESTOP reply as stale). The frame goes
        out whole (after a delimiter that ends any partial frame) and the e-stop stays latched
        across reconnections: re-applying the configuration is followed by ESTOP again.

        Returns:
            ``True`` when the frame was handed to the port, ``False`` when it could not be
            (port closed or failing).
        """
        self._estop_requested = True
        port = self._port
        if port is None:
            return False
        frame = b"\x00" + frame_payload(encode_payload(EstopMsg((self._seq + 128) & 0xFF)))
        locked = self._write_lock.acquire(timeout=_ESTOP_LOCK_WAIT_S)
        try:
            fd = self._fd
            if fd is not None:
                written = os.write(fd, frame)
                if written < len(frame):
                    port.write(frame[written:])
            else:
                port.write(frame)
        except (serial.SerialException, OSError, BlockingIOError) as exc:
            _log.error("%s: e-stop frame not sent: %s", self.url, exc)
            return False
        finally:
            if locked:
                self._write_lock.release()
        self._event("estop_sent", "ESTOP sent on the e-stop path")
        return True

    def add_link_listener(self, listener: Callable[[str, str], None]) -> None:
        """Call ``listener(kind, detail)`` with every :class:`LinkEvent`, after ``on_event``."""
        self._link_listeners.append(listener)

    def abort(self) -> None:
        """Make a blocked request or reconnection give up within one poll period (any thread).

        Every later request fails at once (:class:`BoardConnectionError`) until :meth:`open`.
        """
        self._aborted.set()

    # ------------------------------------------------------------------ Board API
    def open(self) -> BoardInfo:
        """Open the port and perform the HELLO handshake (repeated up to ``open_timeout_s``).

        Raises:
            BoardConnectionError: the port cannot be opened.
            BoardTimeoutError: no HELLO reply within ``open_timeout_s``.
            ProtocolError: protocol version or board id mismatch.
        """
        self._aborted.clear()
        if self._port is None:
            self._open_port()
        try:
            self._info = self._handshake(self._clock() + self.open_timeout_s)
        except _PortLostError as exc:
            self._close_port()
            raise BoardConnectionError(f"{self.url}: link failed during HELLO: {exc}") from exc
        except BaseException:
            self._close_port()
            raise
        info = self._info
        self._event(
            "opened",
            f"protocol {info.protocol_version}, firmware "
            f"{info.firmware_version[0]}.{info.firmware_version[1]}, board id "
            f"{info.board_id}, status {self.last_status!r}",
        )
        return info

    @property
    def info(self) -> BoardInfo:
        """The last HELLO result."""
        if self._info is None:
            raise BoardConnectionError(f"serial link {self.url!r} has not been opened")
        return self._info

    @property
    def is_open(self) -> bool:
        """True while the port is open."""
        return self._port is not None

    def _config_payload(self, pins: Sequence[PinConfig], watchdog_ms: int) -> bytes:
        entries = tuple(ConfigEntry(p.pin, int(p.mode), p.safe_value) for p in pins)
        try:
            return encode_payload(ConfigMsg(self._next_seq(), watchdog_ms, entries, self.bcast_id))
        except WireFormatError as exc:
            raise BoardRequestError(
                f"{self.url}: CONFIG cannot be encoded: {exc}", code=exc.code, pin=None
            ) from exc

    def configure(self, pins: Sequence[PinConfig], *, watchdog_s: float) -> None:
        """Send CONFIG (whole configuration + link watchdog [s], 0 = off) and remember it.

        Raises:
            BoardRequestError: the board (or the encoder) refused the configuration.
        """
        watchdog_ms = round(watchdog_s * 1000.0)
        if not 0 <= watchdog_ms <= 0xFFFF:
            raise BoardRequestError(
                f"{self.url}: watchdog_s = {watchdog_s} s is outside 0-65.535 s",
                code=ErrorCode.BAD_VALUE,
                pin=None,
            )
        pins = tuple(pins)
        self._estop_requested = False  # configuring clears an e-stop (the protocol's rule)
        reply = self._transact(self._config_payload(pins, watchdog_ms))
        if not isinstance(reply, ConfigReplyMsg):
            raise ProtocolError(f"{self.url}: CONFIG answered with {reply!r}")
        self.last_status = BoardStatus(reply.status)
        self._config = (pins, watchdog_ms)
        self._modes = {p.pin: PinMode(p.mode) for p in pins}
        self._dout_word = sum(p.safe_value << p.pin for p in pins if p.mode == PinMode.DIGITAL_OUT)
        self._tick_layouts.clear()

    def _tick_payload(
        self, writes: Mapping[int, int], reads: Sequence[int]
    ) -> tuple[bytes, tuple[int, ...]]:
        """TICK payload and the pins its reply samples (ascending): the cached layout's way."""
        key = (tuple(writes), tuple(reads))
        layout = self._tick_layouts.get(key, False)
        if layout is False:
            if len(self._tick_layouts) >= _MAX_TICK_LAYOUTS:
                self._tick_layouts.clear()
            layout = self._tick_layouts[key] = TickLayout.build(self._modes, key[0], key[1])
        if layout is not None:
            dout = self._dout_word & ~layout.digital_mask
            try:
                for pin in layout.digital_pins:
                    value = writes[pin]
                    if value not in {0, 1}:
                        raise ValueError(value)  # the checked way below names the pin
                    dout |= value << pin
                payload = layout.payload(self._seq, dout, writes)
            except (ValueError, TypeError, struct.error):
                pass  # the checked way below raises the precise error
            else:
                self._seq = (self._seq + 1) & 0xFF
                self._dout_word = dout
                return payload, layout.read_pins
        return self._checked_tick_payload(writes, reads), tuple(sorted(set(reads)))

    def _checked_tick_payload(self, writes: Mapping[int, int], reads: Sequence[int]) -> bytes:
        """TICK payload built message by message, with an error naming every bad write."""
        dout = 0
        wide: list[PinWrite] = []
        for pin, value in sorted(writes.items()):
            mode = self._modes.get(pin, PinMode.UNUSED)
            if mode == PinMode.DIGITAL_OUT:
                if value not in (0, 1):
                    raise BoardRequestError(
                        f"{self.url}: digital output {pin_name(pin)} takes 0 or 1, got {value}",
                        code=ErrorCode.BAD_VALUE,
                        pin=pin,
                    )
                dout |= value << pin
            elif mode in (PinMode.PWM, PinMode.SERVO):
                wide.append(PinWrite(pin, value, mode))
            else:
                raise BoardRequestError(
                    f"{self.url}: write to pin {pin} ({mode.name}), which is not an output",
                    code=ErrorCode.BAD_PIN,
                    pin=pin,
                )
        # Every DIGITAL_OUT pin's level travels in each TICK: unwritten ones keep their level.
        for pin, mode in self._modes.items():
            if mode == PinMode.DIGITAL_OUT and pin not in writes:
                dout |= self._dout_word & (1 << pin)
        rmask = 0
        for pin in reads:
            if not 0 <= pin < 24:
                raise BoardRequestError(
                    f"{self.url}: cannot sample pin {pin}", code=ErrorCode.BAD_PIN, pin=pin
                )
            rmask |= 1 << pin
        try:
            payload = encode_payload(TickMsg(self._next_seq(), dout, rmask, tuple(wide)))
        except WireFormatError as exc:
            raise BoardRequestError(
                f"{self.url}: TICK cannot be encoded: {exc}", code=exc.code, pin=exc.detail
            ) from exc
        self._dout_word = dout
        return payload

    def exchange(self, writes: Mapping[int, int], reads: Sequence[int]) -> TickReply:
        """One TICK round trip: apply ``writes`` (pin -> wire value), sample ``reads``.

        A board that rebooted behind the open port (TICK refused with NOT_CONFIGURED after a
        configure) is handshaken and re-configured, and the TICK repeated once.
        """
        payload, expected = self._tick_payload(writes, reads)
        try:
            reply = self._transact(payload)
        except BoardRequestError as exc:
            if exc.code != ErrorCode.NOT_CONFIGURED or self._config is None:
                raise
            self._event(
                "board_reset",
                "TICK refused with NOT_CONFIGURED: the board rebooted; "
                "handshaking and re-applying the configuration",
            )
            self._recover_from_reset()
            reply = self._transact(payload)
        if not isinstance(reply, TickReplyMsg):
            raise ProtocolError(f"{self.url}: TICK answered with {reply!r}")
        if len(reply.samples) != len(expected):
            raise ProtocolError(
                f"{self.url}: TICK reply carries {len(reply.samples)} samples, "
                f"{len(expected)} were requested"
            )
        status = self._status(reply.status)
        self._note_status(status)
        if reply.status & _STALE:
            self.stats.stale_samples += 1
        return TickReply(
            reply.seq,
            status,
            self._board_time_s(reply.board_time_us, status),
            dict(zip(expected, reply.samples, strict=True)),
        )

    def _status(self, flags: int) -> BoardStatus:
        """``BoardStatus(flags)``, cached (building an IntFlag costs more than the rest of a
        reply)."""
        status = self._statuses.get(flags)
        if status is None:
            status = self._statuses[flags] = BoardStatus(flags)
        return status

    def _recover_from_reset(self) -> None:
        try:
            self._info = self._handshake(self._clock() + self.open_timeout_s)
            self._reapply_config()
        except _PortLostError as exc:
            self._reconnect(str(exc))

    def _note_status(self, status: BoardStatus) -> None:
        self.last_status = status
        if not status:
            return
        if status & BoardStatus.WATCHDOG_TRIPPED:
            self._event("watchdog_tripped", "the board's link watchdog drove the outputs safe")
        if status & BoardStatus.RX_ERRORS:
            self._event("rx_errors", "the board dropped damaged frames since its last reply")

    def _board_time_s(self, time_us: int, status: BoardStatus) -> float:
        """Unwrap the board's u32 µs clock into seconds since its boot."""
        if status and status & BoardStatus.RESET:
            self._time_offset_us = 0
        elif self._last_time_us is not None and time_us < self._last_time_us:
            self._time_offset_us += 1 << 32
        self._last_time_us = time_us
        return (self._time_offset_us + time_us) / 1e6

    def estop(self) -> TickReply:
        """ESTOP: outputs safe now, latched until the next :meth:`configure`.

        The reply carries no board clock: ``board_time_s`` is that of the last TICK reply.
        """
        self._estop_requested = True
        seq_payload = encode_payload(EstopMsg(self._next_seq()))
        reply = self._transact(seq_payload)
        if not isinstance(reply, EstopReplyMsg):
            raise ProtocolError(f"{self.url}: ESTOP answered with {reply!r}")
        status = self._status(reply.status)
        self._note_status(status)
        last = (self._time_offset_us + (self._last_time_us or 0)) / 1e6
        return TickReply(reply.seq, status, last, {})

    def set_board_id(self, board_id: int) -> int:
        """SET_ID: store ``board_id`` (0-65535) in the board's EEPROM; return the read-back id."""
        try:
            payload = encode_payload(SetIdMsg(self._next_seq(), board_id))
        except WireFormatError as exc:
            raise BoardRequestError(
                f"{self.url}: board id {board_id} is not 0-65535", code=ErrorCode.BAD_VALUE
            ) from exc
        reply = self._transact(payload)
        if not isinstance(reply, SetIdReplyMsg):
            raise ProtocolError(f"{self.url}: SET_ID answered with {reply!r}")
        if self._info is not None:
            self._info = dataclasses.replace(self._info, board_id=reply.board_id)
        return reply.board_id

    def request(self, msg_type: int, body: bytes = b"") -> Message:
        """Send a raw request (any type byte and body, a fresh seq); return the decoded reply.

        For tests of the firmware's error handling. Raises :class:`BoardRequestError` for an
        ERROR reply.
        """
        payload = bytes([msg_type & 0xFF, self._next_seq()]) + bytes(body)
        return self._transact(payload)

    def write_raw(self, data: bytes) -> None:
        """Write raw bytes to the link (for tests: garbage, damaged frames)."""
        try:
            self._write(bytes(data))
        except _PortLostError as exc:
            raise BoardConnectionError(f"{self.url}: write failed: {exc}") from exc

    def close(self) -> None:
        """Close the port. Idempotent; a later :meth:`open` starts over."""
        if self._port is not None:
            self._close_port()
            self._event("closed", "port closed by the host")

    def __repr__(self) -> str:
        return f"SerialBoard({self.url!r}, baudrate={self.baudrate})"


def split_url_options(url: str) -> tuple[str, dict[str, Any]]:
    """Split hilswarm's own options (``board_id``, ``baudrate``...) off a link URL's query.

    Returns the URL for pyserial (with any other query keys kept) and the parsed options.

    Raises:
        LinkUrlError: an option value of the wrong type.
    """
    base, sep, query = url.partition("?")
    if not sep:
        return url, {}
    options: dict[str, Any] = {}
    rest: list[tuple[str, str]] = []
    for key, value in parse_qsl(query, keep_blank_values=True):
        if key in URL_OPTIONS:
            try:
                options[key] = URL_OPTIONS[key](value)
            except ValueError:
                raise LinkUrlError(
                    f"link URL {url!r}: option {key}={value!r} is not a {URL_OPTIONS[key].__name__}"
                ) from None
        else:
            rest.append((key, value))
    return (f"{base}?{urlencode(rest)}" if rest else base), options


def board_from_url(url: str, **options: Any) -> SerialBoard:
    """Build a :class:`SerialBoard` for a pyserial URL or device path.

    Query options ``board_id``, ``baudrate``, ``timeout_s``, ``retries``, ``open_timeout_s``,
    ``reconnect_timeout_s`` are taken by hilswarm (e.g. ``/dev/ttyUSB0?board_id=3``); other
    query keys go to pyserial. Keyword ``options`` override nothing silently: a key given both
    ways is an error.
    """
    port_url, from_url = split_url_options(url)
    clash = sorted(set(from_url) & set(options))
    if clash:
        raise LinkUrlError(
            f"link URL {url!r}: {', '.join(clash)} given both in the URL and as keyword options"
        )
    return SerialBoard(url, port_url=port_url, **from_url, **options)


def validate_url(url: str, *, local: bool = True) -> None:
    """Check a serial link URL without opening it: options, URL syntax, and (``local``: the
    board is plugged into this machine) that the device exists.

    ``socket://`` and ``rfc2217://`` URLs are syntax-checked only (``HOST:PORT``): whether the
    server answers is known only when the run opens it.

    Raises:
        LinkUrlError: a bad option, a network URL without host and port, a device path that
            does not exist.
    """
    port_url, _ = split_url_options(url)
    if "://" not in port_url:
        posix_path = os.name == "posix" and port_url.startswith("/")
        if local and posix_path and not os.path.exists(port_url):
            from serial.tools.list_ports import comports  # noqa: PLC0415 - only on this error

            present = sorted(port.device for port in comports())
            raise LinkUrlError(
                f"serial device {port_url!r} does not exist (is the board plugged in?); "
                + (f"serial ports present: {', '.join(present)}" if present else "no serial ports")
            )
        return
    parts = urlsplit(port_url)
    scheme = parts.scheme.lower()
    if scheme in ("socket", "rfc2217"):
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None or not 0 < port < 65536:
            raise LinkUrlError(
                f"link URL {url!r}: expected {scheme}://HOST:PORT with a port 1-65535"
            )

"""Serve the wire protocol for any :class:`Board`: a loopback "firmware" written in Python.

:class:`WireServer` turns request bytes into reply bytes exactly as the firmware does
(``docs/protocol.md``), delegating the pin work to a :class:`Board` (typically the in-process
``SimBoard``). It validates every request with the codec's checks before the board sees it, so it
is at least as strict as the firmware. Transports put it on a byte stream:

* :class:`SocketWireServer` — listens on ``127.0.0.1``; connect with
  ``SerialBoard("socket://127.0.0.1:<port>")``. It can stop and start again on the same port,
  which is how reconnection is tested.
* :class:`PtyWireServer` — a pseudo-terminal; connect with ``SerialBoard(<slave path>)``, exactly
  like a USB serial port.

With these a loopback transport makes every test run without hardware. Fault injection
(:attr:`WireServer.faults`) drops or corrupts replies to exercise the host's retries.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import socket
import threading
import tty
from collections.abc import Callable
from dataclasses import dataclass, field

from hilswarm.agents.errors import BoardRequestError, WireFormatError
from hilswarm.agents.link.board import (
    PIN_COUNT,
    Board,
    BoardInfo,
    BoardStatus,
    ErrorCode,
    PinConfig,
    PinMode,
)
from hilswarm.agents.link.broadcast import SectionLayout
from hilswarm.agents.link.cobs import cobs_encode
from hilswarm.agents.link.codec import (
    BcastReplyMsg,
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
    MsgType,
    SetIdMsg,
    SetIdReplyMsg,
    TickMsg,
    TickReplyMsg,
    check_config,
    check_tick,
    encode_message,
    parse_bcast_body,
    parse_payload,
    pins_of_mask,
)
from hilswarm.agents.link.crc import crc16_bytes

_log = logging.getLogger(__name__)

#: Firmware version the wire server reports when the board does not say.
SERVER_FIRMWARE_VERSION = (1, 0)
#: Status flags that are events (reported once).
_EVENT_FLAGS = BoardStatus.WATCHDOG_TRIPPED | BoardStatus.RX_ERRORS
#: How long transport threads block in one select() before checking for stop [s].
_POLL_S = 0.05


@dataclass
class FaultInjection:
    """Faults a test asks the server to commit (each counter is consumed as it is used).

    Attributes:
        drop_replies: number of next replies to compute but not send (a lost reply).
        drop_requests: number of next valid requests to ignore entirely (a lost request).
        corrupt_replies: number of next replies sent with a flipped CRC bit.
        duplicate_replies: number of next replies sent twice (the copy arrives stale).
    """

    drop_replies: int = 0
    drop_requests: int = 0
    corrupt_replies: int = 0
    duplicate_replies: int = 0


@dataclass
class ServerStats:
    """What the server has seen."""

    requests: int = 0
    replies: int = 0
    errors_sent: int = 0
    dropped_frames: int = 0
    by_type: dict[str, int] = field(default_factory=dict)


class WireServer:
    """Answer wire-protocol requests for ``board`` (see the module docstring).

    Args:
        board: the board doing the pin work; opened on the first HELLO if it is not yet.
        strict: also refuse what the firmware tolerates (a pin written twice in one TICK).
    """

    def __init__(self, board: Board, *, strict: bool = True) -> None:
        self.board = board
        self.strict = strict
        self.faults = FaultInjection()
        self.stats = ServerStats()
        self._decoder = FrameDecoder(on_drop=self._on_drop)
        self._pending_errors: list[ErrorMsg] = []
        self._rx_errors = False
        self._reset = True
        self._estopped = False
        self._modes: list[int] | None = None
        self._layout: SectionLayout | None = None
        self._bcast_id = 0
        self._info: BoardInfo | None = None
        self._board_id: int | None = None

    def reboot(self) -> None:
        """Model a board reset: configuration lost, RESET reported, partial frames dropped.

        Calls ``board.power_cycle()`` when the board has one (``SimBoard`` does).
        """
        power_cycle = getattr(self.board, "power_cycle", None)
        if callable(power_cycle):
            power_cycle()
        self._decoder.reset()
        self._pending_errors.clear()
        self._rx_errors = False
        self._reset = True
        self._estopped = False
        self._modes = None
        self._layout = None
        self._bcast_id = 0

    # ------------------------------------------------------------------ bytes in, bytes out
    def handle_bytes(self, data: bytes) -> bytes:
        """Consume request bytes (any chunking); return the reply bytes to send, in order."""
        out = bytearray()
        start = 0
        while start < len(data):
            end = data.find(b"\x00", start)
            stop = len(data) if end < 0 else end + 1
            for payload in self._decoder.feed(data[start:stop]):
                out += self._handle_payload(payload)
            while self._pending_errors:
                out += self._send(self._pending_errors.pop(0))
            start = stop
        return bytes(out)

    def _on_drop(self, reason: DropReason) -> None:
        self.stats.dropped_frames += 1
        self._rx_errors = True
        if reason is DropReason.TOO_LONG:
            self._pending_errors.append(ErrorMsg(0, ErrorCode.FRAME_TOO_LONG, 0))

    def _send(self, reply: Message) -> bytes:
        if isinstance(reply, ErrorMsg):
            self.stats.errors_sent += 1
        if self.faults.drop_replies > 0:
            self.faults.drop_replies -= 1
            _log.info("wire server: dropping reply %s (fault injection)", reply)
            return b""
        frame = encode_message(reply)
        if self.faults.corrupt_replies > 0:
            self.faults.corrupt_replies -= 1
            payload = bytes([int(reply.msg_type), reply.seq]) + reply.body()
            crc = bytearray(crc16_bytes(payload))
            crc[0] ^= 0x01
            frame = cobs_encode(payload + bytes(crc)) + b"\x00"
        if self.faults.duplicate_replies > 0:
            self.faults.duplicate_replies -= 1
            frame += frame
        self.stats.replies += 1
        return frame

    def _handle_payload(self, payload: bytes) -> bytes:
        if self.faults.drop_requests > 0:
            self.faults.drop_requests -= 1
            _log.info("wire server: ignoring request %s (fault injection)", payload.hex())
            return b""
        if payload[0] == MsgType.BCAST:
            reply = self._bcast(payload)
            return b"" if reply is None else self._send(reply)
        self.stats.requests += 1
        seq = payload[1]
        try:
            if payload[0] == MsgType.TICK and self._modes is None:
                raise BoardRequestError("TICK before any CONFIG", code=ErrorCode.NOT_CONFIGURED)
            msg = parse_payload(payload, modes=self._modes or [0] * PIN_COUNT)
            name = msg.msg_type.name
            self.stats.by_type[name] = self.stats.by_type.get(name, 0) + 1
            reply = self._dispatch(msg)
        except WireFormatError as exc:
            _log.debug("wire server: refusing %s: %s", payload.hex(), exc)
            reply = ErrorMsg(seq, int(exc.code), exc.detail & 0xFF)
        except BoardRequestError as exc:
            _log.debug("wire server: board refused %s: %s", payload.hex(), exc)
            detail = exc.pin if exc.pin is not None and 0 <= exc.pin <= 0xFF else payload[0]
            reply = ErrorMsg(seq, int(exc.code), detail)
        return self._send(reply)

    # ------------------------------------------------------------------ requests
    def _status(self, extra: int = 0) -> int:
        flags = int(extra)
        if self._reset:
            flags |= BoardStatus.RESET
        if self._modes is None:
            flags |= BoardStatus.NOT_CONFIGURED
        if self._estopped:
            flags |= BoardStatus.ESTOPPED
        if self._rx_errors:
            flags |= BoardStatus.RX_ERRORS
            self._rx_errors = False
        return flags

    def _board_flags(self) -> int:
        status = getattr(self.board, "status", None)
        return int(status) if isinstance(status, int) else 0

    def _dispatch(self, msg: Message) -> Message:
        if isinstance(msg, HelloMsg):
            return self._hello(msg)
        if self._info is None:
            self._info = self.board.open()
        if isinstance(msg, ConfigMsg):
            return self._config(msg)
        if isinstance(msg, TickMsg):
            return self._tick(msg)
        if isinstance(msg, EstopMsg):
            reply = self.board.estop()
            self._estopped = True
            return EstopReplyMsg(msg.seq, self._status(reply.status))
        if isinstance(msg, SetIdMsg):
            self._board_id = msg.board_id
            if hasattr(self.board, "board_id"):
                self.board.board_id = msg.board_id  # type: ignore[attr-defined]
            return SetIdReplyMsg(msg.seq, msg.board_id)
        raise WireFormatError(
            f"{msg.msg_type.name} is not a request",
            code=ErrorCode.UNKNOWN_TYPE,
            detail=int(msg.msg_type),
        )

    def _hello(self, msg: HelloMsg) -> HelloReplyMsg:
        before = self._board_flags() & (BoardStatus.RESET | BoardStatus.HW_WATCHDOG_RESET)
        info = self.board.open()
        self._info = info
        status = self._status(before)
        self._reset = False
        board_id = self._board_id if self._board_id is not None else info.board_id
        return HelloReplyMsg(
            msg.seq,
            info.protocol_version,
            info.firmware_version[0],
            info.firmware_version[1],
            board_id,
            status,
            tuple(int(c) for c in info.capabilities),
        )

    def _config(self, msg: ConfigMsg) -> ConfigReplyMsg:
        info = self._info if self._info is not None else self.board.open()
        check_config(msg, info.capabilities)
        events = self._board_flags() & _EVENT_FLAGS
        self.board.configure(
            [PinConfig(e.pin, PinMode(e.mode), e.safe) for e in msg.entries],
            watchdog_s=msg.watchdog_ms / 1000.0,
        )
        modes = [int(PinMode.UNUSED)] * PIN_COUNT
        for e in msg.entries:
            modes[e.pin] = e.mode
        self._modes = modes
        self._layout = SectionLayout.of({e.pin: e.mode for e in msg.entries})
        self._bcast_id = msg.bcast_id
        self._estopped = False
        return ConfigReplyMsg(msg.seq, self._status(events | self._board_flags()), len(msg.entries))

    def _tick(self, msg: TickMsg) -> TickReplyMsg:
        modes = self._modes
        if modes is None:
            raise BoardRequestError("TICK before any CONFIG", code=ErrorCode.NOT_CONFIGURED)
        check_tick(msg, modes)
        writes = {
            pin: msg.dout >> pin & 1
            for pin in range(PIN_COUNT)
            if modes[pin] == PinMode.DIGITAL_OUT
        }
        for w in msg.writes:
            if self.strict and w.pin in writes:
                raise WireFormatError(
                    f"TICK writes pin {w.pin} twice", code=ErrorCode.BAD_PIN, detail=w.pin
                )
            writes[w.pin] = w.value
        reads = pins_of_mask(msg.rmask)
        reply = self.board.exchange(writes, reads)
        time_us = round(reply.board_time_s * 1e6) % (1 << 32)
        samples = tuple(int(reply.samples[pin]) for pin in reads)
        return TickReplyMsg(msg.seq, self._status(reply.status), time_us, samples)

    def _bcast(self, payload: bytes) -> BcastReplyMsg | None:
        """A BCAST (protocol 2): apply our section, answer only if it asks; never an ERROR
        (every board hears a broadcast). A malformed frame or section is dropped and counted
        (RX_ERRORS), as the firmware does."""
        layout = self._layout
        if layout is None or self._bcast_id == 0:
            return None
        try:
            msg = parse_bcast_body(payload[1], payload[2:])
            section = next((s for s in msg.sections if s.board_id == self._bcast_id), None)
            if section is None:
                return None
            writes = layout.decode(section.data)
        except WireFormatError as exc:
            _log.debug("wire server: BCAST dropped: %s", exc)
            self.stats.dropped_frames += 1
            self._rx_errors = True
            return None
        self.stats.requests += 1
        self.stats.by_type["BCAST"] = self.stats.by_type.get("BCAST", 0) + 1
        if self._info is None:
            self._info = self.board.open()
        reply = self.board.exchange(writes, list(layout.input_pins))
        if not section.reply:
            return None
        time_us = round(reply.board_time_s * 1e6) % (1 << 32)
        samples = tuple(int(reply.samples[pin]) for pin in layout.input_pins)
        return BcastReplyMsg(msg.seq, self._status(reply.status), time_us, samples)


# --------------------------------------------------------------------------- transports


class _ThreadedServer:
    """Common start/stop of the transport threads."""

    def __init__(self, server: WireServer) -> None:
        self.server = server
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.failures: list[BaseException] = []

    def _run_safely(self, body: Callable[[], None]) -> None:
        try:
            body()
        except Exception as exc:  # a server bug must fail the test that reads .failures
            _log.exception("wire server thread failed")
            self.failures.append(exc)

    def _start_thread(self, body: Callable[[], None], name: str) -> None:
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._run_safely, args=(body,), name=name, daemon=True
        )
        self._thread.start()

    def _join(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():
                _log.error("wire server thread %s did not stop", self._thread.name)
            self._thread = None


class SocketWireServer(_ThreadedServer):
    """Serve a :class:`WireServer` on ``127.0.0.1:<port>``, one client at a time.

    Use as a context manager, or :meth:`start` / :meth:`stop`; after :meth:`stop`, :meth:`start`
    listens again on the same port (a board that went away and came back).

    Args:
        server: the protocol server (or a Board, wrapped in a WireServer).
        port: TCP port; 0 picks a free one (kept across restarts).
    """

    def __init__(self, server: WireServer | Board, *, port: int = 0) -> None:
        super().__init__(server if isinstance(server, WireServer) else WireServer(server))
        self.port = port
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self.connections = 0

    @property
    def url(self) -> str:
        """pyserial URL of the server: ``socket://127.0.0.1:<port>``."""
        return f"socket://127.0.0.1:{self.port}"

    def start(self) -> SocketWireServer:
        """Listen and serve in a background thread."""
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(1)
        self.port = listener.getsockname()[1]
        self._listener = listener
        self._start_thread(self._serve, f"wire-server-{self.port}")
        return self

    def stop(self) -> None:
        """Stop serving: close the client connection and the listening socket."""
        self._join()
        for sock in (self._client, self._listener):
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.close()
        self._client = self._listener = None

    def _serve(self) -> None:
        listener = self._listener
        while not self._stop.is_set() and listener is not None:
            ready, _, _ = select.select([listener], [], [], _POLL_S)
            if not ready:
                continue
            client, _ = listener.accept()
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._client = client
            self.connections += 1
            self._serve_client(client)
            with contextlib.suppress(OSError):
                client.close()
            self._client = None

    def _serve_client(self, client: socket.socket) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([client], [], [], _POLL_S)
            if not ready:
                continue
            try:
                data = client.recv(4096)
            except OSError:
                return
            if not data:
                return
            reply = self.server.handle_bytes(data)
            if reply:
                try:
                    client.sendall(reply)
                except OSError:
                    return

    def __enter__(self) -> SocketWireServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class PtyWireServer(_ThreadedServer):
    """Serve a :class:`WireServer` on a pseudo-terminal; :attr:`path` is the serial port."""

    def __init__(self, server: WireServer | Board) -> None:
        super().__init__(server if isinstance(server, WireServer) else WireServer(server))
        self._master: int | None = None
        self._slave: int | None = None
        self.path = ""

    @property
    def url(self) -> str:
        """The serial device path to open (``/dev/pts/N``)."""
        return self.path

    def start(self) -> PtyWireServer:
        """Create the pty (raw, 8-bit clean) and serve in a background thread."""
        master, slave = os.openpty()
        tty.setraw(slave)
        self._master, self._slave = master, slave  # keeping the slave open avoids EIO
        self.path = os.ttyname(slave)
        self._start_thread(self._serve, f"wire-server-{self.path}")
        return self

    def stop(self) -> None:
        """Stop serving and close the pty (the device disappears)."""
        self._join()
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None

    def _serve(self) -> None:
        master = self._master
        if master is None:
            return
        while not self._stop.is_set():
            ready, _, _ = select.select([master], [], [], _POLL_S)
            if not ready:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:
                return
            reply = self.server.handle_bytes(data)
            view = memoryview(reply)
            while view:
                written = os.write(master, view)
                view = view[written:]

    def __enter__(self) -> PtyWireServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

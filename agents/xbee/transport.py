"""``xbee://<64-bit address>``: a board behind the XBee gateway, reached over the bus.

The robot's radio is in transparent mode on the Arduino's UART, so the board speaks the same
wire protocol as over USB. :func:`board_from_url` therefore returns a
:class:`~hilswarm.agents.link.serial_board.SerialBoard` whose "serial port" is a
:class:`BusPort`: writes go to ``agent/<name>/link/tx`` (the gateway sends them by radio),
reads come from ``agent/<name>/link/rx``. Seq numbers, CRC, retries, reconnection and every
:class:`~hilswarm.agents.link.serial_board.LinkEvent` work as on a USB link; the timeouts are
those of a radio hop (:data:`DEFAULT_TIMEOUT_S`).

Every answer the gateway puts on ``link/rx`` carries its stage times (:mod:`.stages`); the board
keeps those of the last answer (:meth:`XBeeBoard.take_link_stages`) for the agent's tick ledger.

With ``?sim=sim://<profile>`` or ``?sim=simavr://<profile>`` (for ``[gateway] port = "sim"``)
the agent's process also runs the simulated robot behind that address
(:class:`~.robot_host.RobotHost`), with the vehicle's simulated hardware as plant.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import zenoh
from hilswarm.agents import bus
from hilswarm.agents.errors import BoardConnectionError, LinkUrlError
from hilswarm.agents.link.board import BoardInfo, TickReply
from hilswarm.agents.link.serial_board import SerialBoard, SerialPort
from hilswarm.agents.xbee.config import parse_xbee_url
from hilswarm.agents.xbee.stages import decode_stages

#: Reply wait of one exchange over the radio before a re-send [s] (a round trip through the
#: gateway takes ~10 ms; several robots share the air).
DEFAULT_TIMEOUT_S = 0.25
#: How long the first HELLO is retried [s] (the gateway and the robot start with the run).
DEFAULT_OPEN_TIMEOUT_S = 10.0


class ChannelReader:
    """Receive the samples of ``key`` on a thread of our own and pass their bytes on.

    A channel, not a callback: an agent runs its tick (and so a board's exchange) on a bus
    callback, and a sample delivered by a callback of the same session's link would wait behind
    it. :meth:`close` wakes the thread with an empty sample (no sender on these keys sends
    one), after which it undeclares the subscriber and ends.

    Args:
        session: the bus session.
        key: the key to receive.
        on_bytes: called with each sample's payload (on the reader thread).
        on_attachment: called with each non-empty sample's attachment (``None``: none) just
            before ``on_bytes`` (on the reader thread); default: attachments are ignored.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        on_bytes: Callable[[bytes], None],
        on_attachment: Callable[[bytes | None], None] | None = None,
    ) -> None:
        self._closed = False
        self._on_bytes = on_bytes
        self._on_attachment = on_attachment
        self._wake = session.declare_publisher(key)
        self._sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(1024))
        self._thread = threading.Thread(target=self._drain, name=f"bus-reader-{key}", daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        while True:
            try:
                sample = self._sub.recv()
                data = sample.payload.to_bytes()
            except (zenoh.ZError, RuntimeError, StopIteration):
                return
            if self._closed:
                with contextlib.suppress(zenoh.ZError, RuntimeError):
                    self._sub.undeclare()
                return
            if data:
                if self._on_attachment is not None:
                    attachment = sample.attachment
                    self._on_attachment(None if attachment is None else attachment.to_bytes())
                self._on_bytes(data)

    def close(self) -> None:
        """Stop receiving. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(zenoh.ZError):
            self._wake.put(b"")
        self._thread.join(timeout=2.0)
        with contextlib.suppress(zenoh.ZError):
            self._wake.undeclare()


class BusPort:
    """A byte stream over two bus keys, with the part of pyserial's API SerialBoard uses.

    :attr:`stages` holds the gateway's stage times ``(gateway_s, radio_s)`` [s] of the last
    sample received since the last :meth:`write` (:mod:`.stages`), ``None`` before one arrives.

    Args:
        session: the agent's bus session.
        tx_key: key the written bytes are put on.
        rx_key: key whose samples are the bytes read.
        timeout: read timeout [s] (pyserial's meaning).
    """

    def __init__(self, session: zenoh.Session, tx_key: str, rx_key: str, timeout: float) -> None:
        self.timeout: float | None = timeout
        self._buffer = bytearray()
        self._cond = threading.Condition()
        self._closed = False
        self.stages: tuple[float, float] | None = None
        self._pub = session.declare_publisher(tx_key, **bus.TICK_PATH_QOS)
        self._reader = ChannelReader(session, rx_key, self._received, self._attachment)

    def _attachment(self, attachment: bytes | None) -> None:
        stages = decode_stages(attachment)
        if stages is not None:
            self.stages = stages

    def _received(self, data: bytes) -> None:
        with self._cond:
            self._buffer += data
            self._cond.notify()

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes; waits up to :attr:`timeout` for the first one."""
        with self._cond:
            if not self._buffer and not self._closed:
                self._cond.wait(self.timeout)
            if self._closed:
                raise OSError("bus port closed")
            data = bytes(self._buffer[:size])
            del self._buffer[:size]
            return data

    @property
    def in_waiting(self) -> int:
        """Bytes buffered."""
        with self._cond:
            return len(self._buffer)

    def write(self, data: bytes) -> int:
        """Put ``data`` on the tx key."""
        if self._closed:
            raise OSError("bus port closed")
        self.stages = None
        self._pub.put(bytes(data))
        return len(data)

    def close(self) -> None:
        """Stop reading and undeclare. Idempotent."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self._reader.close()
        with contextlib.suppress(zenoh.ZError):
            self._pub.undeclare()


class XBeeBoard(SerialBoard):
    """A :class:`SerialBoard` over a :class:`BusPort`; also runs the simulated robot if any.

    The link has a bus session of its own (opened on :meth:`open` from ``endpoints``), not the
    agent's: an agent runs its tick on a callback of its own session's link, and a reply
    arriving on that same link would wait behind the tick that waits for it.

    Args:
        url: the ``xbee://`` URL (for messages).
        keys: the experiment's bus keys.
        agent: the agent's name.
        endpoints: bus endpoints to open the link's session with.
        security: the agent's credentials for that session (``None``: none).
        session: use this session instead (not closed by the board; for tests and tools that
            do not exchange from a bus callback).
        sim: the simulated robot's board URL, or ``None``.
        plant: the simulated robot's plant.
        dt: its plant step [s].
        options: :class:`SerialBoard` options.
    """

    def __init__(
        self,
        url: str,
        *,
        keys: bus.BusKeys,
        agent: str,
        endpoints: list[str] | None = None,
        security: bus.SessionSecurity | None = None,
        session: zenoh.Session | None = None,
        sim: str | None = None,
        plant: Any | None = None,
        dt: float | None = None,
        **options: Any,
    ) -> None:
        super().__init__(url, port_factory=self._bus_port, port_url=url, **options)
        self.keys = keys
        self.agent = agent
        self.endpoints = list(endpoints or [])
        self.security = security
        self.session = session
        self._own_session = session is None
        self.sim = sim
        self.plant = plant
        self.dt = dt
        self.robot: Any | None = None
        self._exchanged = False

    def exchange(self, writes: Mapping[int, int], reads: Sequence[int]) -> TickReply:
        """:meth:`SerialBoard.exchange`, noting it for :meth:`take_link_stages`."""
        self._exchanged = True
        return super().exchange(writes, reads)

    def take_link_stages(self) -> tuple[float, float]:
        """The gateway's stage times ``(gateway_s, radio_s)`` [s] of the last answer of the
        exchanges since the previous call, for the agent's tick ledger: ``(0, 0)`` when there
        was no exchange, NaN when none was answered with stage times (the exchange failed)."""
        if not self._exchanged:
            return 0.0, 0.0
        self._exchanged = False
        port = self._port
        stages = port.stages if isinstance(port, BusPort) else None
        return (math.nan, math.nan) if stages is None else stages

    def _bus_port(self, _url: str, _baud: int, poll_s: float) -> SerialPort:
        session = self._require_session()
        try:
            return BusPort(
                session, self.keys.link_tx(self.agent), self.keys.link_rx(self.agent), poll_s
            )
        except zenoh.ZError as exc:
            raise BoardConnectionError(f"{self.url}: cannot declare the bus keys: {exc}") from exc

    def _require_session(self) -> zenoh.Session:
        if self.session is None:
            if not self.endpoints:
                raise BoardConnectionError(f"{self.url}: no bus endpoint to reach the gateway")
            self.session = bus.open_session(
                bus.client_config(self.endpoints, security=self.security)
            )
        return self.session

    def open(self) -> BoardInfo:
        """Start the simulated robot (if any), then the HELLO handshake through the gateway."""
        try:
            if self.sim is not None and self.robot is None:
                from hilswarm.agents.xbee.robot_host import RobotHost  # noqa: PLC0415 - sim only

                self.robot = RobotHost(
                    self.sim,
                    self._require_session(),
                    self.keys,
                    self.agent,
                    plant=self.plant,
                    dt=self.dt,
                )
                self.robot.start()
            return super().open()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Close the link, stop the simulated robot and close the link's own session."""
        super().close()
        robot, self.robot = self.robot, None
        if robot is not None:
            robot.stop()
        if self._own_session and self.session is not None:
            session, self.session = self.session, None
            with contextlib.suppress(zenoh.ZError):
                session.close()

    def __repr__(self) -> str:
        return f"XBeeBoard({self.url!r})"


def board_from_url(
    url: str,
    *,
    endpoints: list[str] | None = None,
    session: zenoh.Session | None = None,
    experiment: str | None = None,
    run_id: str = "",
    security: bus.SessionSecurity | None = None,
    agent: str | None = None,
    plant: Any | None = None,
    dt: float | None = None,
    **options: Any,
) -> XBeeBoard:
    """Build the board of ``xbee://<address>[?sim=...&timeout_s=...]`` for agent ``agent``.

    Raises:
        LinkUrlError: a bad URL, or no bus endpoints (or session) / agent name to reach the
            gateway with.
    """
    link = parse_xbee_url(url)
    if (session is None and not endpoints) or experiment is None or agent is None:
        raise LinkUrlError(
            f"link URL {url!r}: an xbee:// board is reached through the experiment's gateway "
            "over the bus; run it with `hilswarm run` or `hilswarm agent`"
        )
    settings: dict[str, Any] = {
        "timeout_s": DEFAULT_TIMEOUT_S,
        "open_timeout_s": DEFAULT_OPEN_TIMEOUT_S,
        "reconnect_timeout_s": 0.0,  # the bus port does not vanish; the gateway reconnects
        **dict(link.options),
        **options,
    }
    return XBeeBoard(
        url,
        keys=bus.BusKeys(experiment, run_id),
        agent=agent,
        endpoints=endpoints,
        security=security,
        session=session,
        sim=link.sim,
        plant=plant,
        dt=dt,
        **settings,
    )

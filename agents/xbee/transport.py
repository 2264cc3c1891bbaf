"""``xbee://<64-bit address>``: a board behind the XBee gateway, reached over the bus.

The robot's radio is in transparent mode on the Arduino's UART, so the board speaks the same
wire protocol as over USB. :func:`board_from_url` therefore returns a
:class:`~hilswarm.agents.link.serial_board.SerialBoard` whose "serial port" is a
:class:`BusPort`: writes go to ``agent/<name>/link/tx`` (the gateway sends them by radio),
reads come from ``agent/<name>/link/rx``. Seq numbers, CRC, retries, reconnection and every
:class:`~hilswarm.agents.link.serial_board.LinkEvent` work as on a USB link; the timeouts are
those of a radio hop (:data:`DEFAULT_TIMEOUT_S`).

With ``?sim=sim://<profile>`` or ``?sim=simavr://<profile>`` (for ``[gateway] port = "sim"``)
the agent's process also runs the simulated robot behind that address
(:class:`~.robot_host.RobotHost`), with the vehicle's simulated hardware as plant.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Any

import zenoh
from hilswarm.agents import bus
from hilswarm.agents.errors import BoardConnectionError, LinkUrlError
from hilswarm.agents.link.board import BoardInfo
from hilswarm.agents.link.serial_board import SerialBoard, SerialPort
from hilswarm.agents.xbee.config import parse_xbee_url

#: Reply wait of one exchange over the radio before a re-send [s] (a round trip through the
#: gateway takes ~10 ms; several robots share the air).
DEFAULT_TIMEOUT_S = 0.25
#: How long the first HELLO is retried [s] (the gateway and the robot start with the run).
DEFAULT_OPEN_TIMEOUT_S = 10.0


class BusPort:
    """A byte stream over two bus keys, with the part of pyserial's API SerialBoard uses.

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
        self._pub = session.declare_publisher(tx_key, **bus.TICK_PATH_QOS)
        self._sub = session.declare_subscriber(rx_key, self._on_rx)

    def _on_rx(self, sample: zenoh.Sample) -> None:
        """Bus callback: append and wake the reader (short, never blocks on I/O)."""
        with self._cond:
            self._buffer += sample.payload.to_bytes()
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
        self._pub.put(bytes(data))
        return len(data)

    def close(self) -> None:
        """Undeclare. Idempotent."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        for entity in (self._sub, self._pub):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()


class XBeeBoard(SerialBoard):
    """A :class:`SerialBoard` over a :class:`BusPort`; also runs the simulated robot if any."""

    def __init__(self, url: str, *, robot: Any | None = None, **options: Any) -> None:
        super().__init__(url, **options)
        self.robot = robot

    def open(self) -> BoardInfo:
        """Start the simulated robot (if any), then the HELLO handshake through the gateway."""
        if self.robot is not None:
            self.robot.start()
        try:
            return super().open()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Close the link and stop the simulated robot."""
        super().close()
        if self.robot is not None:
            self.robot.stop()

    def __repr__(self) -> str:
        return f"XBeeBoard({self.url!r})"


def board_from_url(
    url: str,
    *,
    session: zenoh.Session | None = None,
    experiment: str | None = None,
    agent: str | None = None,
    plant: Any | None = None,
    dt: float | None = None,
    **options: Any,
) -> XBeeBoard:
    """Build the board of ``xbee://<address>[?sim=...&timeout_s=...]`` for agent ``agent``.

    Raises:
        LinkUrlError: a bad URL, or no bus session / agent name to reach the gateway with.
    """
    link = parse_xbee_url(url)
    if session is None or experiment is None or agent is None:
        raise LinkUrlError(
            f"link URL {url!r}: an xbee:// board is reached through the experiment's gateway; "
            "it needs the agent's bus session (run it with `hilswarm run` or `hilswarm agent`)"
        )
    keys = bus.BusKeys(experiment)
    settings: dict[str, Any] = {
        "timeout_s": DEFAULT_TIMEOUT_S,
        "open_timeout_s": DEFAULT_OPEN_TIMEOUT_S,
        "reconnect_timeout_s": 0.0,  # the bus port does not vanish; the gateway reconnects
        **dict(link.options),
        **options,
    }

    def factory(_url: str, _baud: int, poll_s: float) -> SerialPort:
        try:
            return BusPort(session, keys.link_tx(agent), keys.link_rx(agent), poll_s)
        except zenoh.ZError as exc:
            raise BoardConnectionError(f"{url}: cannot declare the bus keys: {exc}") from exc

    robot = None
    if link.sim is not None:
        from hilswarm.agents.xbee.robot_host import RobotHost  # noqa: PLC0415 - sim only

        robot = RobotHost(link.sim, session, keys, agent, plant=plant, dt=dt)
    return XBeeBoard(url, robot=robot, port_factory=factory, port_url=url, **settings)

"""The far end of a simulated remote radio: the robot's UART (an Arduino running the firmware).

A :class:`RobotUart` is a byte stream with the robot on the other side: :meth:`~RobotUart.write`
sends bytes to the robot, the robot's bytes come back through the ``on_bytes`` callback given
to :meth:`~RobotUart.start` (from any thread: the receiver hands them off). Implementations:

* :class:`WireServerUart` — an in-process :class:`~hilswarm.agents.link.wire_server.WireServer`
  around a board (a ``SimBoard``): the protocol-checking Python "firmware".
* :class:`SerialUart` — any pyserial URL: a ``simavr`` harness's pty (the real firmware) or a
  ``socket://`` robot served elsewhere.
* :class:`SimavrUart` — starts the real firmware in simavr and is a :class:`SerialUart` on it.
* :class:`BusUart` — a robot run by its agent's process (:mod:`.robot_host`), its UART bytes on
  the bus keys ``agent/<name>/link/robot/{in,out}``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable
from typing import Protocol

import serial
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.link.board import Board
from hilswarm.agents.link.simavr import SimavrHarness
from hilswarm.agents.link.wire_server import WireServer

_log = logging.getLogger(__name__)

BytesCallback = Callable[[bytes], None]


class RobotUart(Protocol):
    """The robot side of a remote radio's UART (see the module docstring)."""

    def start(self, on_bytes: BytesCallback) -> None:
        """Begin delivering the robot's bytes to ``on_bytes``."""
        ...

    def write(self, data: bytes) -> None:
        """Send ``data`` to the robot."""
        ...

    def stop(self) -> None:
        """Release the robot. Idempotent."""
        ...


class WireServerUart:
    """A board behind an in-process :class:`WireServer` (answers synchronously).

    Args:
        server: the wire server, or a board to wrap in one.
    """

    def __init__(self, server: WireServer | Board) -> None:
        self.server = server if isinstance(server, WireServer) else WireServer(server)
        self._on_bytes: BytesCallback | None = None

    def start(self, on_bytes: BytesCallback) -> None:
        """Remember the callback."""
        self._on_bytes = on_bytes

    def write(self, data: bytes) -> None:
        """Feed ``data`` to the server; its reply goes to the callback at once."""
        reply = self.server.handle_bytes(data)
        if reply and self._on_bytes is not None:
            self._on_bytes(reply)

    def stop(self) -> None:
        """Nothing to release."""
        self._on_bytes = None


class SerialUart:
    """A robot behind a pyserial URL, read by a background thread.

    Args:
        url: pyserial URL or device path.
        baudrate: line speed [baud].
    """

    def __init__(self, url: str, *, baudrate: int = 115200) -> None:
        self.url = url
        self.baudrate = baudrate
        self._port: serial.SerialBase | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self, on_bytes: BytesCallback) -> None:
        """Open the port and start the reader thread."""
        self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.05)
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._read, args=(on_bytes,), name=f"robot-uart-{self.url}", daemon=True
        )
        self._thread.start()

    def _read(self, on_bytes: BytesCallback) -> None:
        port = self._port
        while port is not None and not self._stop.is_set():
            try:
                data = port.read(1)
                if data and port.in_waiting:
                    data += port.read(port.in_waiting)
            except (serial.SerialException, OSError) as exc:
                if not self._stop.is_set():
                    _log.warning("robot UART %s failed: %s", self.url, exc)
                return
            if data:
                try:
                    on_bytes(data)
                except Exception:  # the receiver failed (e.g. closed): stop reading
                    if not self._stop.is_set():
                        _log.exception("robot UART %s: receiver failed", self.url)
                    return

    def write(self, data: bytes) -> None:
        """Write to the robot (dropped, as on a dead UART, when the port is gone)."""
        port = self._port
        if port is None:
            return
        try:
            port.write(data)
        except (serial.SerialException, OSError) as exc:
            _log.warning("robot UART %s: write failed: %s", self.url, exc)

    def stop(self) -> None:
        """Stop the reader and close the port."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=2.0)
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()


class SimavrUart(SerialUart):
    """The real firmware in simavr (``profile``: uno, duemilanove, fio) as the robot.

    Args:
        profile: simavr board profile.
        paced: simulated time follows the wall clock (real UART timing).
    """

    def __init__(self, profile: str = "uno", *, paced: bool = True) -> None:
        self.harness = SimavrHarness(profile, paced=paced)  # raises if the firmware is not built
        super().__init__("")

    def start(self, on_bytes: BytesCallback) -> None:
        """Start the harness and read its pty."""
        self.url = self.harness.start()
        super().start(on_bytes)

    def stop(self) -> None:
        """Close the pty and stop the harness."""
        super().stop()
        self.harness.stop()


class BusUart:
    """A robot whose UART is carried by the bus (its agent's process runs it).

    Args:
        session: a bus session.
        keys: the experiment's keys.
        agent: the agent whose simulated robot it is.
    """

    def __init__(self, session: zenoh.Session, keys: bus.BusKeys, agent: str) -> None:
        self.session = session
        self.keys = keys
        self.agent = agent
        self._entities: list[object] = []
        self._pub: zenoh.Publisher | None = None

    def start(self, on_bytes: BytesCallback) -> None:
        """Declare the keys; the robot's bytes go to ``on_bytes`` (a short hand-off)."""
        self._pub = self.session.declare_publisher(
            self.keys.link_robot(self.agent, "in"), **bus.TICK_PATH_QOS
        )
        self._entities = [
            self._pub,
            self.session.declare_subscriber(
                self.keys.link_robot(self.agent, "out"),
                lambda sample: on_bytes(sample.payload.to_bytes()),
            ),
        ]

    def write(self, data: bytes) -> None:
        """Put ``data`` on the robot's ``in`` key."""
        if self._pub is not None:
            with contextlib.suppress(zenoh.ZError):
                self._pub.put(data)

    def stop(self) -> None:
        """Undeclare. Idempotent."""
        for entity in self._entities:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()  # type: ignore[attr-defined]
        self._entities = []
        self._pub = None

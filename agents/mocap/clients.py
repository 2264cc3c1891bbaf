"""Clients of real mocap systems, each through a well-kept library, behind one interface.

* ``qualisys`` and ``sim`` — ``qtm-rt``, Qualisys' own Python SDK for the QTM RT protocol over
  TCP. Chosen over ``motioncapture``'s Qualisys backend because the latter's Python bindings
  expose neither the frame timestamp nor the frame number, stream over UDP to a fixed port,
  and block in ``waitForNextFrame`` with no timeout (a lost server cannot be told apart from a
  quiet one). ``qtm-rt`` gives all three, reports the disconnect, and is what the built-in
  simulator (:mod:`.qtm_sim`) is tested against end to end.
* ``vicon``, ``optitrack``, ``vrpn`` — ``motioncapture`` (the Python bindings of
  libmotioncapture: Vicon DataStream SDK, NatNet, VRPN). It gives names, positions [m] and
  quaternions; frames are timed on arrival, and a server that stops sending is detected by
  silence (:data:`SILENCE_FRAMES` frame periods).

:meth:`MocapClient.run` blocks, calling ``on_frame`` with each :class:`Frame` in the
*system's* convention (mapped into the world frame by the caller, :mod:`.frames`), until
:meth:`MocapClient.stop` or the server is lost (:class:`MocapServerLost`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol
from xml.etree import ElementTree

import numpy as np
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.mocap.frames import quaternion_to_rotation

logger = logging.getLogger(__name__)

#: QTM's little-endian RT port.
QTM_PORT = 22223
#: Frame periods of silence after which a server counts as lost.
SILENCE_FRAMES = 50
#: Bound on connecting and on each command [s].
DEFAULT_TIMEOUT_S = 5.0


class MocapConnectionError(HilswarmError, ConnectionError):
    """The mocap server could not be reached or refused the session."""


class MocapServerLost(HilswarmError, ConnectionError):  # noqa: N818 - a domain event name
    """The mocap server went away (connection closed, or silent) while streaming."""


@dataclass(frozen=True)
class Frame:
    """One frame, in the system's own convention.

    Attributes:
        number: the system's frame number.
        time_s: the system's timestamp [s] (arrival time when the system gives none).
        received_s: arrival at this client [s, CLOCK_MONOTONIC].
        bodies: body name -> ``(position [system units], R body -> system)`` or ``None``
            when the body is not tracked in this frame.
        skipped: frames that arrived before this one and were dropped unprocessed because the
            consumer fell behind (a real-time consumer wants the newest frame, not a backlog).
    """

    number: int
    time_s: float
    received_s: float
    bodies: dict[str, tuple[np.ndarray, np.ndarray] | None]
    skipped: int = 0


class MocapClient(Protocol):
    """What the mocap process needs of a client."""

    bodies: tuple[str, ...]
    rate_hz: float | None

    def run(self, on_frame: Callable[[Frame], None], on_ready: Callable[[], None]) -> None:
        """Connect and stream until stopped (returns) or the server is lost (raises)."""

    def stop(self) -> None:
        """Make :meth:`run` return (thread-safe)."""


def body_names(xml: bytes | str) -> tuple[tuple[str, ...], float | None]:
    """Rigid body names and frame rate [Hz] from a QTM ``GetParameters General 6D`` answer."""
    text = xml.decode() if isinstance(xml, bytes) else xml
    try:
        root = ElementTree.fromstring(text.rstrip("\0"))
    except ElementTree.ParseError as exc:
        raise MocapConnectionError(f"QTM sent unreadable parameters: {exc}") from exc
    names = tuple((n.text or "").strip() for n in root.findall("./The_6D/Body/Name"))
    frequency = root.findtext("./General/Frequency")
    try:
        rate = float(frequency) if frequency else None
    except ValueError:
        rate = None
    return names, rate


class QualisysClient:
    """QTM RT protocol over TCP through ``qtm-rt`` (see the module docstring).

    Args:
        host: QTM's address.
        port: its little-endian RT port (default :data:`QTM_PORT`).
        timeout_s: bound on connecting and on each command [s].
        clock: monotonic clock [s] for arrival times.
    """

    def __init__(
        self,
        host: str,
        port: int = QTM_PORT,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self._clock = clock
        self.bodies: tuple[str, ...] = ()
        self.rate_hz: float | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopped: asyncio.Event | None = None
        self._stop_requested = threading.Event()

    def stop(self) -> None:
        """Make :meth:`run` return (thread-safe)."""
        self._stop_requested.set()
        loop, stopped = self._loop, self._stopped
        if loop is not None and stopped is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(stopped.set)

    def run(self, on_frame: Callable[[Frame], None], on_ready: Callable[[], None]) -> None:
        """Connect, read the body list, stream 6D frames until stopped or lost."""
        asyncio.run(self._run(on_frame, on_ready))

    async def _run(self, on_frame: Callable[[Frame], None], on_ready: Callable[[], None]) -> None:
        import qtm_rt  # noqa: PLC0415 - only the qualisys/sim systems need it

        # qtm-rt logs a refused connection itself; it is reported here as an exception.
        logging.getLogger("qtm_rt").setLevel(logging.CRITICAL)
        self._loop = asyncio.get_running_loop()
        self._stopped = asyncio.Event()
        if self._stop_requested.is_set():
            return
        lost: list[str] = []

        def on_disconnect(exc: Exception | None) -> None:
            lost.append(f"{exc}" if exc else "the server closed the connection")
            self._stopped.set()

        where = f"QTM at {self.host}:{self.port}"
        try:
            connection = await asyncio.wait_for(
                qtm_rt.connect(
                    self.host,
                    port=self.port,
                    version="1.25",
                    on_disconnect=on_disconnect,
                    timeout=self.timeout_s,
                ),
                self.timeout_s,
            )
        except (TimeoutError, OSError) as exc:
            raise MocapConnectionError(f"cannot connect to {where}: {exc}") from exc
        if connection is None:
            raise MocapConnectionError(f"cannot connect to {where} (refused or wrong protocol)")
        try:
            xml = await connection.get_parameters(["general", "6d"])
            self.bodies, self.rate_hz = body_names(xml)
            names = self.bodies
            clock = self._clock

            loop = self._loop
            pending: list[tuple[Any, float]] = []

            def on_packet(packet: Any) -> None:
                # Runs once per packet while qtm-rt parses a chunk: only queue it; the newest
                # packet of the chunk is handled right after (a backlog is dropped, counted).
                if not pending:
                    loop.call_soon(handle_newest)
                pending.append((packet, clock()))

            def handle_newest() -> None:
                packet, received = pending[-1]
                skipped = len(pending) - 1
                pending.clear()
                found = packet.get_6d()
                entries = found[1] if found is not None else []
                bodies: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
                for name, (position, rotation) in zip(names, entries, strict=False):
                    p = np.array((position.x, position.y, position.z))
                    if not np.all(np.isfinite(p)):
                        bodies[name] = None
                        continue
                    # QTM's rotation matrix is column-major (RT protocol documentation).
                    r = np.array(rotation.matrix, dtype=np.float64).reshape(3, 3).T
                    bodies[name] = (p, r)
                frame = Frame(
                    packet.framenumber, packet.timestamp * 1e-6, received, bodies, skipped
                )
                on_frame(frame)

            await connection.stream_frames(
                frames="allframes", components=["6d"], on_packet=on_packet
            )
        except (qtm_rt.QRTCommandException, TimeoutError) as exc:
            connection.disconnect()
            raise MocapConnectionError(f"{where} refused the session: {exc}") from exc
        on_ready()
        await self._stopped.wait()
        if lost and not self._stop_requested.is_set():
            raise MocapServerLost(f"mocap server {where} lost: {lost[0]}")
        if connection.has_transport():
            await connection.stream_frames_stop()
            connection.disconnect()


class MotionCaptureClient:
    """Vicon, OptiTrack (NatNet) or VRPN through ``motioncapture`` (see the module docstring).

    Args:
        system: ``"vicon"``, ``"optitrack"`` or ``"vrpn"`` (libmotioncapture's type names).
        host: the server's address.
        rate_hz: the system's frame rate [Hz] (for the silence watchdog).
        clock: monotonic clock [s] for arrival times.
    """

    def __init__(
        self,
        system: str,
        host: str,
        *,
        rate_hz: float = 100.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.system, self.host = system, host
        self.rate_hz: float | None = rate_hz
        self.bodies: tuple[str, ...] = ()
        self._clock = clock
        self._stop = threading.Event()

    def stop(self) -> None:
        """Make :meth:`run` return (thread-safe)."""
        self._stop.set()

    def run(self, on_frame: Callable[[Frame], None], on_ready: Callable[[], None]) -> None:
        """Connect and stream; ``waitForNextFrame`` runs on a daemon thread (it has no timeout)."""
        try:
            import motioncapture  # noqa: PLC0415 - only these systems need it
        except ImportError as exc:
            raise MocapConnectionError(f"the motioncapture package is missing: {exc}") from exc
        try:
            mc = motioncapture.connect(self.system, {"hostname": self.host})
        except RuntimeError as exc:
            raise MocapConnectionError(
                f"cannot connect to {self.system} at {self.host}: {exc}"
            ) from exc
        frames: list[Frame] = []
        arrived = threading.Condition()
        failure: list[str] = []

        def pump() -> None:
            number = 0
            try:
                while not self._stop.is_set():
                    mc.waitForNextFrame()
                    received = self._clock()
                    number += 1
                    bodies: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
                    for name, body in mc.rigidBodies.items():
                        q = body.rotation
                        bodies[name] = (
                            np.asarray(body.position, dtype=np.float64),
                            quaternion_to_rotation(q.w, q.x, q.y, q.z),
                        )
                    with arrived:
                        frames.append(Frame(number, received, received, bodies))
                        arrived.notify()
            except RuntimeError as exc:
                with arrived:
                    failure.append(str(exc))
                    arrived.notify()

        threading.Thread(target=pump, name=f"{self.system}-frames", daemon=True).start()
        silence_s = SILENCE_FRAMES / (self.rate_hz or 100.0)
        ready = False
        while not self._stop.is_set():
            with arrived:
                if not frames and not failure:
                    arrived.wait(silence_s)
                batch, frames[:] = list(frames), []
                failed = list(failure)
            if failed:
                raise MocapServerLost(f"{self.system} server at {self.host} lost: {failed[0]}")
            if not batch:
                raise MocapServerLost(
                    f"{self.system} server at {self.host} silent for {silence_s:.2f} s"
                )
            newest = batch[-1]  # a backlog is dropped (counted): the newest frame matters
            self.bodies = tuple(sorted(set(self.bodies) | set(newest.bodies)))
            on_frame(
                Frame(
                    newest.number, newest.time_s, newest.received_s, newest.bodies, len(batch) - 1
                )
            )
            if not ready:
                ready = True
                on_ready()


def make_client(system: str, host: str, port: int | None, rate_hz: float) -> MocapClient:
    """The client for ``system`` (see the module docstring)."""
    if system in ("qualisys", "sim"):
        return QualisysClient(host, port or QTM_PORT)
    if system in ("vicon", "optitrack", "vrpn"):
        return MotionCaptureClient(
            system, host if port is None else f"{host}:{port}", rate_hz=rate_hz
        )
    raise MocapConnectionError(f"unknown mocap system {system!r}")

"""Clients of real mocap systems, each through a well-kept library, behind one interface.

* ``qualisys`` and ``sim`` — ``qtm-rt``, Qualisys' own Python SDK for the QTM RT protocol over
  TCP. Chosen over ``motioncapture``'s Qualisys backend because the latter's Python bindings
  expose neither the frame timestamp nor the frame number, stream over UDP to a fixed port,
  and block in ``waitForNextFrame`` with no timeout (a lost server cannot be told apart from a
  quiet one). ``qtm-rt`` gives all three, reports the disconnect, and is what the built-in
  simulator (:mod:`.qtm_sim`) is tested against end to end.
* ``vicon``, ``optitrack``, ``vrpn`` — ``motioncapture`` (the Python bindings of
  libmotioncapture: Vicon DataStream SDK, NatNet, VRPN), run in a worker process
  (:mod:`.mc_worker`: the bindings hold the GIL while they wait, and an OptiTrack connect with
  no server never returns). It gives names, positions [m] and quaternions; frames are timed on
  arrival; connecting is bounded (:data:`DEFAULT_TIMEOUT_S`), and a server that stops sending
  is detected by silence (:data:`SILENCE_FRAMES` frame periods). VRPN's client reports no
  connection state and paces empty frames by itself, so for VRPN only frames with a body count:
  no body within the bound is a connection error, no body for the silence period a lost server.

:meth:`MocapClient.run` blocks, calling ``on_frame`` with each :class:`Frame` in the
*system's* convention (mapped into the world frame by the caller, :mod:`.frames`), until
:meth:`MocapClient.stop` or the server is lost (:class:`MocapServerLost`). Every client first
looks the server's name up (:func:`check_resolves`): neither library tells a name that does not
resolve from a refused or silent server.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol
from xml.etree import ElementTree

import numpy as np
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.mocap.frames import quaternion_to_rotation
from hilswarm.agents.mocap.mc_worker import RecordError, RecordReader

logger = logging.getLogger(__name__)

#: QTM's little-endian RT port.
QTM_PORT = 22223
#: Frame periods of silence after which a server counts as lost.
SILENCE_FRAMES = 50
#: Bound on connecting and on each command [s].
DEFAULT_TIMEOUT_S = 5.0
#: How often a waiting client looks at its stop flag [s].
_POLL_S = 0.05
#: Frames read past at most at once when a client has fallen behind.
_MAX_BACKLOG = 1000


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


def qtm_bodies(
    names: Sequence[str], entries: Sequence[tuple[Any, Any]]
) -> dict[str, tuple[np.ndarray, np.ndarray] | None]:
    """:attr:`Frame.bodies` from a QTM 6D packet's ``(position, rotation)`` entries, in the
    order of ``names`` (the 6D parameters' bodies; extra entries or names are ignored).

    Positions [mm] are the entries' ``x, y, z``; QTM's rotation ``matrix`` is column-major
    (RT protocol documentation), so ``R`` (body -> system) is its transpose. A body whose
    position is not finite (QTM sends NaN for an untracked body) maps to ``None``. Every body
    at once, as two arrays (at 16 bodies and 240 Hz the per-body arrays cost ~0.1 ms a frame
    on the frames' way to the agents); each body's ``(p, R)`` are views of them.
    """
    count = min(len(names), len(entries))
    if count == 0:
        return {}
    kept = entries[:count]
    positions = np.array([entry[0] for entry in kept], dtype=np.float64).reshape(count, 3)
    matrices = np.array([entry[1].matrix for entry in kept], dtype=np.float64)
    rotations = matrices.reshape(count, 3, 3).transpose(0, 2, 1)
    seen = np.isfinite(positions).all(axis=1).tolist()
    return {
        name: (positions[i], rotations[i]) if seen[i] else None
        for i, name in enumerate(names[:count])
    }


class MocapClient(Protocol):
    """What the mocap process needs of a client."""

    bodies: tuple[str, ...]
    rate_hz: float | None

    def run(self, on_frame: Callable[[Frame], None], on_ready: Callable[[], None]) -> None:
        """Connect and stream until stopped (returns) or the server is lost (raises)."""

    def stop(self) -> None:
        """Make :meth:`run` return (thread-safe)."""


def host_of(address: str) -> str:
    """The host of ``host``, ``host:port`` or ``[v6 address]:port``."""
    if address.startswith("["):
        return address[1:].partition("]")[0]
    if address.count(":") == 1:  # more colons: an IPv6 address without a port
        return address.partition(":")[0]
    return address


def check_resolves(host: str, where: str, *, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
    """Raise :class:`MocapConnectionError` saying so when ``host`` is a name that does not
    resolve (``socket.gaierror``). A lookup still running after ``timeout_s``, or another
    error, is left to the client (its own connection bound then applies).
    """
    failed: list[socket.gaierror] = []

    def look_up() -> None:
        try:
            socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
        except socket.gaierror as exc:
            failed.append(exc)
        except (OSError, UnicodeError):  # not a name-resolution failure: the client reports it
            return

    lookup = threading.Thread(target=look_up, name="mocap-resolve", daemon=True)
    lookup.start()
    lookup.join(timeout_s)
    if failed:
        raise MocapConnectionError(
            f"cannot connect to {where}: the host name {host!r} does not resolve "
            f"(name resolution failed: {failed[0].strerror or failed[0]})"
        )


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
        check_resolves(self.host, f"QTM at {self.host}:{self.port}", timeout_s=self.timeout_s)
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
                bodies = qtm_bodies(names, found[1] if found is not None else [])
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
        clock: monotonic clock [s] for the deadlines.
        connect_timeout_s: bound on connecting (VRPN: on the first body) [s].
    """

    def __init__(
        self,
        system: str,
        host: str,
        *,
        rate_hz: float = 100.0,
        clock: Callable[[], float] = time.monotonic,
        connect_timeout_s: float = DEFAULT_TIMEOUT_S,
    ) -> None:
        self.system, self.host = system, host
        self.rate_hz: float | None = rate_hz
        self.connect_timeout_s = connect_timeout_s
        self.bodies: tuple[str, ...] = ()
        self._clock = clock
        self._stop = threading.Event()

    def stop(self) -> None:
        """Make :meth:`run` return (thread-safe)."""
        self._stop.set()

    def run(self, on_frame: Callable[[Frame], None], on_ready: Callable[[], None]) -> None:
        """Connect and stream, the library in a worker process (:mod:`.mc_worker`: it holds the
        GIL while it waits); every wait here has a deadline.

        Raises:
            MocapConnectionError: no connection within :attr:`connect_timeout_s` (for VRPN: no
                body, as VRPN reports no connection state), or the library refused, or the
                host's name does not resolve.
            MocapServerLost: the worker failed, or no frame (VRPN: no frame with a body) came
                for :data:`SILENCE_FRAMES` frame periods.
        """
        check_resolves(
            host_of(self.host),
            f"{self.system} at {self.host}",
            timeout_s=self.connect_timeout_s,
        )
        worker = subprocess.Popen(
            [sys.executable, "-m", "hilswarm.agents.mocap.mc_worker", self.system, self.host],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            start_new_session=True,
        )  # fmt: skip
        # The library's own chatter ("tracker: cf1", version notes) goes to the log, not the
        # user's terminal; the thread ends when the worker's stderr closes.
        threading.Thread(
            target=_log_lines, args=(worker.stderr, f"{self.system} client"), daemon=True
        ).start()
        try:
            self._stream(RecordReader(worker.stdout.fileno()), on_frame, on_ready)  # type: ignore[union-attr]
        finally:
            worker.kill()  # it may be inside the library, holding its own GIL
            worker.wait(DEFAULT_TIMEOUT_S)
            if worker.stdout is not None:
                worker.stdout.close()

    def _next(
        self, reader: RecordReader, timeout_s: float, *, streaming: bool = False
    ) -> tuple[Any, ...] | None:
        """The worker's next record; its error record raises — a connection error before the
        stream began, a lost server (the library failed while waiting for a frame) after."""
        try:
            record = reader.read(timeout_s)
        except (EOFError, RecordError) as exc:
            raise MocapServerLost(f"{self.system} client at {self.host} failed: {exc}") from exc
        if record is not None and record[0] == "error":
            if streaming:
                raise MocapServerLost(f"{self.system} server at {self.host} lost: {record[1]}")
            raise MocapConnectionError(str(record[1]))
        return record

    def _stream(
        self, reader: RecordReader, on_frame: Callable[[Frame], None], on_ready: Callable[[], None]
    ) -> None:
        where = f"{self.system} at {self.host}"
        deadline = self._clock() + self.connect_timeout_s
        try:
            connected = False
            while not connected and self._clock() < deadline and not self._stop.is_set():
                record = self._next(reader, min(_POLL_S, max(0.0, deadline - self._clock())))
                connected = record is not None and record[0] == "ready"
        except MocapServerLost as exc:
            raise MocapConnectionError(f"cannot connect to {where}: {exc}") from exc
        if self._stop.is_set():
            return
        if not connected:
            raise MocapConnectionError(
                f"no {self.system} server answered at {self.host} within "
                f"{self.connect_timeout_s:g} s"
            )
        # VRPN's client paces empty frames itself, server or not: only a body proves a server.
        needs_body = self.system == "vrpn"
        silence_s = SILENCE_FRAMES / (self.rate_hz or 100.0)
        last_heard, number, ready = self._clock(), 0, False
        first_by = last_heard + self.connect_timeout_s  # the first frame's deadline
        if needs_body:
            first = (
                f"no body from {where} within {self.connect_timeout_s:g} s (VRPN reports no "
                "connection state: the server is unreachable or tracks no body)"
            )
        else:
            first = f"{where} connected but sent no frame within {self.connect_timeout_s:g} s"

        def usable(record: tuple[Any, ...] | None) -> bool:
            if record is None or record[0] != "frame":
                return False
            return bool(record[2]) or not needs_body

        while not self._stop.is_set():
            record = self._next(reader, _POLL_S, streaming=True)
            now = self._clock()
            if not usable(record):
                if not ready and now > first_by:
                    raise MocapConnectionError(first)
                if ready and now - last_heard > silence_s:
                    raise MocapServerLost(f"{self.system} server at {self.host} silent for "
                                          f"{now - last_heard:.2f} s")  # fmt: skip
                continue
            skipped, failure = 0, None  # a backlog is dropped (counted): the newest frame matters
            for _ in range(_MAX_BACKLOG):
                try:
                    newer = self._next(reader, 0.0, streaming=True)
                except MocapServerLost as exc:
                    failure = exc  # raised once the frames before it are given
                    break
                if newer is None:
                    break
                if usable(newer):
                    record, skipped = newer, skipped + 1
            _, received, listed = record  # type: ignore[misc]
            last_heard, number = now, number + 1 + skipped
            bodies: dict[str, tuple[np.ndarray, np.ndarray] | None] = {
                name: (np.asarray(p, dtype=np.float64), quaternion_to_rotation(*q))
                for name, p, q in listed
            }
            self.bodies = tuple(sorted(set(self.bodies) | set(bodies)))
            on_frame(Frame(number, received, received, bodies, skipped))
            if not ready:
                ready = True
                on_ready()
            if failure is not None:
                raise failure


def _log_lines(stream: Any, what: str) -> None:
    """Log each line of ``stream`` (a worker's stderr) at INFO until it closes."""
    with stream:
        for raw in iter(stream.readline, b""):
            logger.info("%s: %s", what, raw.decode(errors="replace").rstrip())


def make_client(system: str, host: str, port: int | None, rate_hz: float) -> MocapClient:
    """The client for ``system`` (see the module docstring)."""
    if system in ("qualisys", "sim"):
        return QualisysClient(host, port or QTM_PORT)
    if system in ("vicon", "optitrack", "vrpn"):
        return MotionCaptureClient(
            system, host if port is None else f"{host}:{port}", rate_hz=rate_hz
        )
    raise MocapConnectionError(f"unknown mocap system {system!r}")

"""A protocol-level Qualisys (QTM RT protocol, TCP) server on loopback, fed by true poses.

The mocap counterpart of ``simavr://``: the real client library (``qtm-rt``, Qualisys' own
Python SDK) connects to it unchanged, so the whole client path runs with no hardware. It
speaks the little-endian RT protocol (version 1.x) over one TCP connection per client —
unicast only, no discovery broadcast, no UDP:

* every packet is ``uint32 size`` (header included), ``uint32 type`` (0 error, 1 command,
  2 XML, 3 data, 4 no more data, 6 event), then the body; commands and their answers are
  NUL-terminated ASCII;
* on connection the server says ``QTM RT Interface connected``; the client then sets the
  protocol version (``Version 1.25`` -> ``Version set to 1.25``);
* ``GetParameters General 6D`` -> an XML packet naming the rigid bodies and the frame rate;
* ``StreamFrames AllFrames|Frequency:n|FrequencyDivisor:n 6D`` -> data packets until
  ``StreamFrames Stop``; ``GetCurrentFrame 6D`` -> one data packet;
* a data packet: ``int64 timestamp [µs]``, ``uint32 frame number``, ``uint32 component
  count``, then per component ``uint32 size``, ``uint32 type`` (5: 6D): ``int32 body count``,
  ``uint16 drop rate``, ``uint16 out-of-sync rate``, then per body (in parameter order) the
  position ``3 x float32`` [mm] and the rotation matrix ``9 x float32`` (column-major); a body
  that is not tracked has NaN everywhere, as QTM sends it.

Stricter than QTM: anything but the version command before the version is set, an unknown
command or component, a malformed packet or a command with no terminating NUL is answered with
an error packet (a malformed packet also closes the connection).

The frames carry the simulator's camera time: ``CLOCK_MONOTONIC`` in µs (the same clock every
process of this host reads), so a client on this host can measure latency from the frame's
exposure. Noise, occlusion (random dropouts and scripted windows), latency and frame rate are
configurable (:class:`SimSettings`) and the noise is seeded. True poses come in through
:meth:`QtmSimulator.set_truth` (the simulator process feeds them from the bus,
:mod:`hilswarm.agents.mocap.sim_process`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import struct
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from xml.sax.saxutils import escape

import numpy as np
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.mocap.frames import rotation_zyx, rotations_zyx

logger = logging.getLogger(__name__)

PROTOCOL_VERSION = "1.25"
QTM_VERSION = "QTM Version is 2024.2 (build 1) -- hilswarm protocol simulator"
HEADER = struct.Struct("<II")
TYPE_ERROR, TYPE_COMMAND, TYPE_XML, TYPE_DATA, TYPE_NO_MORE_DATA, TYPE_EVENT = 0, 1, 2, 3, 4, 6
COMPONENT_6D = 5
#: Largest command packet accepted [bytes] (a command is a short line).
MAX_COMMAND = 4096
_DATA_HEAD = struct.Struct("<qII")
_COMPONENT_HEAD = struct.Struct("<II")
_6D_HEAD = struct.Struct("<ihh")
_BODY = struct.Struct("<12f")
_NAN_BODY = _BODY.pack(*([math.nan] * 12))


class SimulatorError(HilswarmError, RuntimeError):
    """The simulator could not start (bad settings, port in use)."""


@dataclass(frozen=True)
class SimSettings:
    """What the simulated camera system does.

    Attributes:
        bodies: rigid body names, in the order the system lists them.
        rate_hz: camera frame rate [Hz].
        noise_std_m: position noise per axis [m] (Gaussian, seeded).
        noise_std_rad: attitude noise per Euler angle [rad].
        latency_s: exposure -> packet sent [s].
        dropout_rate: probability per body and frame that an occlusion starts.
        dropout_frames: length of a random occlusion [frames].
        occlusions: scripted occlusions, body -> ``(start_s, end_s)``: in experiment time
            when the true poses carry it (the agents' plants), else counted from the first
            frame that has the body's true pose.
        seed: seed of the noise and dropout generator.
    """

    bodies: tuple[str, ...]
    rate_hz: float = 100.0
    noise_std_m: float = 0.0
    noise_std_rad: float = 0.0
    latency_s: float = 0.0
    dropout_rate: float = 0.0
    dropout_frames: int = 5
    occlusions: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.bodies or len(set(self.bodies)) != len(self.bodies):
            raise SimulatorError(f"simulator: bodies must be distinct names, got {self.bodies}")
        checks = (
            ("rate_hz", self.rate_hz, 0.0, 10000.0, False),
            ("noise_std_m", self.noise_std_m, 0.0, 10.0, True),
            ("noise_std_rad", self.noise_std_rad, 0.0, 10.0, True),
            ("latency_s", self.latency_s, 0.0, 10.0, True),
            ("dropout_rate", self.dropout_rate, 0.0, 1.0, True),
        )
        for name, value, low, high, inclusive in checks:
            ok = isinstance(value, int | float) and math.isfinite(value)
            ok = ok and (low <= value if inclusive else low < value) and value <= high
            if not ok:
                raise SimulatorError(f"simulator: {name} = {value!r} is out of range")
        unknown = [name for name in self.occlusions if name not in self.bodies]
        if unknown:
            raise SimulatorError(f"simulator: occlusions name unknown bodies {unknown}")


def parameters_xml(bodies: Sequence[str], rate_hz: float, parts: Sequence[str]) -> str:
    """The ``GetParameters`` answer for ``parts`` (``general``, ``6d``), as QTM lays it out."""
    out = [f"<QTM_Parameters_Ver_{PROTOCOL_VERSION}>"]
    if "general" in parts or "all" in parts:
        out.append(
            f"<General><Frequency>{rate_hz:g}</Frequency><Capture_Time>0</Capture_Time>"
            "<Start_On_External_Trigger>False</Start_On_External_Trigger></General>"
        )
    if "6d" in parts or "all" in parts:
        out.append(f"<The_6D><Bodies>{len(bodies)}</Bodies>")
        for name in bodies:
            out.append(
                f"<Body><Name>{escape(name)}</Name><Enabled>true</Enabled>"
                '<Color R="255" G="0" B="0"/><MaximumResidual>10</MaximumResidual>'
                "<MinimumMarkersInBody>3</MinimumMarkersInBody></Body>"
            )
        out.append("</The_6D>")
    out.append(f"</QTM_Parameters_Ver_{PROTOCOL_VERSION}>")
    return "".join(out)


def packet(kind: int, body: bytes) -> bytes:
    """One RT packet: header and body."""
    return HEADER.pack(HEADER.size + len(body), kind) + body


def text_packet(kind: int, text: str) -> bytes:
    """A command/error/XML packet (NUL-terminated ASCII)."""
    return packet(kind, text.encode() + b"\0")


def data_packet(timestamp_us: int, frame: int, bodies: Sequence[bytes]) -> bytes:
    """A data packet with one 6D component of the packed ``bodies`` (see :data:`_BODY`)."""
    return _data_packet(timestamp_us, frame, b"".join(bodies), len(bodies))


def _data_packet(timestamp_us: int, frame: int, body_bytes: bytes, count: int) -> bytes:
    component = (
        _COMPONENT_HEAD.pack(_COMPONENT_HEAD.size + _6D_HEAD.size + len(body_bytes), COMPONENT_6D)
        + _6D_HEAD.pack(count, 0, 0)
        + body_bytes
    )
    return packet(TYPE_DATA, _DATA_HEAD.pack(timestamp_us, frame, 1) + component)


def pack_bodies(poses: np.ndarray) -> bytes:
    """The 6D body entries of world poses ``(n, 6)`` ``[x, y, z (m), roll, pitch, yaw
    (rad)]``, in one go (a row with a non-finite value: an untracked body, NaN everywhere);
    the same bytes as :func:`pack_body` of each row."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    entries = np.full((poses.shape[0], 12), np.nan, dtype="<f4")
    seen = np.isfinite(poses).all(axis=1)
    if seen.any():
        tracked = poses[seen]
        rotations = rotations_zyx(tracked[:, 3:])
        entries[seen, :3] = tracked[:, :3] * 1e3
        entries[seen, 3:] = rotations.transpose(0, 2, 1).reshape(-1, 9)  # column-major
    return entries.tobytes()


def pack_body(pose: np.ndarray | None) -> bytes:
    """A 6D body entry from a world pose ``[x, y, z (m), roll, pitch, yaw (rad)]`` (None: NaN)."""
    if pose is None or not np.all(np.isfinite(pose)):
        return _NAN_BODY
    x, y, z, roll, pitch, yaw = (float(v) for v in pose)
    rotation = rotation_zyx(roll, pitch, yaw)
    return _BODY.pack(x * 1e3, y * 1e3, z * 1e3, *rotation.T.reshape(9).tolist())


class _Client(asyncio.Protocol):
    """One client connection: parses command packets, answers, streams."""

    def __init__(self, server: QtmSimulator) -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.buffer = b""
        self.version: str | None = None
        self.streaming = False
        self.divisor = 1

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        self.server.clients.add(self)
        self.send(text_packet(TYPE_COMMAND, "QTM RT Interface connected"))

    def connection_lost(self, exc: Exception | None) -> None:
        self.server.clients.discard(self)
        self.transport = None

    def send(self, data: bytes) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(data)

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        while len(self.buffer) >= HEADER.size:
            size, kind = HEADER.unpack_from(self.buffer)
            if size < HEADER.size + 1 or size > MAX_COMMAND or kind != TYPE_COMMAND:
                self.fail(f"malformed packet (size {size}, type {kind})")
                return
            if len(self.buffer) < size:
                return
            body, self.buffer = self.buffer[HEADER.size : size], self.buffer[size:]
            if not body.endswith(b"\0"):
                self.send(text_packet(TYPE_ERROR, "Command not NUL-terminated"))
                continue
            self.command(body[:-1].decode("ascii", "replace").strip())

    def fail(self, reason: str) -> None:
        logger.warning("simulator: %s; closing the connection", reason)
        self.send(text_packet(TYPE_ERROR, reason))
        if self.transport is not None:
            self.transport.close()

    def command(self, line: str) -> None:
        words = line.split()
        verb = words[0].lower() if words else ""
        args = [w.lower() for w in words[1:]]
        if verb == "version":
            if len(args) == 1 and args[0].startswith("1."):
                self.version = args[0]
                self.send(text_packet(TYPE_COMMAND, f"Version set to {args[0]}"))
            else:
                self.send(text_packet(TYPE_ERROR, f"Version NOT supported: {line}"))
            return
        if self.version is None:
            self.send(text_packet(TYPE_ERROR, "Set the protocol version first (Version 1.x)"))
            return
        if verb == "qtmversion":
            self.send(text_packet(TYPE_COMMAND, QTM_VERSION))
        elif verb == "byteorder":
            self.send(text_packet(TYPE_COMMAND, "Byte order is little endian"))
        elif verb == "getstate":
            self.send(packet(TYPE_EVENT, bytes([1])))  # EventConnected
        elif verb == "getparameters":
            known = {"all", "general", "6d"}
            if not args or any(a not in known for a in args):
                self.send(text_packet(TYPE_ERROR, f"Parse error: {line}"))
            else:
                settings = self.server.settings
                xml = parameters_xml(settings.bodies, settings.rate_hz, args)
                self.send(text_packet(TYPE_XML, xml))
        elif verb == "getcurrentframe":
            if args != ["6d"]:
                self.send(text_packet(TYPE_ERROR, f"Parse error: {line}"))
            else:
                self.send(self.server.last_packet or packet(TYPE_NO_MORE_DATA, b""))
        elif verb == "streamframes":
            self.stream(args, line)
        else:
            self.send(text_packet(TYPE_ERROR, f"Parse error: {line}"))

    def stream(self, args: list[str], line: str) -> None:
        if args == ["stop"]:
            self.streaming = False
            return
        if len(args) != 2 or args[1] != "6d":
            self.send(text_packet(TYPE_ERROR, f"Parse error (only the 6D component): {line}"))
            return
        rate = self.server.settings.rate_hz
        how, _, value = args[0].partition(":")
        try:
            if how == "allframes" and not value:
                divisor = 1
            elif how == "frequencydivisor":
                divisor = int(value)
            elif how == "frequency":
                divisor = max(1, round(rate / float(value)))
            else:
                raise ValueError(how)
            if divisor < 1:
                raise ValueError(value)
        except ValueError:
            self.send(text_packet(TYPE_ERROR, f"Parse error: {line}"))
            return
        self.divisor, self.streaming = divisor, True


class QtmSimulator:
    """The server (see the module docstring); runs its own event loop on a thread.

    Args:
        settings: bodies, rate, noise, occlusion, latency, seed.
        host: address to listen on (loopback).
        port: TCP port; 0 picks a free one (see :attr:`port` after :meth:`start`).
        clock_ns: monotonic clock [ns] of the camera time stamps (CLOCK_MONOTONIC).
    """

    def __init__(
        self,
        settings: SimSettings,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        clock_ns: object = time.monotonic_ns,
    ) -> None:
        self.settings = settings
        self.host = host
        self.port = port
        self._clock_ns = clock_ns
        self.clients: set[_Client] = set()
        self.last_packet: bytes | None = None
        self.frames_sent = 0
        self._truth: dict[str, np.ndarray] = {}
        self._rng = np.random.default_rng(settings.seed)
        self._occluded_until = dict.fromkeys(settings.bodies, -1)
        self._appeared: dict[str, float] = {}  # body -> elapsed time of its first truth [s]
        self._truth_t: dict[str, float] = {}  # body -> experiment time of its truth [s]
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._stop: asyncio.Event | None = None

    # -- feeding -----------------------------------------------------------------------------

    def set_truth(self, body: str, pose: np.ndarray, *, t: float | None = None) -> None:
        """The true world pose of ``body`` (thread-safe; the next frame measures it).

        Args:
            body: the rigid body.
            pose: ``[x, y, z (m), roll, pitch, yaw (rad)]``, world frame.
            t: the experiment time it holds for [s] (scripted occlusions follow it); ``None``
                or NaN: no experiment time (before the run, or a free-running feed).
        """
        if body in self._occluded_until:
            self._truth[body] = np.asarray(pose, dtype=np.float64).reshape(6).copy()
            if t is not None:
                self._truth_t[body] = t

    # -- life cycle --------------------------------------------------------------------------

    def start(self, timeout_s: float = 10.0) -> int:
        """Start listening and streaming on a thread; returns the TCP port."""
        self._thread = threading.Thread(target=self._run, name="qtm-simulator", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout_s):
            raise SimulatorError(f"simulator did not start within {timeout_s} s")
        if self._error is not None:
            raise SimulatorError(f"simulator could not listen: {self._error}") from self._error
        return self.port

    def close(self) -> None:
        """Stop streaming, close every connection and the listening socket."""
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(5.0)

    def __enter__(self) -> QtmSimulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        try:
            asyncio.run(self._serve())
        except OSError as exc:
            self._error = exc
            self._started.set()

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        server = await self._loop.create_server(lambda: _Client(self), self.host, self.port)
        self.port = server.sockets[0].getsockname()[1]
        self._started.set()
        frames = asyncio.create_task(self._frames())
        await self._stop.wait()
        frames.cancel()
        server.close()
        for client in list(self.clients):
            if client.transport is not None:
                client.transport.abort()
        with contextlib.suppress(asyncio.CancelledError):
            await frames
        await server.wait_closed()

    # -- frames ------------------------------------------------------------------------------

    async def _frames(self) -> None:
        loop = self._loop
        period = 1.0 / self.settings.rate_hz
        start = loop.time()
        frame = 0
        while True:
            frame += 1
            due = start + frame * period
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            elif delay < -10 * period:  # far behind (a stalled machine): skip, keep the grid
                frame += int(-delay / period)
                continue
            data = self._frame(frame, (frame - 1) * period)
            self.last_packet = data
            latency = self.settings.latency_s
            if latency > 0:
                loop.call_later(latency, self._send, frame, data)
            else:
                self._send(frame, data)

    def _send(self, frame: int, data: bytes) -> None:
        for client in list(self.clients):
            if client.streaming and frame % client.divisor == 0:
                client.send(data)
        self.frames_sent += 1

    def _frame(self, frame: int, elapsed_s: float) -> bytes:
        settings, rng = self.settings, self._rng
        timestamp_us = self._clock_ns() // 1000  # type: ignore[operator]
        # Every body at once (at 16 bodies one at a time took ~0.26 ms between the time stamp
        # and the send): the occlusions body by body, then the noise of the tracked ones.
        measured = np.full((len(settings.bodies), 6), np.nan)
        for i, name in enumerate(settings.bodies):
            truth = self._truth.get(name)
            if truth is not None and not self._occluded(name, frame, elapsed_s):
                measured[i] = truth
        seen = np.isfinite(measured).all(axis=1)
        tracked = int(seen.sum())
        if tracked and settings.noise_std_m:
            measured[seen, :3] += rng.normal(0.0, settings.noise_std_m, (tracked, 3))
        if tracked and settings.noise_std_rad:
            measured[seen, 3:] += rng.normal(0.0, settings.noise_std_rad, (tracked, 3))
        return _data_packet(timestamp_us, frame, pack_bodies(measured), len(settings.bodies))

    def _occluded(self, name: str, frame: int, elapsed_s: float) -> bool:
        window = self.settings.occlusions.get(name)
        if window is not None and name in self._truth:
            since = elapsed_s - self._appeared.setdefault(name, elapsed_s)
            if name in self._truth_t:  # experiment time (NaN before the run: never occluded)
                since = self._truth_t[name]
            if window[0] <= since < window[1]:
                return True
        if self.settings.dropout_rate:
            if frame <= self._occluded_until[name]:
                return True
            if self._rng.random() < self.settings.dropout_rate:
                self._occluded_until[name] = frame + self.settings.dropout_frames - 1
                return True
        return False

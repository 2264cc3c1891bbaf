"""A VRPN tracker server on loopback: the protocol-level stand-in for a VRPN mocap stream.

VRPN is what Vicon Tracker, OptiTrack Motive and many other systems stream besides their own
protocols; ``motioncapture`` (libmotioncapture's VRPN backend, :mod:`.clients`) connects to
this server unchanged, so the ``system = "vrpn"`` client path runs end to end with no hardware.

The protocol (VRPN 07.xx, big-endian, every message 8-byte aligned):

* **Connecting.** A client named ``host:port`` sends a UDP datagram to ``port``:
  ``"<its address> <its TCP port>\\0"``; the server connects back over TCP to that port. A
  client named ``tcp://host:port`` connects over TCP directly. Both then exchange 24-byte
  cookies (``"vrpn: ver. 07.35  0"`` padded with NUL); a cookie of another major version is
  refused (the connection closed), as the real library does.
* **Names.** Each body is a tracker: one ``SENDER_DESCRIPTION`` message (type -1, the sender id
  being described, a body of ``u32 length`` + the name and its NUL), and one
  ``TYPE_DESCRIPTION`` (type -2) for ``"vrpn_Tracker Pos_Quat"``.
* **Poses.** Per frame, per body in view: ``vrpn_Tracker Pos_Quat``, the body ``i32 sensor (0)``,
  ``i32 padding``, position ``x y z`` [m] and quaternion ``x y z w`` (VRPN's order), doubles.
  A body out of view sends nothing, as a real VRPN server does.
* **Framing.** A 24-byte header: ``i32 length`` (24 + the unpadded body), ``i32 seconds``,
  ``i32 microseconds`` (the frame time), ``i32 sender``, ``i32 type``, 4 bytes of padding; the
  body padded with NUL to 8 bytes.

Everything arriving from a client (its own descriptions, its UDP port) is read and dropped.
Poses come from ``poses()``, called once per frame on the server's thread: body name -> (position
[m], quaternion ``(w, x, y, z)``) in the system's convention (z up for VRPN), or ``None`` while
out of view.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import time
from collections.abc import Callable, Mapping, Sequence

from hilswarm.agents.mocap.paced_server import PacedServer

logger = logging.getLogger(__name__)

#: The cookie this server sends (VRPN 07.35, no remote logging).
COOKIE = b"vrpn: ver. 07.35  0".ljust(24, b"\0")
#: What a compatible peer's cookie starts with (the major version must match).
COOKIE_PREFIX = b"vrpn: ver. 07."
SENDER_DESCRIPTION = -1
TYPE_DESCRIPTION = -2
POS_QUAT = "vrpn_Tracker Pos_Quat"
#: The type id this server gives :data:`POS_QUAT` (its type description says so).
POS_QUAT_ID = 0
_HEADER = struct.Struct(">iiiii4x")
_POS_QUAT = struct.Struct(">ii3d4d")
#: Bound on a client's cookie and on connecting back to it [s].
HANDSHAKE_TIMEOUT_S = 2.0

Pose = tuple[Sequence[float], Sequence[float]]


def message(sender: int, kind: int, body: bytes, t: float) -> bytes:
    """One framed VRPN message (module docstring), stamped ``t`` [s since the Unix epoch]."""
    seconds = int(t)
    head = _HEADER.pack(_HEADER.size + len(body), seconds, int((t - seconds) * 1e6), sender, kind)
    return head + body + b"\0" * (-len(body) % 8)


def description(name: str) -> bytes:
    """The body of a sender or type description: ``u32`` length (NUL included) + name + NUL."""
    raw = name.encode() + b"\0"
    return struct.pack(">I", len(raw)) + raw


class VrpnTrackerServer(PacedServer):
    """A VRPN server on ``host`` (loopback) with one tracker per body (module docstring).

    Args:
        bodies: the tracker names, in sender-id order.
        poses: per frame, body name -> (position [m], quaternion ``(w, x, y, z)``) or ``None``
            (out of view); called on the server's thread.
        rate_hz: frame rate [Hz].
        host: the address to listen on (UDP and TCP, the same port).
        port: the port (0: a free one, :attr:`port` tells which).
    """

    def __init__(
        self,
        bodies: Sequence[str],
        poses: Callable[[], Mapping[str, Pose | None]],
        *,
        rate_hz: float = 100.0,
        host: str = "127.0.0.1",
        port: int = 0,
    ) -> None:
        super().__init__(rate_hz, "vrpn-sim")
        self.bodies, self._poses = tuple(bodies), poses
        self.host = host
        self._udp, self._tcp = self._bind(host, port)
        self.port: int = self._udp.getsockname()[1]
        self._clients: list[socket.socket] = []
        self.refused = 0

    @staticmethod
    def _bind(host: str, port: int) -> tuple[socket.socket, socket.socket]:
        """A UDP and a TCP socket on one port number (retried when a free UDP port is taken
        for TCP)."""
        for _ in range(20):
            udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            try:
                udp.bind((host, port))
                tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                tcp.bind((host, udp.getsockname()[1]))
                tcp.listen(8)
                return udp, tcp
            except OSError:
                udp.close()
                tcp.close()
                if port:
                    raise
        raise OSError("no port free for both UDP and TCP")

    # -- the server's thread -----------------------------------------------------------------

    def _readable(self) -> list[socket.socket]:
        return [self._udp, self._tcp, *self._clients]

    def _close(self) -> None:
        for sock in (*self._clients, self._udp, self._tcp):
            sock.close()
        self._clients.clear()

    def _handshake(self, sock: socket.socket) -> None:
        """Cookies both ways, then the names; closes and counts a refused peer."""
        try:
            sock.settimeout(HANDSHAKE_TIMEOUT_S)
            sock.sendall(COOKIE)
            cookie = b""
            for _ in range(24):  # bounded: each pass reads at least one byte or fails
                if len(cookie) >= len(COOKIE):
                    break
                chunk = sock.recv(len(COOKIE) - len(cookie))
                if not chunk:
                    raise ConnectionError("closed during the handshake")
                cookie += chunk
            if not cookie.startswith(COOKIE_PREFIX):
                raise ConnectionError(f"incompatible cookie {cookie[:19]!r}")
            now = time.time()
            names = b"".join(
                message(i, SENDER_DESCRIPTION, description(name), now)
                for i, name in enumerate(self.bodies)
            )
            sock.sendall(names + message(POS_QUAT_ID, TYPE_DESCRIPTION, description(POS_QUAT), now))
            sock.setblocking(False)
        except OSError as exc:
            logger.info("vrpn sim: client refused: %s", exc)
            self.refused += 1
            sock.close()
            return
        self._clients.append(sock)

    def _on_readable(self, ready: list[socket.socket]) -> None:
        if self._udp in ready:
            datagram, _ = self._udp.recvfrom(512)
            try:
                address, port = datagram.rstrip(b"\0").decode("ascii").split()
                sock = socket.create_connection((address, int(port)), HANDSHAKE_TIMEOUT_S)
            except (ValueError, OSError) as exc:
                logger.info("vrpn sim: bad connection request %r: %s", datagram[:64], exc)
                self.refused += 1
            else:
                self._handshake(sock)
        if self._tcp in ready:
            sock, _ = self._tcp.accept()
            self._handshake(sock)
        for sock in [s for s in self._clients if s in ready]:
            try:
                alive = bool(sock.recv(65536))  # the client's own messages: dropped
            except BlockingIOError:
                alive = True
            except OSError:
                alive = False
            if not alive:
                self._drop(sock)

    def _drop(self, sock: socket.socket) -> None:
        with contextlib.suppress(ValueError):
            self._clients.remove(sock)
        sock.close()

    def _send_frame(self) -> None:
        poses, now = self._poses(), time.time()
        data = b"".join(
            message(i, POS_QUAT_ID, _POS_QUAT.pack(0, 0, *pose[0], *pose[1][1:], pose[1][0]), now)
            for i, name in enumerate(self.bodies)
            if (pose := poses.get(name)) is not None
        )
        self.frames += 1
        for sock in list(self._clients):
            try:
                sock.sendall(data)
            except OSError:  # BlockingIOError included: its buffer is full
                self._drop(sock)  # a client that cannot keep up is dropped, as a lost link

"""A NatNet server on loopback, unicast: the protocol-level stand-in for OptiTrack Motive.

OptiTrack's Motive streams rigid bodies with NatNet; ``motioncapture`` (libmotioncapture's
OptiTrack backend, :mod:`.clients`) connects to this server unchanged, so the
``system = "optitrack"`` client path runs end to end with no hardware.

The protocol (NatNet 3.1 or 4.1, little-endian, one UDP datagram per packet; every packet
starts with ``u16 message id`` and ``u16 byte count`` of what follows):

* **Commands** arrive on the command port (Motive's 1510; here a free one unless given).
  ``NAT_CONNECT`` (0) is answered with ``NAT_SERVERINFO`` (1): the application's name (256
  bytes), its version and the NatNet version (4 bytes each), the high-resolution clock's
  frequency (``u64`` ticks per second), the data port (``u16``), whether the stream is
  multicast (``u8``: never, here) and the multicast group (4 bytes). The sender becomes a
  client: frames go to its address at the data port. ``NAT_REQUEST_MODELDEF`` (4) is answered
  with ``NAT_MODELDEF`` (5): one rigid-body description per body (type 1; name, id, parent id
  -1, offset 0 0 0, no markers). ``NAT_KEEPALIVE`` (10) is accepted, ``NAT_DISCONNECT`` (9)
  drops the client. Anything else — another message id, a byte count that disagrees with the
  datagram's length — is answered with ``NAT_UNRECOGNIZED_REQUEST`` (100) and counted in
  :attr:`NatNetServer.refused`: stricter than Motive, which ignores what it does not know.
* **Frames** (``NAT_FRAMEOFDATA``, 7) at the frame rate, to every client's address at the data
  port: the frame number; no marker sets and no unlabeled markers; every body as a rigid body
  (id, position ``x y z`` [m], quaternion ``qx qy qz qw``, mean marker error [m], params whose
  bit 0 says "tracked in this frame": a body out of view is sent with that bit clear and a zero
  pose, as Motive does); no skeletons, (4.1: assets,) labeled markers, force plates or devices;
  the timecode, the frame's timestamp [s since the server started] and, from NatNet 3.0 on, the
  camera mid-exposure, camera-data-received and transmit times in clock ticks; the frame params
  and the end-of-data tag. From NatNet 4.1 on each list's count is followed by its size in
  bytes (and each model description by its size).

Poses come from ``poses()``, called once per frame on the server's thread: body name ->
(position [m], quaternion ``(w, x, y, z)``) in the system's convention (**y up** for Motive's
default streaming, :mod:`.frames`), or ``None`` while out of view.
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

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_FRAMEOFDATA = 7
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100
#: The NatNet versions this server speaks (major, minor).
VERSIONS = ((3, 1), (4, 1))
#: The high-resolution clock's frequency the server announces [ticks/s].
CLOCK_HZ = 10_000_000
#: Motive's version the server announces.
APP_VERSION = bytes((3, 1, 0, 0))
_HEAD = struct.Struct("<HH")
_I32 = struct.Struct("<i")
#: Rigid body in a frame: id, x y z, qx qy qz qw, mean marker error, params.
_RIGID_BODY = struct.Struct("<i3f4ffh")
_MAX_DATAGRAM = 65507

Pose = tuple[Sequence[float], Sequence[float]]


def packet(message_id: int, body: bytes) -> bytes:
    """One NatNet packet: ``u16`` id, ``u16`` byte count, the body."""
    return _HEAD.pack(message_id, len(body)) + body


def free_udp_port(host: str = "0.0.0.0") -> int:
    """A UDP port free on ``host`` now (libmotioncapture binds its data port on every address)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


class NatNetServer(PacedServer):
    """A NatNet server on ``host`` (loopback), unicast, one rigid body per body (module docstring).

    Args:
        bodies: the rigid bodies' names, in id order (ids 1, 2, ...).
        poses: per frame, body name -> (position [m], quaternion ``(w, x, y, z)``) or ``None``
            (out of view), y up; called on the server's thread.
        rate_hz: frame rate [Hz].
        host: the address to listen on and to send from.
        command_port: the command port (0: a free one, :attr:`command_port` tells which).
        data_port: the port the clients receive frames on (0: one free now).
        version: the NatNet version, one of :data:`VERSIONS`.
    """

    def __init__(
        self,
        bodies: Sequence[str],
        poses: Callable[[], Mapping[str, Pose | None]],
        *,
        rate_hz: float = 100.0,
        host: str = "127.0.0.1",
        command_port: int = 0,
        data_port: int = 0,
        version: tuple[int, int] = (3, 1),
    ) -> None:
        if tuple(version) not in VERSIONS:
            raise ValueError(f"NatNet version {version!r} is not one of {VERSIONS}")
        super().__init__(rate_hz, "natnet-sim")
        self.bodies, self._poses = tuple(bodies), poses
        self.version = (int(version[0]), int(version[1]))
        self.host = host
        self._command = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._command.bind((host, command_port))
        self.command_port: int = self._command.getsockname()[1]
        self.data_port = data_port or free_udp_port()
        self._data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._data.bind((host, 0))
        self.clients: set[str] = set()
        self._started_ns = time.monotonic_ns()
        self.refused = 0

    @property
    def sized(self) -> bool:
        """Whether each list and description carries its size in bytes (NatNet 4.1 and later)."""
        return self.version >= (4, 1)

    # -- packets ---------------------------------------------------------------------------------

    def server_info(self) -> bytes:
        """``NAT_SERVERINFO``: unicast, frames to the data port."""
        major, minor = self.version
        body = (
            b"Motive".ljust(256, b"\0")
            + APP_VERSION
            + bytes((major, minor, 0, 0))
            + struct.pack("<QH?4s", CLOCK_HZ, self.data_port, False, bytes((239, 255, 42, 99)))
        )
        return packet(NAT_SERVERINFO, body)

    def model_definitions(self) -> bytes:
        """``NAT_MODELDEF``: one rigid-body description (type 1) per body."""
        datasets = b""
        for body_id, name in enumerate(self.bodies, start=1):
            description = name.encode() + b"\0" + struct.pack("<ii3fi", body_id, -1, 0, 0, 0, 0)
            size = _I32.pack(len(description)) if self.sized else b""
            datasets += _I32.pack(1) + size + description
        return packet(NAT_MODELDEF, _I32.pack(len(self.bodies)) + datasets)

    def _list(self, items: Sequence[bytes]) -> bytes:
        """A count, (4.1: the size in bytes,) the items."""
        data = b"".join(items)
        return _I32.pack(len(items)) + (_I32.pack(len(data)) if self.sized else b"") + data

    def frame(self, number: int, poses: Mapping[str, Pose | None], now_ns: int) -> bytes:
        """``NAT_FRAMEOFDATA`` number ``number`` with ``poses`` at ``now_ns`` [ns, monotonic]."""
        rigid = []
        for body_id, name in enumerate(self.bodies, start=1):
            pose = poses.get(name)
            if pose is None:  # out of view: sent, untracked, as Motive does
                rigid.append(_RIGID_BODY.pack(body_id, 0, 0, 0, 0, 0, 0, 0, 0.0, 0))
                continue
            (x, y, z), (qw, qx, qy, qz) = pose
            rigid.append(_RIGID_BODY.pack(body_id, x, y, z, qx, qy, qz, qw, 0.0002, 1))
        ticks = (now_ns - self._started_ns) * CLOCK_HZ // 1_000_000_000
        body = _I32.pack(number) + self._list([]) + self._list([]) + self._list(rigid)
        body += self._list([])  # skeletons
        if self.sized:
            body += self._list([])  # assets
        body += self._list([]) + self._list([]) + self._list([])  # labeled markers, plates, devices
        body += struct.pack("<IId", 0, 0, ticks / CLOCK_HZ)
        body += struct.pack("<QQQ", max(0, ticks - 20_000), max(0, ticks - 5_000), ticks)
        body += struct.pack("<hi", 0, 0)  # frame params, end of data
        return packet(NAT_FRAMEOFDATA, body)

    # -- the server's thread ---------------------------------------------------------------------

    def _readable(self) -> list[socket.socket]:
        return [self._command]

    def _on_readable(self, ready: list[socket.socket]) -> None:
        self._command_in()

    def _close(self) -> None:
        self._command.close()
        self._data.close()
        self.clients.clear()

    def _command_in(self) -> None:
        datagram, sender = self._command.recvfrom(_MAX_DATAGRAM)
        if len(datagram) < _HEAD.size:
            self._refuse(sender, f"a datagram of {len(datagram)} bytes")
            return
        message_id, count = _HEAD.unpack_from(datagram)
        if count != len(datagram) - _HEAD.size:
            self._refuse(sender, f"byte count {count} in a packet of {len(datagram)} bytes")
        elif message_id == NAT_CONNECT:
            self.clients.add(sender[0])
            self._command.sendto(self.server_info(), sender)
        elif message_id == NAT_REQUEST_MODELDEF:
            self._command.sendto(self.model_definitions(), sender)
        elif message_id == NAT_DISCONNECT:
            self.clients.discard(sender[0])
        elif message_id != NAT_KEEPALIVE:
            self._refuse(sender, f"message id {message_id}")

    def _refuse(self, sender: tuple[str, int], what: str) -> None:
        logger.info("natnet sim: refused %s from %s:%d", what, *sender)
        self.refused += 1
        with contextlib.suppress(OSError):
            self._command.sendto(packet(NAT_UNRECOGNIZED_REQUEST, b""), sender)

    def _send_frame(self) -> None:
        data = self.frame(self.frames, self._poses(), time.monotonic_ns())
        self.frames += 1
        for address in list(self.clients):
            with contextlib.suppress(OSError):  # UDP: a client not listening loses the frame
                self._data.sendto(data, (address, self.data_port))

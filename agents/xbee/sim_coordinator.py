"""A simulated XBee coordinator on a pseudo-terminal, with simulated remote radios and the air.

:class:`SimCoordinator` opens a pty that a gateway (or digi-xbee, or X-CTU) opens like the USB
port of a real coordinator: it speaks API frames (mode 1 or 2) of the 802.15.4 family (0x00 /
0x80 / 0x89) or the ZigBee/DigiMesh family (0x10 / 0x90 / 0x8B), answers local AT commands
(``HV``/``VR`` tell which family, as on a real radio), node discovery (``ND``) and remote AT
commands. Every byte is paced by the models of :mod:`.air`: the host UART at ``BD`` both ways,
the seeded 802.15.4 air (backoff, ACK, retries, per-link loss, payload limit) and each remote's
UART to its robot. It is stricter than the hardware: a frame of the other family, an RF payload
over ``NP`` or an unknown destination is refused with the status a radio gives.

Each :class:`SimRemote` is a radio in *transparent* mode on a robot's UART (the robots need no
new wiring): RF data it receives goes out of its UART; what the robot sends is packetized
(``RO`` quiet characters, or a full payload) and sent by unicast to the coordinator (``DH``/``DL``).

Faults: :meth:`SimCoordinator.unplug` / :meth:`SimCoordinator.replug` (the USB cable; the port
path is a stable symlink that points at the new pty), :meth:`SimCoordinator.set_out_of_range`
(no ACK from a robot) and per-link loss probabilities.
"""

from __future__ import annotations

import contextlib
import logging
import os
import random
import select
import struct
import tempfile
import threading
import tty
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from hilswarm.agents.xbee.air import Air, AirParams, uart_s
from hilswarm.agents.xbee.api_frames import (
    BROADCAST_64,
    ApiFrame,
    ApiFrameDecoder,
    ApiMode,
    AtCommand,
    AtQueuedCommand,
    AtResponse,
    FrameFamily,
    ModemStatus,
    ReceivePacket,
    RemoteAtCommand,
    RemoteAtResponse,
    Rx64Packet,
    TransmitRequest,
    TransmitStatus,
    Tx64Request,
    TxStatus,
    TxStatusCode,
    encode_frame,
)
from hilswarm.agents.xbee.event_loop import EventLoop
from hilswarm.agents.xbee.sim_robot import RobotUart

_log = logging.getLogger(__name__)

#: Default 64-bit address of the simulated coordinator.
COORDINATOR_ADDRESS = 0x0013A200400000FF
#: ``HV`` / ``VR`` a real radio of each family reports (what digi-xbee reads to tell them apart):
#: XBee 802.15.4 (XB24-A, hardware 0x17xx, firmware 10xx) and ZigBee (XB24-B, 0x19xx, 21xx).
FAMILY_VERSIONS: dict[FrameFamily, tuple[bytes, bytes]] = {
    FrameFamily.IEEE_802_15_4: (b"\x17\x42", b"\x10\xef"),
    FrameFamily.ZIGBEE: (b"\x19\x4a", b"\x21\xa7"),
}
#: ``BD`` code -> baud rate.
BAUD_CODES = {0: 1200, 1: 2400, 2: 4800, 3: 9600, 4: 19200, 5: 38400, 6: 57600, 7: 115200}
#: AT status codes.
AT_OK, AT_ERROR, AT_BAD_COMMAND, AT_BAD_PARAMETER, AT_NO_RESPONSE = 0, 1, 2, 3, 4
_POLL_S = 0.05


def baud_code(baud: int) -> int:
    """The ``BD`` code of ``baud`` (raises ``ValueError`` for a rate the radio lacks)."""
    for code, rate in BAUD_CODES.items():
        if rate == baud:
            return code
    raise ValueError(f"{baud} baud is not a standard XBee rate ({sorted(BAUD_CODES.values())})")


def _default_params(address: int, node_id: str, api_mode: int, baud: int) -> dict[str, bytes]:
    return {
        "SH": struct.pack(">I", address >> 32),
        "SL": struct.pack(">I", address & 0xFFFFFFFF),
        "MY": b"\xff\xfe",
        "NI": node_id.encode(),
        "AP": bytes((api_mode,)),
        "BD": struct.pack(">I", baud_code(baud)),
        "CH": b"\x0c",
        "ID": b"\x33\x32",
        "CE": b"\x00",
        "RR": b"\x00",
        "RO": b"\x03",
        "NP": b"\x00\x64",
        "NT": b"\x0a",  # node discovery time [100 ms]: 1 s (a real radio's default is 2.5 s)
        "DH": b"\x00\x00\x00\x00",
        "DL": b"\x00\x00\x00\x00",
        "MM": b"\x00",
        "AO": b"\x00",
        "DB": b"\x28",
        "EE": b"\x00",
        "NO": b"\x00",
        "SM": b"\x00",
        "D7": b"\x01",
        "D6": b"\x00",
    }


@dataclass
class RemoteStats:
    """What happened to one remote radio."""

    rx_packets: int = 0
    tx_packets: int = 0
    tx_failures: int = 0
    retries: int = 0
    rx_bytes: int = 0
    tx_bytes: int = 0


@dataclass
class SimRemote:
    """A remote XBee in transparent mode on a robot's UART.

    Attributes:
        address: its 64-bit address.
        robot: the robot's UART.
        node_id: its ``NI`` string.
        rssi_dbm: signal strength the coordinator hears it with [dBm].
        baud: its UART rate to the robot [baud].
    """

    address: int
    robot: RobotUart
    node_id: str = ""
    rssi_dbm: int = -45
    baud: int = 115200
    stats: RemoteStats = field(default_factory=RemoteStats)
    params: dict[str, bytes] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.params = {
            **_default_params(self.address, self.node_id or f"{self.address:016X}", 0, self.baud),
            "DB": bytes((min(-self.rssi_dbm, 255),)),
            **self.params,
        }
        self._pending = bytearray()  # robot bytes not yet packetized
        self._flush_at = 0.0
        self._uart_free_at = 0.0


@dataclass
class CoordinatorStats:
    """Totals of the simulated coordinator (host side)."""

    frames_in: int = 0
    frames_out: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    refused: int = 0


class SimCoordinator:
    """A simulated coordinator on a pty (see the module docstring). Use as a context manager.

    Args:
        remotes: the remote radios in range.
        api_mode: ``AP`` 1 or 2.
        family: the frame family its firmware speaks.
        baud: host UART rate [baud] (``BD``).
        address: its 64-bit address.
        air: the air model (default: :class:`Air` seeded with ``seed``).
        seed: random seed of the air and the RSSI noise.
        link_dir: folder of the stable port symlink (default: a new temporary folder).
    """

    def __init__(
        self,
        remotes: Iterable[SimRemote] = (),
        *,
        api_mode: int = 1,
        family: FrameFamily = FrameFamily.IEEE_802_15_4,
        baud: int = 115200,
        address: int = COORDINATOR_ADDRESS,
        air: Air | None = None,
        seed: int = 0,
        link_dir: str | Path | None = None,
    ) -> None:
        self.remotes: dict[int, SimRemote] = {r.address: r for r in remotes}
        self.family = family
        self.address = address
        self.air = air if air is not None else Air(AirParams(), seed=seed)
        self.params = _default_params(address, "COORDINATOR", int(api_mode), baud)
        hv, vr = FAMILY_VERSIONS[family]
        self.params.update(HV=hv, VR=vr)
        self.stats = CoordinatorStats()
        self.loop = EventLoop("xbee-sim-air")
        self._rng = random.Random(seed + 1)
        self._decoder = ApiFrameDecoder(ApiMode(api_mode))
        self._uart_in_free = 0.0
        self._uart_out_free = 0.0
        self._master: int | None = None
        self._slave: int | None = None
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._own_dir = link_dir is None
        self._dir = Path(tempfile.mkdtemp(prefix="xbee-sim-") if link_dir is None else link_dir)
        self.url = str(self._dir / "coordinator")
        self.plugged = False

    # ------------------------------------------------------------------ settings
    @property
    def api_mode(self) -> ApiMode:
        """The current ``AP`` setting."""
        return ApiMode(self.params["AP"][0])

    @property
    def baud(self) -> int:
        """The current host UART rate [baud]."""
        return BAUD_CODES[int.from_bytes(self.params["BD"], "big")]

    # ------------------------------------------------------------------ life cycle
    def start(self) -> SimCoordinator:
        """Start the air and the remotes, and plug the coordinator in."""
        self.loop.start()
        for remote in self.remotes.values():
            remote.robot.start(
                lambda data, r=remote: self.loop.call_soon(lambda: self._robot(r, data))
            )
        self.replug()
        return self

    def stop(self) -> None:
        """Unplug, stop the air and release the robots. Idempotent."""
        self.unplug()
        self.loop.stop()
        for remote in self.remotes.values():
            remote.robot.stop()
        if self._own_dir:
            with contextlib.suppress(OSError):
                os.rmdir(self._dir)

    def __enter__(self) -> SimCoordinator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def replug(self) -> None:
        """Plug the coordinator (back) in: a new pty behind the same port path."""
        if self.plugged:
            return
        master, slave = os.openpty()
        tty.setraw(slave)
        self._master, self._slave = master, slave
        link = Path(self.url)
        with contextlib.suppress(FileNotFoundError):
            link.unlink()
        link.symlink_to(os.ttyname(slave))
        self._decoder.reset()
        self._stop_reader.clear()
        self._reader = threading.Thread(target=self._read_host, name="xbee-sim-pty", daemon=True)
        self._reader.start()
        self.plugged = True
        self.loop.call_soon(lambda: self._send_host(ModemStatus(0)))  # hardware reset

    def unplug(self) -> None:
        """Pull the cable: the pty closes (the host's reads fail) and the port path vanishes."""
        if not self.plugged:
            return
        self.plugged = False
        self._stop_reader.set()
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.join(timeout=2.0)
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None
        with contextlib.suppress(FileNotFoundError):
            Path(self.url).unlink()

    def set_out_of_range(self, address: int, out: bool = True) -> None:
        """Put robot ``address`` out of range (every frame to or from it lost) or back."""
        self.loop.call_soon(lambda: self.air.set_loss(self.address, address, 1.0 if out else 0.0))

    def set_loss(self, address: int, probability: float) -> None:
        """Loss probability of one frame between the coordinator and ``address``."""
        self.loop.call_soon(lambda: self.air.set_loss(self.address, address, probability))

    # ------------------------------------------------------------------ host UART
    def _read_host(self) -> None:
        master = self._master
        while master is not None and not self._stop_reader.is_set():
            ready, _, _ = select.select([master], [], [], _POLL_S)
            if not ready:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:
                return
            if data:
                self.loop.call_soon(lambda d=data: self._host_bytes(d))

    def _host_bytes(self, data: bytes) -> None:
        """Bytes from the host arrive at the UART rate; each frame is handled when complete."""
        now = self.loop.clock()
        self.stats.bytes_in += len(data)
        self._uart_in_free = max(now, self._uart_in_free) + uart_s(len(data), self.baud)
        frames = self._decoder.feed(data)
        if frames:
            self.loop.call_at(self._uart_in_free, lambda: self._handle_frames(frames))

    def _send_host(self, frame: ApiFrame) -> None:
        """Queue ``frame`` on the UART to the host; written when its last byte is out."""
        wire = encode_frame(frame, self.api_mode)
        now = self.loop.clock()
        self._uart_out_free = max(now, self._uart_out_free) + uart_s(len(wire), self.baud)
        self.loop.call_at(self._uart_out_free, lambda: self._write_host(wire))

    def _write_host(self, wire: bytes) -> None:
        master = self._master
        if master is None or not self.plugged:
            return
        try:
            os.write(master, wire)
        except OSError as exc:
            _log.debug("simulated coordinator: host write failed: %s", exc)
            return
        self.stats.frames_out += 1
        self.stats.bytes_out += len(wire)

    # ------------------------------------------------------------------ frames from the host
    def _handle_frames(self, frames: list[ApiFrame]) -> None:
        for frame in frames:
            self.stats.frames_in += 1
            if isinstance(frame, Tx64Request | TransmitRequest):
                self._transmit(frame)
            elif isinstance(frame, AtCommand | AtQueuedCommand):
                self._at(frame)
            elif isinstance(frame, RemoteAtCommand):
                self._remote_at(frame)
            else:
                self.stats.refused += 1  # a frame a radio never receives from its host

    def _status(self, frame: Tx64Request | TransmitRequest, status: int, retries: int) -> None:
        if frame.frame_id == 0:
            return
        if self.family == FrameFamily.IEEE_802_15_4:
            self._send_host(TxStatus(frame.frame_id, status))
        else:
            self._send_host(TransmitStatus(frame.frame_id, status, retries=min(retries, 255)))

    def _transmit(self, frame: Tx64Request | TransmitRequest) -> None:
        ieee = self.family == FrameFamily.IEEE_802_15_4
        if isinstance(frame, Tx64Request) != ieee:
            self.stats.refused += 1  # the other family's frame: a real radio ignores it
            return
        now = self.loop.clock()
        size = len(frame.data)
        if size > self.air.params.max_payload:
            self._status(frame, TxStatusCode.ZB_PAYLOAD_TOO_LARGE, 0)
            return
        if frame.dest == BROADCAST_64:
            tx = self.air.transmit(now, self.address, None, size)
            for remote in self.remotes.values():
                if tx.delivered_s is not None and not self.air.lost(self.address, remote.address):
                    self.loop.call_at(
                        tx.delivered_s, lambda r=remote: self._to_robot(r, frame.data)
                    )
            self.loop.call_at(tx.end_s, lambda: self._status(frame, TxStatusCode.SUCCESS, 0))
            return
        remote = self.remotes.get(frame.dest)
        if remote is None:  # nobody answers: every retry spent
            self.air.set_loss(self.address, frame.dest, 1.0)
        no_ack = options_disable_ack(frame)
        tx = self.air.transmit(now, self.address, None if no_ack else frame.dest, size)
        if (
            remote is not None
            and tx.delivered_s is not None
            and (not no_ack or not self.air.lost(self.address, remote.address))
        ):
            self.loop.call_at(tx.delivered_s, lambda: self._to_robot(remote, frame.data))
        ok = tx.acked or no_ack
        status = (
            TxStatusCode.SUCCESS
            if ok
            else (TxStatusCode.NO_ACK if ieee else TxStatusCode.ZB_MAC_ACK_FAILURE)
        )
        if remote is not None:
            remote.stats.retries += tx.retries
            remote.stats.tx_failures += 0 if ok else 1
        self.loop.call_at(tx.end_s, lambda: self._status(frame, status, tx.retries))

    # ------------------------------------------------------------------ remotes
    def _to_robot(self, remote: SimRemote, data: bytes) -> None:
        """RF data reached ``remote``: out of its UART to the robot at the robot's baud."""
        remote.stats.rx_packets += 1
        remote.stats.rx_bytes += len(data)
        now = self.loop.clock()
        remote._uart_free_at = max(now, remote._uart_free_at) + uart_s(len(data), remote.baud)
        self.loop.call_at(remote._uart_free_at, lambda: remote.robot.write(data))

    def _robot(self, remote: SimRemote, data: bytes) -> None:
        """Bytes from the robot's UART: packetize (``RO`` quiet chars or a full payload)."""
        remote._pending += data
        limit = self.air.params.max_payload
        while len(remote._pending) >= limit:
            chunk = bytes(remote._pending[:limit])
            del remote._pending[:limit]
            self._from_remote(remote, chunk)
        if remote._pending:
            quiet = uart_s(self.air.params.packetization_chars, remote.baud)
            remote._flush_at = self.loop.clock() + quiet
            self.loop.call_at(remote._flush_at, lambda: self._packet_timeout(remote))

    def _packet_timeout(self, remote: SimRemote) -> None:
        if remote._pending and self.loop.clock() >= remote._flush_at:
            chunk = bytes(remote._pending)
            remote._pending.clear()
            self._from_remote(remote, chunk)

    def _from_remote(self, remote: SimRemote, data: bytes) -> None:
        """A remote sends ``data`` by unicast to the coordinator; it reaches the host if acked."""
        tx = self.air.transmit(self.loop.clock(), remote.address, self.address, len(data))
        remote.stats.tx_packets += 1
        remote.stats.tx_bytes += len(data)
        remote.stats.retries += tx.retries
        if tx.delivered_s is None:
            remote.stats.tx_failures += 1
            return
        rssi = remote.rssi_dbm + self._rng.choice((-1, 0, 0, 1))
        if self.family == FrameFamily.IEEE_802_15_4:
            packet: ApiFrame = Rx64Packet(remote.address, rssi, data)
        else:
            packet = ReceivePacket(remote.address, data)
        self.params["DB"] = bytes((min(-rssi, 255),))
        self.loop.call_at(tx.delivered_s, lambda: self._send_host(packet))

    # ------------------------------------------------------------------ AT commands
    def _apply(self, params: dict[str, bytes], command: str, value: bytes) -> int:
        if command in ("WR", "AC", "FR", "RE"):
            return AT_OK
        if command not in params or command in ("SH", "SL", "HV", "VR", "DB"):
            return AT_BAD_COMMAND if command not in params else AT_ERROR
        if command == "AP" and value not in (b"\x00", b"\x01", b"\x02"):
            return AT_BAD_PARAMETER
        if command == "BD" and int.from_bytes(value, "big") not in BAUD_CODES:
            return AT_BAD_PARAMETER
        if command == "NI":
            params[command] = value
        else:  # numeric: keep the width of the stored value
            width = len(params[command])
            number = int.from_bytes(value, "big")
            if number >= 1 << (8 * width):
                return AT_BAD_PARAMETER
            params[command] = number.to_bytes(width, "big")
        return AT_OK

    def _at(self, frame: AtCommand | AtQueuedCommand) -> None:
        command = frame.command.upper()
        if command == "ND":
            self._node_discovery(frame.frame_id)
            return
        if frame.parameter or command in ("WR", "AC", "FR", "RE"):
            old_mode = self.api_mode
            status = self._apply(self.params, command, frame.parameter)
            answer = AtResponse(frame.frame_id, command, status)
            if command == "AP" and status == AT_OK:  # the answer still goes out in the old mode
                self._decoder.mode = self.api_mode
                self.loop.call_soon(lambda: self._send_mode(answer, old_mode))
                return
            self._send_host(answer)
            return
        value = self.params.get(command)
        if value is None:
            self._send_host(AtResponse(frame.frame_id, command, AT_BAD_COMMAND))
        else:
            self._send_host(AtResponse(frame.frame_id, command, AT_OK, value))

    def _send_mode(self, frame: ApiFrame, mode: ApiMode) -> None:
        wire = encode_frame(frame, mode)
        now = self.loop.clock()
        self._uart_out_free = max(now, self._uart_out_free) + uart_s(len(wire), self.baud)
        self.loop.call_at(self._uart_out_free, lambda: self._write_host(wire))

    def _node_discovery(self, frame_id: int) -> None:
        now = self.loop.clock()
        nt_s = self.params["NT"][0] / 10.0
        for remote in self.remotes.values():
            if self.air.loss.get(frozenset((self.address, remote.address)), 0.0) >= 1.0:
                continue
            value = (
                remote.params["MY"]
                + remote.params["SH"]
                + remote.params["SL"]
                + bytes((min(-remote.rssi_dbm, 255),))
                + remote.params["NI"]
                + b"\x00"
            )
            if self.family == FrameFamily.ZIGBEE:
                value = (
                    remote.params["MY"]
                    + remote.params["SH"]
                    + remote.params["SL"]
                    + remote.params["NI"]
                    + b"\x00\xff\xfe\x01\x00\xc1\x05\x10\x1e"
                )
            delay = self._rng.uniform(0.0, nt_s / 2)
            answer = AtResponse(frame_id, "ND", AT_OK, value)
            self.loop.call_at(now + delay, lambda a=answer: self._send_host(a))
        self.loop.call_at(now + nt_s, lambda: self._send_host(AtResponse(frame_id, "ND", AT_OK)))

    def _remote_at(self, frame: RemoteAtCommand) -> None:
        remote = self.remotes.get(frame.dest)
        now = self.loop.clock()
        payload = 2 + len(frame.parameter) + 4
        if remote is None:
            self.air.set_loss(self.address, frame.dest, 1.0)
        out = self.air.transmit(now, self.address, frame.dest, payload)
        if remote is None or not out.acked:
            reply = RemoteAtResponse(frame.frame_id, frame.dest, frame.command, AT_NO_RESPONSE)
            self.loop.call_at(out.end_s, lambda: self._send_host(reply))
            return
        command = frame.command.upper()
        if frame.parameter or command in ("WR", "AC"):
            status = self._apply(remote.params, command, frame.parameter)
            value = b""
        elif command in remote.params:
            status, value = AT_OK, remote.params[command]
        else:
            status, value = AT_BAD_COMMAND, b""
        back = self.air.transmit(out.end_s, remote.address, self.address, 5 + len(value))
        if not back.acked:
            reply = RemoteAtResponse(frame.frame_id, frame.dest, command, AT_NO_RESPONSE)
            self.loop.call_at(back.end_s, lambda: self._send_host(reply))
            return
        reply = RemoteAtResponse(frame.frame_id, remote.address, command, status, value)
        self.loop.call_at(back.end_s, lambda: self._send_host(reply))


def options_disable_ack(frame: Tx64Request | TransmitRequest) -> bool:
    """True when the transmit options ask for no MAC acknowledgement (bit 0x01)."""
    return bool(frame.options & 0x01)

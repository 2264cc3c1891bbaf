"""The XBee gateway: one coordinator radio in API mode serves every ``xbee://`` robot.

The gateway owns the coordinator's serial port. Agents reach it over the experiment's bus:

* an agent's board (:mod:`.transport`) puts each wire-protocol frame it sends on
  ``agent/<name>/link/tx``; the gateway sends it as a TX Request (0x00, or 0x10 on a ZigBee /
  DigiMesh radio) to that robot's 64-bit address;
* what a robot sends back arrives as RX Packets (0x80 / 0x90): their RF data go, unchanged, to
  ``agent/<name>/link/rx``. The robots' radios are in transparent mode, so the firmware and the
  agent's :class:`~hilswarm.agents.link.serial_board.SerialBoard` logic (seq numbers, retries,
  CRC) are exactly those of a USB link;
* with ``answer = "at_once"`` the TICKs still go to the robots, but each agent is answered at
  once from its robot's newest samples, marked STALE (:mod:`.unicast_answers`); with
  ``mode = "broadcast"`` a tick's TICKs go as one packed broadcast (:mod:`.packer`).

Bus callbacks only hand the bytes to the writer thread's queue. A reader thread decodes the
port (:class:`~.api_frames.ApiFrameDecoder`) and publishes. TX Status frames are counted per
robot (delivered, failed, retries): a robot out of range misses its ticks — its agent's board
times out and the agent goes safe — while the others go on.

Start-up (and after every reconnection, so that a re-plugged coordinator is configured again):
the gateway asks the radio for ``HV``/``VR`` (its frame family), and sets ``AP`` when the
radio answers in the other API mode. A lost port (coordinator unplugged) is re-opened every
:data:`REOPEN_S`; meanwhile the agents' boards time out and their agents go safe.

For every tick the manager releases (every ``stats_period_s`` without ticks) it publishes JSON
on ``gateway/stats`` (recorded as ``/gateway/stats``): ``k``, ``t``, ``values`` =
:data:`STATS_FIELDS` (estimated air time, air and host UART load both ways, TX failures,
retries), per robot the last RSSI [dBm] and the running totals; ``gateway/status`` carries
``connected`` / ``disconnected``.

Every sample put on an agent's ``link/rx`` carries the gateway's stage times of that answer as
its attachment (:mod:`.stages`: the gateway's own time and the radio's), for the agent's tick
ledger. Per robot the gateway keeps when its last request came in and when it went to the UART;
a few clock readings per frame, nothing else on the hot path.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import serial
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.timed_queue import get_within
from hilswarm.agents.xbee.air import AirParams, uart_s
from hilswarm.agents.xbee.api_frames import (
    BROADCAST_64,
    ApiFrame,
    ApiFrameDecoder,
    ApiMode,
    AtCommand,
    AtResponse,
    FrameFamily,
    ReceivePacket,
    Rx64Packet,
    TransmitRequest,
    TransmitStatus,
    Tx64Request,
    TxStatus,
    encode_frame,
)
from hilswarm.agents.xbee.config import GatewayConfig, format_address
from hilswarm.agents.xbee.packer import Action, Broadcast, BroadcastPacker, ToAgent, Unicast
from hilswarm.agents.xbee.stages import encode_stages
from hilswarm.agents.xbee.unicast_answers import UnicastAnswers

_log = logging.getLogger(__name__)

#: Pause between two attempts to re-open a lost coordinator port [s].
REOPEN_S = 0.2
#: The ``values`` of a ``gateway/stats`` message.
STATS_FIELDS = (
    "air_s",  # estimated air time of the period's packets [s]
    "air_load",  # the same as a fraction of the period
    "uart_out_load",  # host -> coordinator UART, fraction of its capacity
    "uart_in_load",  # coordinator -> host UART, fraction of its capacity
    "tx_failures",  # TX Status failures in the period
    "retries",  # MAC retries reported in the period (ZigBee/DigiMesh Transmit Status)
)
#: How long the start-up AT exchange waits for each answer [s].
AT_TIMEOUT_S = 1.0
_POLL_S = 0.02


class GatewayError(HilswarmError, ConnectionError):
    """The coordinator cannot be opened or does not answer as an XBee in API mode."""


@dataclass
class RobotStats:
    """Counters of one robot seen by the gateway."""

    tx_frames: int = 0
    tx_bytes: int = 0
    rx_frames: int = 0
    rx_bytes: int = 0
    delivered: int = 0
    tx_failures: int = 0
    retries: int = 0
    rssi_dbm: int | None = None
    sections: int = 0  # broadcast mode: BCAST sections sent to it
    stale_replies: int = 0  # broadcast mode: TICK_REPLYs the gateway answered itself
    fresh_replies: int = 0  # broadcast mode: the robot's own replies received
    asked_again: int = 0  # broadcast mode: asked out of turn, its last reply lost or late


@dataclass
class GatewayStats:
    """Counters of the gateway (host UART bytes both ways, frames, per robot)."""

    uart_out_bytes: int = 0
    uart_in_bytes: int = 0
    air_s: float = 0.0  # estimated air time of every packet sent and received [s]
    reconnections: int = 0
    dropped_frames: int = 0
    broadcast_frames: int = 0  # BCAST frames sent (broadcast mode)
    broadcast_bytes: int = 0
    robots: dict[str, RobotStats] = field(default_factory=dict)


class Gateway:
    """The gateway process's work (see the module docstring).

    Args:
        config: ``[gateway]`` settings; ``config.port`` is opened with pyserial (a simulated
            coordinator's pty path when the caller started one).
        keys: the experiment's bus keys.
        robots: agent name -> 64-bit address of its robot's radio.
        session: the bus session (the gateway's own principal).
        port_url: what to open instead of ``config.port`` (the simulated coordinator's path).
        stats_period_s: period of ``gateway/stats`` [s].
        clock: monotonic clock [s].
        reply_every: broadcast mode: agent name -> m (its robot answers every m-th tick).
        rate_hz: broadcast mode: the experiment's tick rate [Hz] (how long a round gathers).
    """

    def __init__(
        self,
        config: GatewayConfig,
        keys: bus.BusKeys,
        robots: Mapping[str, int],
        session: zenoh.Session,
        *,
        port_url: str | None = None,
        stats_period_s: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
        reply_every: Mapping[str, int] | None = None,
        rate_hz: float = 20.0,
    ) -> None:
        self.config = config
        self.keys = keys
        self.robots = dict(robots)
        self.by_address = {address: name for name, address in self.robots.items()}
        self.session = session
        self.port_url = port_url or config.port
        self.stats_period_s = stats_period_s
        self.clock = clock
        self.family = FrameFamily.IEEE_802_15_4
        self.stats = GatewayStats(robots={name: RobotStats() for name in self.robots})
        self.connected = threading.Event()
        self._mode = ApiMode(config.api_mode)
        self._decoder = ApiFrameDecoder(self._mode)
        self._port: serial.SerialBase | None = None
        self._port_lock = threading.Lock()
        self._outbox: queue.SimpleQueue[tuple[str, bytes, float] | tuple[()] | None] = (
            queue.SimpleQueue()
        )
        # Stage times (module docstring), per robot: when its agent's last request reached the
        # gateway, and (when it went to the UART, the gateway's time until then) [s, clock].
        self._arrived: dict[str, float] = {}
        self._sent: dict[str, tuple[float, float]] = {}
        self._frame_id = 0
        self._pending: dict[int, str] = {}  # frame id -> robot name
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._entities: list[Any] = []
        self._rx_pubs: dict[str, Any] = {}
        self._air = AirParams()
        self._max_payload = self._air.max_payload
        self._ticks: queue.SimpleQueue[tuple[int, float]] = queue.SimpleQueue()
        #: What reads the agents' frames: the TICK packer (``mode = "broadcast"``), the
        #: answers at once by unicast (``answer = "at_once"``), else ``None`` (the bytes go
        #: through unread).
        self.packer: BroadcastPacker | UnicastAnswers | None = None
        if config.mode == "broadcast":
            self.packer = BroadcastPacker(
                sorted(self.robots),
                reply_every=reply_every,
                period_s=1.0 / rate_hz,
                answer=config.answer,
            )
        elif config.answer == "at_once":
            self.packer = UnicastAnswers(sorted(self.robots))
        self._packer_lock = threading.Lock()
        self._last_tick = (0, 0.0)

    # ------------------------------------------------------------------ life cycle
    def start(self) -> Gateway:
        """Open the coordinator (raises :class:`GatewayError`), declare the bus entities and
        start the threads."""
        self._open_port()
        for name in self.robots:
            self._rx_pubs[name] = self.session.declare_publisher(
                self.keys.link_rx(name), **bus.TICK_PATH_QOS
            )
            self._entities.append(
                self.session.declare_subscriber(
                    self.keys.link_tx(name), lambda s, n=name: self._on_tx(n, s)
                )
            )
        self._entities.append(self.session.declare_subscriber(self.keys.tick, self._on_tick))
        self._status_pub = self.session.declare_publisher(self.keys.gateway("status"))
        self._stats_pub = self.session.declare_publisher(self.keys.gateway("stats"))
        for target, name in (
            (self._write_loop, "xbee-gateway-tx"),
            (self._read_loop, "xbee-gateway-rx"),
            (self._stats_loop, "xbee-gateway-stats"),
        ):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        self._publish_status("connected")
        return self

    def stop(self) -> None:
        """Stop the threads, undeclare and close the port. Idempotent."""
        self._stop.set()
        self._outbox.put(None)
        for thread in self._threads:
            thread.join(timeout=3.0)
        self._threads.clear()
        for entity in self._entities:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self._entities.clear()
        self._close_port()

    def __enter__(self) -> Gateway:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ port
    def _open_port(self) -> None:
        try:
            port = serial.serial_for_url(
                self.port_url, baudrate=self.config.baud, timeout=_POLL_S, write_timeout=1.0
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise GatewayError(f"cannot open the coordinator at {self.port_url!r}: {exc}") from exc
        with self._port_lock:
            self._port = port
        self._decoder.reset()
        try:
            self._configure_radio()
        except GatewayError:
            self._close_port()
            raise
        self.connected.set()

    def _close_port(self) -> None:
        self.connected.clear()
        with self._port_lock:
            port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()

    def _configure_radio(self) -> None:
        """Ask the radio for its versions (frame family) and make sure ``AP`` is ours."""
        hv = self._at_query("HV")
        if hv is None:  # perhaps the radio is in the other API mode: switch it to ours
            self._set_api_mode()
            hv = self._at_query("HV")
        ap = self._at_query("AP")  # frames without escapable bytes read alike in modes 1 and 2
        if ap is not None and ap.value[:1] != bytes((int(self._mode),)):
            _log.info("coordinator is in API mode %s; setting AP=%d", ap.value.hex(), self._mode)
            self._write_frame(AtCommand(0xF1, "AP", bytes((int(self._mode),))))
            self._write_frame(AtCommand(0xF2, "WR"))
            self._at_query("AP")
        vr = self._at_query("VR")
        if hv is None or vr is None:
            raise GatewayError(
                f"the coordinator at {self.port_url!r} does not answer AT commands in API mode "
                f"{int(self._mode)} at {self.config.baud} baud; put it in API mode with "
                "`hilswarm xbee setup` (or check port, baud and api_mode in [gateway])"
            )
        # XBee 802.15.4 firmware versions start with 1 on XB24-A hardware (0x17/0x18);
        # ZigBee (2x) and DigiMesh (8x) use the 0x10/0x90/0x8B frames.
        self.family = (
            FrameFamily.IEEE_802_15_4
            if hv.value[:1] in (b"\x17", b"\x18") and vr.value[:1] < b"\x80"
            else FrameFamily.ZIGBEE
        )
        _log.info(
            "coordinator %s: HV %s VR %s, %s frames, API mode %d",
            self.port_url,
            hv.value.hex(),
            vr.value.hex(),
            self.family.value,
            self._mode,
        )

    def _set_api_mode(self) -> None:
        """Try the other API mode; if the radio answers there, set ``AP`` to ours."""
        ours = self._mode
        other = ApiMode.ESCAPED if ours == ApiMode.API else ApiMode.API
        self._mode = self._decoder.mode = other
        try:
            if self._at_query("HV") is not None:
                _log.info("coordinator answered in API mode %d; setting AP=%d", other, ours)
                self._write_frame(AtCommand(0xF1, "AP", bytes((int(ours),))))
                self._write_frame(AtCommand(0xF2, "WR"))
                self._at_query("AP")  # its answer (in the old mode) drains here
        finally:
            self._mode = self._decoder.mode = ours

    def _at_query(self, command: str) -> AtResponse | None:
        """Send a local AT query and wait for its answer (start-up only: the reader is not
        running yet, so read here)."""
        frame_id = 0xF0
        self._write_frame(AtCommand(frame_id, command))
        deadline = self.clock() + AT_TIMEOUT_S
        while self.clock() < deadline:
            for frame in self._read_frames():
                if isinstance(frame, AtResponse) and frame.command == command:
                    return frame if frame.status == 0 else None
        return None

    def _read_frames(self) -> list[ApiFrame]:
        with self._port_lock:
            port = self._port
        if port is None:
            raise serial.SerialException("port closed")
        data = port.read(1)
        if data and port.in_waiting:
            data += port.read(port.in_waiting)
        if not data:
            return self._decoder.idle() if self._decoder.pending else []
        self.stats.uart_in_bytes += len(data)
        return self._decoder.feed(data)

    def _write_frame(self, frame: ApiFrame) -> None:
        wire = encode_frame(frame, self._mode)
        with self._port_lock:
            port = self._port
            if port is None:
                raise serial.SerialException("port closed")
            port.write(wire)
        self.stats.uart_out_bytes += len(wire)

    # ------------------------------------------------------------------ bus -> radio
    def _on_tx(self, name: str, sample: zenoh.Sample) -> None:
        """Bus callback: hand the bytes, with their arrival time, to the writer thread (never
        blocks)."""
        self._outbox.put((name, sample.payload.to_bytes(), self.clock()))

    def _next_frame_id(self) -> int:
        self._frame_id = self._frame_id % 255 + 1  # 1..255 (0 would ask for no status)
        return self._frame_id

    def _write_loop(self) -> None:
        while not self._stop.is_set():
            packer = self.packer
            due = None if packer is None else packer.due(self.clock())
            try:
                item = (
                    self._outbox.get()
                    if due is None
                    else get_within(self._outbox, due - self.clock())
                )
            except queue.Empty:
                item = ()  # a round's gathering time is over
            if item is None:
                return
            if item:
                self._arrived[item[0]] = item[2]
            if packer is not None:
                with self._packer_lock:
                    actions = (
                        packer.from_agent(item[0], item[1], self.clock())
                        if item
                        else packer.poll(self.clock())
                    )
                self._act(actions)
                continue
            if not self.connected.is_set():
                continue  # coordinator away: the frame is lost, the agent's board retries
            self._send_unicast(item[0], item[1])

    def _act(self, actions: list[Action], received_s: float | None = None) -> None:
        """Carry out the packer's actions (writer thread; reader thread with ``received_s``,
        when the robot's frame that caused them was decoded [s, clock])."""
        for action in actions:
            if isinstance(action, ToAgent) and action.stale and not self.connected.is_set():
                continue  # coordinator away: no answers from old samples; the boards time out
            if isinstance(action, ToAgent):
                robot = self.stats.robots[action.name]
                robot.stale_replies += action.stale
                self._publish_rx(action.name, action.data, None if action.stale else received_s)
            elif not self.connected.is_set():
                continue  # coordinator away: lost; the agents' boards retry
            elif isinstance(action, Unicast):
                self._send_unicast(action.name, action.data)
            else:
                self._send_broadcast(action)

    def _tx_frame(self, frame_id: int, address: int, data: bytes) -> ApiFrame:
        """The transmit request of the radio's frame family (frame id 0: no TX Status)."""
        if self.family == FrameFamily.IEEE_802_15_4:
            return Tx64Request(frame_id, address, data)
        return TransmitRequest(frame_id, address, data)

    def _note_sent(self, name: str, now: float) -> None:
        """Robot ``name``'s request goes to the UART now: the gateway's time until then."""
        self._sent[name] = (now, now - self._arrived.get(name, now))

    def _publish_rx(self, name: str, data: bytes, received_s: float | None) -> None:
        """Put ``data`` on agent ``name``'s ``link/rx`` with the answer's stage times
        (:mod:`.stages`): the robot's answer decoded at ``received_s``, or (``None``) an answer
        the gateway gives itself."""
        now = self.clock()
        attachment = None
        if received_s is None:
            arrived = self._arrived.get(name)
            if arrived is not None:
                attachment = encode_stages(now - arrived, 0.0)
        else:
            sent = self._sent.get(name)
            if sent is not None:
                attachment = encode_stages(sent[1] + now - received_s, received_s - sent[0])
        self._rx_pubs[name].put(data, attachment=attachment)

    def _send_broadcast(self, action: Broadcast) -> None:
        """One BCAST frame to every robot: no ACK, no MAC retry, no TX Status (frame id 0)."""
        frame = self._tx_frame(0, BROADCAST_64, action.data)
        now = self.clock()
        for name in action.names:
            self._note_sent(name, now)
        try:
            self._write_frame(frame)
        except (serial.SerialException, OSError) as exc:
            _log.debug("gateway: write failed (%s); the reader reconnects", exc)
            return
        self.stats.broadcast_frames += 1
        self.stats.broadcast_bytes += len(action.data)
        self.stats.air_s += self._air.mean_broadcast_s(len(action.data))
        for name in action.names:
            self.stats.robots[name].sections += 1

    def _send_unicast(self, name: str, data: bytes) -> None:
        """``data`` to robot ``name`` as TX Requests of at most the RF payload each."""
        address = self.robots[name]
        robot = self.stats.robots[name]
        self._note_sent(name, self.clock())
        for start in range(0, len(data), self._max_payload):
            chunk = data[start : start + self._max_payload]
            frame_id = self._next_frame_id()
            self._pending[frame_id] = name
            frame = self._tx_frame(frame_id, address, chunk)
            try:
                self._write_frame(frame)
            except (serial.SerialException, OSError) as exc:
                _log.debug("gateway: write failed (%s); the reader reconnects", exc)
                break
            robot.tx_frames += 1
            robot.tx_bytes += len(chunk)
            self.stats.air_s += self._air.mean_unicast_s(len(chunk))

    # ------------------------------------------------------------------ radio -> bus
    def _read_loop(self) -> None:
        while not self._stop.is_set():
            try:
                frames = self._read_frames()
            except (serial.SerialException, OSError) as exc:
                if self._stop.is_set():
                    return
                self._lost(str(exc))
                continue
            for frame in frames:
                self._dispatch(frame)

    def _dispatch(self, frame: ApiFrame) -> None:
        if isinstance(frame, Rx64Packet | ReceivePacket):
            received_s = self.clock()
            name = self.by_address.get(frame.source)
            if name is None:
                self.stats.dropped_frames += 1
                _log.debug(
                    "gateway: data from unknown radio %s dropped", format_address(frame.source)
                )
                return
            robot = self.stats.robots[name]
            robot.rx_frames += 1
            robot.rx_bytes += len(frame.data)
            self.stats.air_s += self._air.mean_unicast_s(len(frame.data))
            if isinstance(frame, Rx64Packet):
                robot.rssi_dbm = frame.rssi_dbm
            if self.packer is not None:
                with self._packer_lock:
                    actions = self.packer.from_robot(name, frame.data)
                self._act(actions, received_s)
                return
            self._publish_rx(name, frame.data, received_s)
        elif isinstance(frame, TxStatus | TransmitStatus):
            name = self._pending.pop(frame.frame_id, None)
            if name is None:
                return
            robot = self.stats.robots[name]
            if frame.status == 0:
                robot.delivered += 1
            else:
                robot.tx_failures += 1
            if isinstance(frame, TransmitStatus):
                robot.retries += frame.retries
        elif isinstance(frame, AtResponse):  # a late answer to a start-up query: nothing waits
            _log.debug("gateway: AT %s answer after start-up ignored", frame.command)

    def _lost(self, cause: str) -> None:
        """The coordinator went away: reopen until it is back (or the gateway stops)."""
        _log.warning("gateway: coordinator %s lost (%s); reconnecting", self.port_url, cause)
        self._close_port()
        self._pending.clear()
        self._publish_status("disconnected", cause)
        while not self._stop.wait(REOPEN_S):
            try:
                self._open_port()
            except GatewayError as exc:
                _log.debug("gateway: reopen failed: %s", exc)
                continue
            self.stats.reconnections += 1
            self._publish_status("connected", "reconnected; radio configuration re-applied")
            return

    # ------------------------------------------------------------------ figures
    def _on_tick(self, sample: zenoh.Sample) -> None:
        """Bus callback: note the released tick (the stats thread publishes its figures)."""
        try:
            tick = bus.decode_tick(sample.payload.to_bytes())
        except bus.BusMessageError:
            return
        self._ticks.put((tick.k, tick.t))

    def _publish_status(self, state: str, detail: str = "") -> None:
        k, t = self._last_tick
        payload = {
            "k": k,
            "t": t,
            "values": [],
            "state": state,
            "detail": detail,
            "port": self.port_url,
        }
        with contextlib.suppress(zenoh.ZError):
            self._status_pub.put(json.dumps(payload))

    def snapshot(self) -> dict[str, Any]:
        """The counters as a JSON-ready dict (what ``gateway/stats`` carries)."""
        if self.packer is not None:
            with self._packer_lock:
                replies = self.packer.stats()
            for name, counts in replies.items():
                robot = self.stats.robots.get(name)
                if robot is not None:
                    robot.fresh_replies = counts["fresh_replies"]
                    robot.asked_again = counts["asked_again"]
        data = asdict(self.stats)
        data["connected"] = self.connected.is_set()
        data["family"] = self.family.value
        return data

    def _stats_loop(self) -> None:
        """Publish ``gateway/stats`` once per tick released (or every ``stats_period_s``
        without ticks): the figures since the previous message."""
        last = self.snapshot()
        last_t = self.clock()
        while not self._stop.is_set():
            try:
                self._last_tick = get_within(self._ticks, self.stats_period_s)
                while True:  # a burst of releases (lockstep window): report once
                    self._last_tick = self._ticks.get_nowait()
            except queue.Empty:
                pass
            now_t = self.clock()
            snap = self.snapshot()
            period = max(now_t - last_t, 1e-9)
            capacity = period / uart_s(1, self.config.baud)  # bytes the UART carries per period
            air = snap["air_s"] - last["air_s"]
            out_load = (snap["uart_out_bytes"] - last["uart_out_bytes"]) / capacity
            in_load = (snap["uart_in_bytes"] - last["uart_in_bytes"]) / capacity
            failures = sum(r["tx_failures"] for r in snap["robots"].values()) - sum(
                r["tx_failures"] for r in last["robots"].values()
            )
            retries = sum(r["retries"] for r in snap["robots"].values()) - sum(
                r["retries"] for r in last["robots"].values()
            )
            k, t = self._last_tick
            message = {
                "k": k,
                "t": t,
                "fields": list(STATS_FIELDS),
                "values": [air, air / period, out_load, in_load, failures, retries],
                "period_s": period,
                "rssi_dbm": {n: r["rssi_dbm"] for n, r in snap["robots"].items()},
                "totals": snap,
            }
            with contextlib.suppress(zenoh.ZError):
                self._stats_pub.put(json.dumps(message))
            last, last_t = snap, now_t

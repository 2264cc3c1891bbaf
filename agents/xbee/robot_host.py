"""The simulated robot behind a simulated radio, run by its agent's process.

With ``link = "xbee://<address>?sim=sim://duemilanove"`` (or ``?sim=simavr://duemilanove``)
and ``[gateway] port = "sim"``, the robot — the board and the vehicle's simulated hardware —
lives in the agent's process, as for a ``sim://`` link, so that the simulated motion capture
follows the same plant. Its UART is carried by the bus keys ``agent/<name>/link/robot/in``
(bytes the robot's radio puts out) and ``.../out`` (bytes the robot sends); the simulated air
(:class:`~.sim_robot.BusUart` in the gateway's process) paces them at the robot UART's rate.

* ``sim://``: a :class:`~hilswarm.agents.link.sim_board.SimBoard` behind a
  :class:`~hilswarm.agents.link.wire_server.WireServer` (the protocol-checking Python firmware).
* ``simavr://``: the real firmware in simavr (paced to the wall clock). With a plant, the plant
  advances by ``dt`` just before each TICK frame reaches the firmware (or each BCAST holding
  this robot's section, protocol 2): the outputs the firmware drove since the previous one are
  held over the step, the plant's voltages are put on the simulated pins, then the frame applies
  its writes and samples them.

Bus callbacks only queue the bytes; one worker thread feeds the robot.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from typing import Any

import zenoh
from hilswarm.agents import bus
from hilswarm.agents.errors import WireFormatError
from hilswarm.agents.link.board import PinMode
from hilswarm.agents.link.codec import (
    ConfigMsg,
    FrameDecoder,
    MsgType,
    parse_bcast_body,
    parse_payload,
)
from hilswarm.agents.link.simavr import SimavrBoard, outputs_from_state
from hilswarm.agents.link.url import board_for_url
from hilswarm.agents.link.wire_server import WireServer
from hilswarm.agents.xbee.sim_robot import SerialUart
from hilswarm.agents.xbee.transport import ChannelReader

_log = logging.getLogger(__name__)


class RobotHost:
    """Run the simulated robot ``sim_url`` behind agent ``agent``'s simulated radio.

    Args:
        sim_url: ``sim://<profile>`` or ``simavr://<profile>``.
        session: the agent's bus session.
        keys: the experiment's keys.
        agent: the agent's name.
        plant: the vehicle's simulated hardware (a ``PinPlant``) or ``None``.
        dt: plant step per tick [s].
    """

    def __init__(
        self,
        sim_url: str,
        session: zenoh.Session,
        keys: bus.BusKeys,
        agent: str,
        *,
        plant: Any | None = None,
        dt: float | None = None,
    ) -> None:
        self.sim_url = sim_url
        self.session = session
        self.keys = keys
        self.agent = agent
        self.plant = plant
        self.dt = dt
        self._inbox: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._entities: list[Any] = []
        self._server: WireServer | None = None
        self._simavr: SimavrBoard | None = None
        self._uart: SerialUart | None = None
        self._decoder = FrameDecoder()
        self._modes: dict[int, PinMode] = {}
        self._bcast_id = 0
        self._reader: ChannelReader | None = None

    def start(self) -> None:
        """Power the robot on and connect its UART to the bus."""
        out = self.session.declare_publisher(
            self.keys.link_robot(self.agent, "out"), **bus.TICK_PATH_QOS
        )
        self._entities.append(out)
        if self.sim_url.startswith("simavr://"):
            # the SimavrBoard only for its harness and pin injection; the radio talks to the pty
            simavr = board_for_url(self.sim_url, plant=None, paced=True)
            if not isinstance(simavr, SimavrBoard):
                raise TypeError(f"{self.sim_url!r} did not give a simavr board")
            self._simavr = simavr
            pty = simavr.harness.start()
            self._uart = SerialUart(pty)
            self._uart.start(out.put)
        else:
            board = board_for_url(self.sim_url, plant=self.plant, dt=self.dt or 0.05)
            self._server = WireServer(board)
        self._thread = threading.Thread(
            target=self._work, args=(out,), name=f"robot-{self.agent}", daemon=True
        )
        self._thread.start()
        self._reader = ChannelReader(
            self.session, self.keys.link_robot(self.agent, "in"), self._inbox.put
        )

    def _work(self, out: zenoh.Publisher) -> None:
        while True:
            data = self._inbox.get()
            if data is None:
                return
            try:
                if self._server is not None:
                    reply = self._server.handle_bytes(data)
                    if reply:
                        out.put(reply)
                elif self._uart is not None:
                    self._before_firmware(data)
                    self._uart.write(data)
            except Exception:  # the simulated robot must not kill the agent
                _log.exception("simulated robot of %s failed", self.agent)

    def _before_firmware(self, data: bytes) -> None:
        """simavr with a plant: note CONFIG's modes, step the plant before each TICK."""
        if self.plant is None or self._simavr is None:
            return
        for payload in self._decoder.feed(data):
            kind = payload[0]
            if kind == MsgType.CONFIG:
                with contextlib.suppress(Exception):
                    msg = parse_payload(payload)
                    if isinstance(msg, ConfigMsg):
                        self._modes = {e.pin: PinMode(e.mode) for e in msg.entries}
                        self._simavr._modes = dict(self._modes)
                        self._bcast_id = msg.bcast_id
            elif (kind == MsgType.TICK or self._ours(payload)) and self._modes:
                state = self._simavr.harness.state()
                volts = self.plant.advance(outputs_from_state(state, self._modes), self.dt or 0.05)
                for pin, value in volts.items():
                    self._simavr.set_input_voltage(int(pin), float(value))

    def _ours(self, payload: bytes) -> bool:
        """True for a BCAST that holds a section of this robot."""
        if payload[0] != MsgType.BCAST or self._bcast_id == 0:
            return False
        try:
            sections = parse_bcast_body(payload[1], payload[2:]).sections
        except WireFormatError:
            return False
        return any(s.board_id == self._bcast_id for s in sections)

    def stop(self) -> None:
        """Power the robot off. Idempotent."""
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        if self._uart is not None:
            self._uart.stop()
            self._uart = None
        self._inbox.put(None)
        if self._thread is not None:
            self._thread.join(timeout=3.0)
            self._thread = None
        for entity in self._entities:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self._entities.clear()
        if self._simavr is not None:
            self._simavr.harness.stop()
            self._simavr = None

"""The gateway's unicast mode answering at once (``[gateway] answer = "at_once"``). Pure.

By unicast each agent's TICK goes to its robot as a TX Request, and with ``answer = "wait"``
(the default) the robot's own TICK_REPLY comes back to the agent: the agent waits for the
whole radio round trip (its TICK through the host UART, the air and the robot's UART, the
reply back), ~15 ms for one robot and ~6.75 ms more for each other robot on the coordinator
in the same tick. With ``at_once`` the gateway still sends every TICK to its robot, but
answers the agent at once, as the broadcast packer does
(:class:`~hilswarm.agents.xbee.packer.BroadcastPacker`):

* **Stale answers.** The answer carries the newest samples the robot sent (its replies to
  earlier TICKs) and its board time, with status :attr:`~.board.BoardStatus.STALE` (never
  passed off as fresh); one-shot status events (WATCHDOG_TRIPPED, RX_ERRORS) of replies no
  agent saw are carried into the next answer, so each is reported once. The robot's own reply
  to a TICK answered so is kept for the next answers, not forwarded.
* **When the agent waits after all.** A TICK goes through as with ``wait`` (the robot's own
  reply is its answer) when the gateway holds no samples of the pins it reads (the first TICK
  after the robot's HELLO or CONFIG), when it repeats the previous TICK's seq (the agent's
  board retrying: the board answers it itself, with an ERROR if it rebooted), and when the
  robot left its last :data:`PATIENCE_TICKS` TICKs without a reply (out of range, switched
  off: its agent's board then times out, retries and goes safe as over ``wait``). An ERROR
  from the robot (NOT_CONFIGURED after a reboot, or a TICK it refused) drops its samples, so
  the agent's next TICK gets the robot's own answer: the ERROR, and the board recovers (a
  reboot: configured again) as over ``wait``.
* Everything else (HELLO, CONFIG, ESTOP, SET_ID and their replies) goes through unchanged.

Any firmware works (protocol 1 too): the robots see the same TICKs as with ``wait``.

The answerer is fed and drained by the gateway's threads under one lock; it does no I/O and
reads no clock.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from hilswarm.agents.errors import WireFormatError
from hilswarm.agents.link.codec import (
    FrameDecoder,
    MsgType,
    TickReplyMsg,
    frame_payload,
    parse_payload,
    pins_of_mask,
)
from hilswarm.agents.xbee.packer import EVENTS, Action, ToAgent, Unicast, stale_tick_reply

#: A robot whose last this many TICKs brought no reply of its own is answered no more at once.
PATIENCE_TICKS = 4
#: TICKs in flight remembered per robot (older ones' replies go to the agent unchanged).
_IN_FLIGHT = 8
#: Where a TICK's read mask sits in its payload (type, seq, dout u24, rmask u24).
_RMASK = slice(5, 8)


@dataclass
class _Robot:
    """What the answerer knows of one robot."""

    name: str
    samples: dict[int, int] = field(default_factory=dict)  # newest sample by pin
    status: int = 0
    time_us: int = 0
    events: int = 0  # one-shot events of replies no agent has seen yet
    unanswered: int = 0  # TICKs sent since the robot's last reply of its own
    last_seq: int | None = None
    in_flight: dict[int, tuple[tuple[int, ...], bool]] = field(default_factory=dict)
    tx: FrameDecoder = field(default_factory=FrameDecoder)
    rx: FrameDecoder = field(default_factory=FrameDecoder)
    fresh: int = 0  # the robot's own TICK_REPLYs
    stale: int = 0  # answers the gateway gave itself
    waited: int = 0  # TICKs after the first whose agent waited for the robot (no answer at once)


def _read_pins(payload: bytes) -> tuple[int, ...] | None:
    """The pins a TICK payload samples, ascending (``None``: too short to be a TICK)."""
    if len(payload) < _RMASK.stop:
        return None
    return tuple(pins_of_mask(int.from_bytes(payload[_RMASK], "little")))


class UnicastAnswers:
    """Answer every TICK at once from the robot's newest samples (module docstring).

    Args:
        robots: agent names of the robots.
    """

    def __init__(self, robots: Sequence[str]) -> None:
        self.robots = {name: _Robot(name) for name in robots}

    # ------------------------------------------------------------------ agent -> robot
    def from_agent(self, name: str, data: bytes, now_s: float) -> list[Action]:
        """Bytes an agent's board sent: the actions they cause (``now_s`` unused: the same
        interface as the broadcast packer)."""
        robot = self.robots[name]
        actions: list[Action] = []
        for payload in robot.tx.feed(data):
            kind = payload[0]
            if kind in (MsgType.HELLO, MsgType.CONFIG):
                robot.samples.clear()  # a new board or new pins: fresh samples first
            if kind == MsgType.TICK and (reads := _read_pins(payload)) is not None:
                answer = self._tick(robot, payload[1], reads)
                if answer is not None:  # first: the agent need not wait for the write
                    actions.append(answer)
            actions.append(Unicast(name, frame_payload(payload)))
        return actions

    def _tick(self, robot: _Robot, seq: int, reads: tuple[int, ...]) -> ToAgent | None:
        """A TICK on its way to the robot: its stale answer, or ``None`` (the agent waits)."""
        retry = seq == robot.last_seq
        robot.last_seq = seq
        at_once = (
            not retry
            and robot.fresh > 0
            and robot.unanswered < PATIENCE_TICKS
            and all(pin in robot.samples for pin in reads)
        )
        if not at_once and robot.fresh > 0:
            robot.waited += 1
        robot.unanswered += 1
        robot.in_flight[seq] = (reads, at_once)
        while len(robot.in_flight) > _IN_FLIGHT:
            del robot.in_flight[next(iter(robot.in_flight))]
        if not at_once:
            return None
        robot.stale += 1
        values = tuple(robot.samples[pin] for pin in reads)
        data = stale_tick_reply(seq, robot.status, robot.events, robot.time_us, values)
        robot.events = 0
        return ToAgent(robot.name, data, stale=True)

    def due(self, now_s: float) -> float | None:
        """Nothing waits for a deadline here (the broadcast packer's rounds do)."""
        return None

    def poll(self, now_s: float) -> list[Action]:
        """Nothing to send on a deadline."""
        return []

    # ------------------------------------------------------------------ robot -> agent
    def from_robot(self, name: str, data: bytes) -> list[Action]:
        """Bytes a robot sent: what goes to its agent."""
        robot = self.robots[name]
        actions: list[Action] = []
        for payload in robot.rx.feed(data):
            kind = payload[0]
            if kind == MsgType.ERROR and self._error(robot, payload[1]):
                continue
            if kind == MsgType.TICK_REPLY and self._fresh(robot, payload):
                continue
            actions.append(ToAgent(name, frame_payload(payload)))
        return actions

    def _fresh(self, robot: _Robot, payload: bytes) -> bool:
        """The robot's own TICK_REPLY: keep its samples; True when its agent was answered at
        once (the reply goes no further). A malformed one goes on to the agent's board."""
        try:
            reply = parse_payload(payload)
        except WireFormatError:
            return False
        if not isinstance(reply, TickReplyMsg):
            return False
        flight = robot.in_flight.pop(reply.seq, None)
        robot.fresh += 1
        robot.unanswered = 0
        robot.status, robot.time_us = reply.status, reply.board_time_us
        if flight is not None and len(flight[0]) == len(reply.samples):
            robot.samples.update(zip(flight[0], reply.samples, strict=True))
        if flight is None or not flight[1]:
            return False
        robot.events |= reply.status & EVENTS  # no agent sees this reply
        return True

    def _error(self, robot: _Robot, seq: int) -> bool:
        """An ERROR from the robot (rebooted: NOT_CONFIGURED; or a TICK it refused): its
        samples go, so that the agent's next TICK gets the robot's own answer. True when it
        answers a TICK whose agent was answered at once (it goes no further: that agent would
        discard a reply to an old seq)."""
        robot.samples.clear()
        robot.unanswered = 0
        flight = robot.in_flight.pop(seq, None)
        return flight is not None and flight[1]

    def stats(self) -> dict[str, dict[str, int]]:
        """Per robot so far: its own replies received (``fresh_replies``), and the TICKs after
        its first whose agent waited for the robot's own reply (``asked_again``: no samples
        of a pin, a retry, or the robot silent for :data:`PATIENCE_TICKS` TICKs)."""
        return {
            n: {"fresh_replies": r.fresh, "asked_again": r.waited} for n, r in self.robots.items()
        }

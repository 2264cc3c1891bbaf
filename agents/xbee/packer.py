"""The gateway's broadcast mode: the agents' TICKs of one tick packed into one BCAST. Pure.

Agents are unchanged: each one's board sends a TICK per tick and waits for its TICK_REPLY, as
over USB. In ``[gateway] mode = "broadcast"`` the gateway reads those frames
(:meth:`BroadcastPacker.from_agent`) and, for every robot that speaks protocol 2 and whose
configuration it saw accepted, turns each TICK into the robot's compact section
(:class:`~hilswarm.agents.link.broadcast.SectionLayout`):

* **Gathering.** A round collects the TICKs of one tick; it is sent when every robot *expected*
  (one that sent a TICK within the last two tick periods) is in, or ``gather_s`` after its first
  TICK. One round is one BCAST frame, or as few as the 96-byte payload limit needs. A TICK the
  packer cannot pack (a write missing, a pin sampled that is no input) goes by unicast, as do
  HELLO, CONFIG (with the robot's broadcast id added: its index + 1 in name order), ESTOP and
  SET_ID.
* **Decimated replies.** Robot i answers on round r when ``(r + i) % reply_every == 0``
  (round-robin, so the replies of a tick are spread), and always when it has no samples yet,
  when it missed its last reply. Its BCAST_REPLY
  becomes the agent's TICK_REPLY (the agent's seq, the agent's sampled pins).
* **Stale replies.** On the other rounds the packer answers the agent itself at once: the
  robot's last samples and board time, status :attr:`~.board.BoardStatus.STALE` (never passed
  off as fresh; the one-shot events are not repeated). It does so only while the robot's last
  requested reply arrived: a robot that misses one is asked again, and its agent gets no answer
  until it does, so its board times out, retries and goes safe as over unicast. A retry (an
  agent repeating a TICK's seq) goes by unicast: the board answers it itself, with an ERROR if
  it rebooted (NOT_CONFIGURED), so the agent's board recovers as over USB. A robot the
  broadcasts leave out (its agent stopped sending) trips its watchdog by itself.

* **Answering at once** (``answer = "at_once"``). Waiting for a robot's own reply costs its
  agent the radio round trip (the BCAST through the host UART, the air and the robot's UART,
  the reply back: ~13 ms for one robot, ~39 ms for sixteen at 115200 baud), longer than a
  50 Hz tick. With ``at_once`` the packer answers every TICK at once (once the robot has
  answered for the first time) with the newest samples it holds, always marked STALE: they
  were taken for an earlier tick (``board_time_us`` tells when); the robot's decimated replies
  refresh them during the following tick. It keeps answering only while the robot's replies
  keep coming (none for ``2 * reply_every + 2`` rounds: its agent is left to time out).
* **Events.** A reply's one-shot status events (WATCHDOG_TRIPPED, RX_ERRORS) that reach no
  agent (a late reply) are carried into the agent's next answer, so each is reported once.

Robots whose firmware speaks protocol 1 (HELLO reports it) stay on unicast.

The packer is fed and drained by the gateway's threads under one lock; it does no I/O and reads
no clock (times are passed in, [s] of a monotonic clock).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from hilswarm.agents.errors import WireFormatError
from hilswarm.agents.link.board import PIN_COUNT, BoardStatus, PinMode
from hilswarm.agents.link.broadcast import SectionLayout
from hilswarm.agents.link.codec import (
    MAX_PAYLOAD,
    BcastMsg,
    BcastSection,
    ConfigMsg,
    FrameDecoder,
    MsgType,
    TickReplyMsg,
    encode_payload,
    frame_payload,
    parse_payload,
    pins_of_mask,
)

_log = logging.getLogger(__name__)

#: One-shot status events (reported once) and the bits a stale reply repeats.
EVENTS = int(BoardStatus.WATCHDOG_TRIPPED | BoardStatus.RX_ERRORS)
_KEPT_STATUS = ~EVENTS & 0xFF
#: ``answer`` values: wait for the robot's own reply on its reply ticks, or answer at once.
ANSWERS = ("wait", "at_once")
#: Section header bytes (id, hdr) and a BCAST's type + seq [B].
_SECTION_HEADER = 2
_FRAME_HEADER = 2


@dataclass(frozen=True)
class Unicast:
    """Send ``data`` (wire frames) to robot ``name`` by unicast."""

    name: str
    data: bytes


@dataclass(frozen=True)
class Broadcast:
    """Send ``data`` (one BCAST wire frame) to every robot; ``names``: whose sections it holds."""

    data: bytes
    names: tuple[str, ...]


@dataclass(frozen=True)
class ToAgent:
    """Publish ``data`` (wire frames) on agent ``name``'s ``link/rx``; ``stale``: answered by
    the gateway from the robot's last samples."""

    name: str
    data: bytes
    stale: bool = False


Action = Unicast | Broadcast | ToAgent


@dataclass
class _Pending:
    """A TICK waiting in the current round."""

    agent_seq: int
    read_pins: tuple[int, ...]
    data: bytes


@dataclass
class _Robot:
    """What the packer knows of one robot."""

    name: str
    index: int
    reply_every: int
    protocol: int | None = None
    pending_config: tuple[int, dict[int, int]] | None = None  # CONFIG seq, its modes
    layout: SectionLayout | None = None
    modes: dict[int, int] = field(default_factory=dict)
    samples: dict[int, int] | None = None  # last fresh samples by pin
    status: int = 0
    time_us: int = 0
    owed: tuple[int, int, tuple[int, ...]] | None = None  # BCAST seq, agent seq, read pins
    events: int = 0  # events of replies no agent has seen yet
    fresh_round: int = 0  # round of the last reply received
    last_agent_seq: int | None = None
    last_tick_s: float = -1e9
    tx: FrameDecoder = field(default_factory=FrameDecoder)
    rx: FrameDecoder = field(default_factory=FrameDecoder)
    fresh: int = 0
    stale: int = 0
    asked_again: int = 0  # rounds it was asked out of turn: its last requested reply missing

    @property
    def bcast_id(self) -> int:
        """The robot's broadcast id (1-255)."""
        return self.index + 1

    @property
    def packable(self) -> bool:
        """True once the robot speaks protocol 2 and its configuration is known."""
        return self.layout is not None


class BroadcastPacker:
    """Gather TICKs into BCAST rounds, answer from decimated replies (module docstring).

    Args:
        robots: agent names of the robots (broadcast ids follow this order: index + 1).
        reply_every: agent name -> m (its robot answers every m-th round); absent: 1.
        period_s: the experiment's tick period [s].
        gather_s: how long a round waits for the expected TICKs after its first [s]
            (default: half the period).
        answer: ``"wait"`` (a robot's agent waits for its reply on its reply ticks) or
            ``"at_once"`` (every TICK answered at once, samples always STALE).
    """

    def __init__(
        self,
        robots: Sequence[str],
        *,
        reply_every: Mapping[str, int] | None = None,
        period_s: float,
        gather_s: float | None = None,
        answer: str = "wait",
    ) -> None:
        if answer not in ANSWERS:
            raise ValueError(f"answer must be one of {ANSWERS}, got {answer!r}")
        self.at_once = answer == "at_once"
        every = dict(reply_every or {})
        if len(robots) > 255:
            raise ValueError("a broadcast addresses at most 255 robots (8-bit ids)")
        self.robots = {
            name: _Robot(name, i, max(1, int(every.get(name, 1)))) for i, name in enumerate(robots)
        }
        self.period_s = period_s
        self.gather_s = period_s / 2 if gather_s is None else gather_s
        self.rounds = 0
        self.frames = 0
        self._seq = 0
        self._round: dict[str, _Pending] = {}
        self._round_start_s: float | None = None

    # ------------------------------------------------------------------ agent -> robot
    def from_agent(self, name: str, data: bytes, now_s: float) -> list[Action]:
        """Bytes an agent's board sent: the actions they cause."""
        robot = self.robots[name]
        actions: list[Action] = []
        for payload in robot.tx.feed(data):
            kind = payload[0]
            if kind == MsgType.TICK and robot.packable:
                pending = self._pending(robot, payload)
                if pending is not None:
                    robot.last_tick_s = now_s
                    if name in self._round:  # a second TICK before the round left: send it
                        actions += self.flush(now_s)
                    if not self._round:
                        self._round_start_s = now_s
                    self._round[name] = pending
                    if self._complete(now_s):
                        actions += self.flush(now_s)
                    continue
            out = self._config(robot, payload) if kind == MsgType.CONFIG else payload
            actions.append(Unicast(name, frame_payload(out)))
        return actions

    def _pending(self, robot: _Robot, payload: bytes) -> _Pending | None:
        """The TICK as this robot's section, or ``None`` to send it by unicast."""
        layout = robot.layout
        if layout is None:
            return None
        modes = [robot.modes.get(pin, PinMode.UNUSED) for pin in range(PIN_COUNT)]
        try:
            msg = parse_payload(payload, modes=modes)
            if msg.msg_type != MsgType.TICK:
                return None
            written = {w.pin: w.value for w in msg.writes}  # type: ignore[union-attr]
            reads = tuple(pins_of_mask(msg.rmask))  # type: ignore[union-attr]
            if set(written) != set(layout.wide_pins) or not set(reads) <= set(layout.input_pins):
                return None
            data = layout.encode(msg.dout, written)  # type: ignore[union-attr]
        except WireFormatError:
            return None  # the board answers it with the right ERROR over unicast
        retry = robot.last_agent_seq == payload[1]
        robot.last_agent_seq = payload[1]
        return None if retry else _Pending(payload[1], reads, data)

    def _config(self, robot: _Robot, payload: bytes) -> bytes:
        """A CONFIG on its way: note its modes; add the broadcast id for a protocol-2 robot."""
        robot.layout = None  # until this configuration is accepted
        robot.samples = None
        robot.owed = None
        try:
            msg = parse_payload(payload)
        except WireFormatError:
            return payload
        if not isinstance(msg, ConfigMsg):
            return payload
        robot.pending_config = (msg.seq, {e.pin: e.mode for e in msg.entries})
        if robot.protocol is None or robot.protocol < 2:
            return payload
        return encode_payload(ConfigMsg(msg.seq, msg.watchdog_ms, msg.entries, robot.bcast_id))

    def _complete(self, now_s: float) -> bool:
        horizon = now_s - 2 * self.period_s
        expected = {n for n, r in self.robots.items() if r.packable and r.last_tick_s >= horizon}
        return expected <= self._round.keys()

    def due(self, now_s: float) -> float | None:
        """When the current round must leave even if incomplete [s] (``None``: no round)."""
        if self._round_start_s is None:
            return None
        return self._round_start_s + self.gather_s

    def poll(self, now_s: float) -> list[Action]:
        """Send the current round if its gathering time is over."""
        due = self.due(now_s)
        return self.flush(now_s) if due is not None and now_s >= due else []

    def flush(self, now_s: float) -> list[Action]:
        """Send the current round: its BCAST frame(s), then the stale answers."""
        if not self._round:
            return []
        self.rounds += 1
        sections: list[tuple[str, BcastSection]] = []
        answers: list[Action] = []
        for name, pending in self._round.items():
            robot = self.robots[name]
            turn = (self.rounds + robot.index) % robot.reply_every == 0
            if self.at_once and robot.samples is not None:
                patience = 2 * robot.reply_every + 2
                if self.rounds - robot.fresh_round <= patience:  # its replies keep coming
                    sections.append((name, BcastSection(robot.bcast_id, turn, pending.data)))
                    answers.append(self._stale(robot, pending))
                    continue
            # asked last time and never answered; or (at once) no reply for too long
            missed = robot.owed is not None or (self.at_once and robot.samples is not None)
            reply = turn or missed or robot.samples is None
            if reply and not turn and robot.samples is not None:
                robot.asked_again += 1
            sections.append((name, BcastSection(robot.bcast_id, reply, pending.data)))
            if reply:
                robot.owed = (-1, pending.agent_seq, pending.read_pins)  # seq set below
            else:
                answers.append(self._stale(robot, pending))
        self._round.clear()
        self._round_start_s = None
        return [*self._frames(sections), *answers]

    def _frames(self, sections: list[tuple[str, BcastSection]]) -> list[Action]:
        out: list[Action] = []
        batch: list[tuple[str, BcastSection]] = []
        size = _FRAME_HEADER
        for item in sections:
            need = _SECTION_HEADER + len(item[1].data)
            if batch and size + need > MAX_PAYLOAD:
                out.append(self._frame(batch))
                batch, size = [], _FRAME_HEADER
            batch.append(item)
            size += need
        if batch:
            out.append(self._frame(batch))
        return out

    def _frame(self, batch: list[tuple[str, BcastSection]]) -> Broadcast:
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFF
        self.frames += 1
        for name, section in batch:
            robot = self.robots[name]
            if section.reply and robot.owed is not None:
                robot.owed = (seq, robot.owed[1], robot.owed[2])
        payload = encode_payload(BcastMsg(seq, tuple(s for _, s in batch)))
        return Broadcast(frame_payload(payload), tuple(name for name, _ in batch))

    def _stale(self, robot: _Robot, pending: _Pending) -> ToAgent:
        samples = robot.samples or {}
        robot.stale += 1
        values = tuple(samples.get(pin, 0) for pin in pending.read_pins)
        data = stale_tick_reply(
            pending.agent_seq, robot.status, robot.events, robot.time_us, values
        )
        robot.events = 0
        return ToAgent(robot.name, data, stale=True)

    # ------------------------------------------------------------------ robot -> agent
    def from_robot(self, name: str, data: bytes) -> list[Action]:
        """Bytes a robot sent: what goes to its agent."""
        robot = self.robots[name]
        actions: list[Action] = []
        for payload in robot.rx.feed(data):
            kind = payload[0]
            if kind == MsgType.BCAST_REPLY:
                answer = self._fresh(robot, payload)
                if answer is not None:
                    actions.append(answer)
                continue
            if kind == MsgType.HELLO_REPLY and len(payload) > 2:
                robot.protocol = payload[2]
            elif kind == MsgType.CONFIG_REPLY and robot.pending_config is not None:
                seq, modes = robot.pending_config
                if payload[1] == seq:
                    robot.pending_config = None
                    robot.modes = modes
                    robot.layout = (
                        SectionLayout.of(modes)
                        if robot.protocol is not None and robot.protocol >= 2
                        else None
                    )
            actions.append(ToAgent(name, frame_payload(payload)))
        return actions

    def _fresh(self, robot: _Robot, payload: bytes) -> ToAgent | None:
        """A BCAST_REPLY: the newest samples; the agent's TICK_REPLY if it answers the
        broadcast the agent waits for."""
        layout = robot.layout
        if layout is None:
            return None
        try:
            msg = parse_payload(payload)
        except WireFormatError:
            return None
        samples = getattr(msg, "samples", ())
        if len(samples) != len(layout.input_pins):
            return None
        robot.fresh += 1
        robot.fresh_round = self.rounds
        robot.samples = dict(zip(layout.input_pins, samples, strict=True))
        robot.time_us = int.from_bytes(payload[3:7], "little")
        robot.status = payload[2]
        owed = robot.owed
        if owed is None or payload[1] != owed[0]:
            robot.events |= robot.status & EVENTS  # late or unasked: no agent sees it now
            return None
        robot.owed = None
        reply = TickReplyMsg(
            owed[1],
            robot.status | robot.events,
            robot.time_us,
            tuple(robot.samples[pin] for pin in owed[2]),
        )
        robot.events = 0
        return ToAgent(robot.name, frame_payload(encode_payload(reply)))

    def stats(self) -> dict[str, dict[str, int]]:
        """Per robot so far: its own replies received (``fresh_replies``), the rounds it was
        asked out of its turn because its last requested reply had not come (``asked_again``:
        a reply lost or late on the radio), and its broadcast id."""
        return {
            n: {"bcast_id": r.bcast_id, "fresh_replies": r.fresh, "asked_again": r.asked_again}
            for n, r in self.robots.items()
        }


def stale_tick_reply(
    agent_seq: int, status: int, events: int, time_us: int, samples: Sequence[int]
) -> bytes:
    """The wire frame of a TICK_REPLY the gateway gives itself from a robot's last samples:
    the robot's last ``status`` without its one-shot events, the ``events`` no agent has seen
    yet, and :attr:`~.board.BoardStatus.STALE`; ``time_us``: the board time of the samples."""
    reply = TickReplyMsg(
        agent_seq,
        (status & _KEPT_STATUS) | events | BoardStatus.STALE,
        time_us,
        tuple(samples),
    )
    return frame_payload(encode_payload(reply))

"""The radio budget of one XBee gateway: host UART bytes and air time per tick. Pure.

**Unicast** (``[gateway] mode = "unicast"``): per tick and per robot one TICK request and one
reply, with the frame sizes of :mod:`.api_frames` and the air model of :mod:`.air`:

* host UART out (host -> coordinator): a TX Request around the TICK frame (802.15.4: 15 B +
  payload; ZigBee/DigiMesh: 18 B + payload);
* host UART in (coordinator -> host): an RX Packet around the reply (15 B + payload; 16 B) and
  a TX Status (7 B; 11 B);
* air (one channel, both directions share it): an acknowledged unicast for the request and one
  for the reply, each at its mean time (:meth:`~.air.AirParams.mean_unicast_s`).

**Packed broadcast** (``mode = "broadcast"``, :mod:`.packer`): per tick the robots' sections
(2 B + levels + one byte per PWM duty, two per servo) packed into as few BCAST frames as the
96-byte payload limit needs, each one TX Request to the broadcast address (no ACK, no retry, no
TX Status), plus the replies of the tick: robot i answers when ``(k + i) % reply_every == 0``;
the budget takes the tick with the most replies (their RX Packets and acknowledged unicasts).

A budget over 100 % of the tick period fails ``hilswarm check`` (the ticks cannot all go
through); over 70 % it warns (no room for retries). Each message says what overflows, by how
much, and what would fit: a lower rate, fewer robots, a faster baud, the packed broadcast or a
larger ``reply_every``.

**Latency** (:func:`tick_latency`). The budget sums each resource's time per tick; a tick also
needs its stages one after the other, which the sums leave out: the first request through the
host UART before any air time, each robot's radio passing a whole packet to its board's UART
(the firmware's 115200 baud, :data:`ROBOT_BAUD`) before the board answers, the reply back
through the robot's UART and the host UART. With ``answer = "wait"`` a tick is done when
every agent has its answer; answering at once (unicast or broadcast), when every robot drives
the tick's outputs. :data:`HOST_ALLOWANCE_S` stands for what the host adds (the bus hops,
the gathering of the agents' TICKs, the gateway's Python: measured 2-4 ms above the model).
Above :data:`LATENCY_WARN_FRACTION` of the period a realtime run can expect late ticks, and
``hilswarm check`` warns (a lockstep run has no deadline).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from hilswarm.agents.link.board import PinConfig, PinMode
from hilswarm.agents.link.broadcast import SectionLayout
from hilswarm.agents.link.codec import (
    MAX_PAYLOAD,
    PinWrite,
    TickMsg,
    TickReplyMsg,
    encode_payload,
    frame_payload,
)
from hilswarm.agents.xbee.air import AirParams, uart_s
from hilswarm.agents.xbee.api_frames import FrameFamily
from hilswarm.agents.xbee.sim_coordinator import BAUD_CODES

#: Above this fraction of the tick period a budget warns.
WARN_FRACTION = 0.70
#: Above this fraction it fails.
FAIL_FRACTION = 1.00
#: The robots' UART [baud]: the firmware's 115200 8N1 (docs/protocol.md); each robot's radio
#: passes every packet it receives to its board at this rate.
ROBOT_BAUD = 115200
#: What the host adds to a tick above the radio model [s]: the bus hops, the gathering of the
#: agents' TICKs and the gateway's Python (measured 2-4 ms above it, docs/xbee.md "Measured").
HOST_ALLOWANCE_S = 0.002
#: Above this fraction of the period a realtime tick's latency warns (late ticks to expect).
LATENCY_WARN_FRACTION = 0.80
#: API frame bytes around the payload: (TX request, RX packet, TX status) per family.
FRAME_BYTES = {
    FrameFamily.IEEE_802_15_4: (15, 15, 7),
    FrameFamily.ZIGBEE: (18, 16, 11),
}


def tick_frame_sizes(pins: Sequence[PinConfig]) -> tuple[int, int]:
    """Wire bytes (COBS frame with CRC and delimiter) of a TICK writing every output of
    ``pins`` and sampling every input, and of its reply."""
    writes = tuple(
        PinWrite(p.pin, 1000 if p.mode == PinMode.SERVO else 1, PinMode(p.mode))
        for p in pins
        if p.mode in (PinMode.PWM, PinMode.SERVO)
    )
    rmask = 0
    n_reads = 0
    for p in pins:
        if PinMode(p.mode).is_input:
            rmask |= 1 << p.pin
            n_reads += 1
    request = frame_payload(encode_payload(TickMsg(1, 0, rmask, writes)))
    reply = frame_payload(encode_payload(TickReplyMsg(1, 0, 1, (1,) * n_reads)))
    return len(request), len(reply)


def section_size(pins: Sequence[PinConfig]) -> int:
    """Data bytes of the BCAST section of a board configured with ``pins`` (its reply, a
    sample of every input, is as long as :func:`tick_frame_sizes`' reply)."""
    return SectionLayout.of({p.pin: int(p.mode) for p in pins}).length


@dataclass(frozen=True)
class RobotTraffic:
    """What one robot exchanges per tick.

    Attributes:
        name: agent name.
        request_bytes: TICK frame [B].
        reply_bytes: reply frame [B] (a TICK's or a BCAST's: every input sampled).
        section_bytes: data of its BCAST section [B] (broadcast mode).
        reply_every: broadcast mode: it answers every ``reply_every``-th tick.
    """

    name: str
    request_bytes: int
    reply_bytes: int
    section_bytes: int = 0
    reply_every: int = 1


@dataclass(frozen=True)
class Budget:
    """One gateway's load per tick.

    Attributes:
        rate_hz: tick rate [Hz].
        baud: host UART rate [baud].
        family: radio frame family.
        robots: the robots' traffic.
        uart_out_s: host -> coordinator UART time per tick [s].
        uart_in_s: coordinator -> host UART time per tick [s].
        air_request_s: air time of the requests per tick [s].
        air_reply_s: air time of the replies per tick [s].
        mode: ``"unicast"`` or ``"broadcast"``.
        frames: broadcast mode: BCAST frames per tick.
        replies: broadcast mode: replies in the tick with the most.
    """

    rate_hz: float
    baud: int
    family: FrameFamily
    robots: tuple[RobotTraffic, ...]
    uart_out_s: float
    uart_in_s: float
    air_request_s: float
    air_reply_s: float
    mode: str = "unicast"
    frames: int = 0
    replies: int = 0

    @property
    def dt(self) -> float:
        """Tick period [s]."""
        return 1.0 / self.rate_hz

    @property
    def air_s(self) -> float:
        """Air time per tick, both directions (one shared channel) [s]."""
        return self.air_request_s + self.air_reply_s

    def fractions(self) -> dict[str, float]:
        """Load of each resource as a fraction of the tick period."""
        return {
            "host UART out": self.uart_out_s / self.dt,
            "host UART in": self.uart_in_s / self.dt,
            "air": self.air_s / self.dt,
        }


def gateway_budget(
    robots: Sequence[RobotTraffic],
    *,
    rate_hz: float,
    baud: int = 115200,
    family: FrameFamily = FrameFamily.IEEE_802_15_4,
    air: AirParams | None = None,
) -> Budget:
    """The unicast budget of ``robots`` on one coordinator (see the module docstring)."""
    air = air or AirParams()
    tx, rx, status = FRAME_BYTES[family]
    out_bytes = sum(tx + r.request_bytes for r in robots)
    in_bytes = sum(rx + r.reply_bytes + status for r in robots)
    return Budget(
        rate_hz,
        baud,
        family,
        tuple(robots),
        uart_s(out_bytes, baud),
        uart_s(in_bytes, baud),
        sum(air.mean_unicast_s(r.request_bytes) for r in robots),
        sum(air.mean_unicast_s(r.reply_bytes) for r in robots),
    )


def bcast_frame_sizes(section_bytes: Sequence[int]) -> list[int]:
    """Wire bytes of the BCAST frames that carry sections of ``section_bytes`` data each, packed
    in order into payloads of at most 96 B (type, seq, then id, hdr and data per section; COBS
    adds one byte below 254, the CRC two, the delimiter one)."""
    frames: list[int] = []
    size = 2
    for data in section_bytes:
        need = 2 + data
        if size > 2 and size + need > MAX_PAYLOAD:
            frames.append(size + 4)
            size = 2
        size += need
    if size > 2:
        frames.append(size + 4)
    return frames


def _reply_ticks(robots: Sequence[RobotTraffic]) -> list[list[RobotTraffic]]:
    """Who answers on each tick of one round-robin cycle (robot i when (k + i) % m == 0); at
    most 1000 ticks of it (the least common multiple of the m can be long)."""
    cycle = min(math.lcm(*(max(1, r.reply_every) for r in robots)) if robots else 1, 1000)
    return [
        [r for i, r in enumerate(robots) if (k + i) % max(1, r.reply_every) == 0]
        for k in range(cycle)
    ]


def broadcast_budget(
    robots: Sequence[RobotTraffic],
    *,
    rate_hz: float,
    baud: int = 115200,
    family: FrameFamily = FrameFamily.IEEE_802_15_4,
    air: AirParams | None = None,
) -> Budget:
    """The packed-broadcast budget of ``robots`` (see the module docstring): the tick with the
    most replies."""
    air = air or AirParams()
    tx, rx, _status = FRAME_BYTES[family]
    frames = bcast_frame_sizes([r.section_bytes for r in robots])
    ticks = _reply_ticks(robots)
    air_reply = max(sum(air.mean_unicast_s(r.reply_bytes) for r in t) for t in ticks)
    in_bytes = max(sum(rx + r.reply_bytes for r in t) for t in ticks)
    return Budget(
        rate_hz,
        baud,
        family,
        tuple(robots),
        uart_s(sum(tx + f for f in frames), baud),
        uart_s(in_bytes, baud),
        sum(air.mean_broadcast_s(f) for f in frames),
        air_reply,
        "broadcast",
        len(frames),
        max(len(t) for t in ticks),
    )


def budget_for(
    robots: Sequence[RobotTraffic],
    *,
    mode: str,
    rate_hz: float,
    baud: int = 115200,
    family: FrameFamily = FrameFamily.IEEE_802_15_4,
) -> Budget:
    """:func:`gateway_budget` or :func:`broadcast_budget`, by ``mode``."""
    build = broadcast_budget if mode == "broadcast" else gateway_budget
    return build(robots, rate_hz=rate_hz, baud=baud, family=family)


def _worst(budget: Budget) -> float:
    return max(budget.fractions().values())


def _broadcast_advice(budget: Budget, limit: float) -> str | None:
    """The packed broadcast (or a larger ``reply_every``) that brings ``budget`` under
    ``limit``, with its figure; ``None`` if none does."""
    current = min((r.reply_every for r in budget.robots), default=1)
    for m in (1, 2, 3, 5, 10, 20):
        if budget.mode == "broadcast" and m <= current:
            continue
        robots = [replace(r, reply_every=max(m, r.reply_every)) for r in budget.robots]
        other = broadcast_budget(
            robots, rate_hz=budget.rate_hz, baud=budget.baud, family=budget.family
        )
        if _worst(other) <= limit:
            what = (
                '[gateway] mode = "broadcast"'
                if budget.mode != "broadcast"
                else "a larger reply_every"
            )
            return f"{what} with reply_every = {m} ({_worst(other):.0%} of the tick)"
    return None


def _advice(budget: Budget, resource: str, fraction: float, limit: float = 1.0) -> str:
    n = len(budget.robots)
    need_s = fraction * budget.dt
    fitting_rate = budget.rate_hz / fraction
    per_robot_s = need_s / n if n else need_s
    fitting_robots = math.floor(budget.dt / per_robot_s) if per_robot_s > 0 else n
    parts = [f"rate_hz <= {math.floor(fitting_rate * 10) / 10:g} Hz"]
    if fitting_robots < n:
        parts.append(f"at most {fitting_robots} robots on this coordinator")
    if resource.startswith("host UART"):
        faster = [b for b in sorted(BAUD_CODES.values()) if b > budget.baud]
        needed = budget.baud * fraction
        fits = [b for b in faster if b >= needed]
        parts.append(
            f"[gateway] baud = {fits[0]}" if fits else "a second coordinator (no faster baud)"
        )
    else:
        parts.append("a second coordinator on another channel")
    packed = _broadcast_advice(budget, limit)
    if packed is not None:
        parts.insert(0, packed)
    parts.append("fewer pins per TICK (smaller frames)")
    return "; ".join(parts)


def budget_messages(budget: Budget) -> tuple[list[str], list[str]]:
    """``(errors, warnings)``: each resource over 100 % (error) or over 70 % (warning)."""
    errors: list[str] = []
    warnings: list[str] = []
    n = len(budget.robots)
    for resource, fraction in budget.fractions().items():
        if fraction <= WARN_FRACTION:
            continue
        used_ms = fraction * budget.dt * 1e3
        head = (
            f"XBee {resource}: {used_ms:.1f} ms per tick of {budget.dt * 1e3:.1f} ms "
            f"({fraction:.0%}) for {n} robots {_how(budget)} at {budget.rate_hz:g} Hz, "
            f"{budget.baud} baud"
        )
        if fraction > FAIL_FRACTION:
            errors.append(
                f"{head}: over by {fraction - 1:.0%}; to fit: {_advice(budget, resource, fraction)}"
            )
        else:
            warnings.append(
                f"{head}: little room for retries; to fit below {WARN_FRACTION:.0%}: "
                f"{_advice(budget, resource, fraction / WARN_FRACTION, WARN_FRACTION)}"
            )
    return errors, warnings


def _how(budget: Budget) -> str:
    if budget.mode != "broadcast":
        return "by unicast"
    every = sorted({r.reply_every for r in budget.robots})
    m = str(every[0]) if len(every) == 1 else f"{every[0]}-{every[-1]}"
    return (
        f"by packed broadcast ({budget.frames} frame(s), {budget.replies} replies in the "
        f"busiest tick, reply_every {m})"
    )


@dataclass(frozen=True)
class TickLatency:
    """How long one tick takes through the radio (module docstring, "Latency").

    Attributes:
        radio_s: by the model, from the tick's start to what it waits for [s].
        waits_for: ``"answers"`` (every agent's answer: ``answer = "wait"``) or
            ``"outputs"`` (every robot driving the tick's outputs: ``answer = "at_once"``).
        period_s: the tick period [s].
    """

    radio_s: float
    waits_for: str
    period_s: float

    @property
    def total_s(self) -> float:
        """The model plus :data:`HOST_ALLOWANCE_S` [s]."""
        return self.radio_s + HOST_ALLOWANCE_S

    @property
    def fraction(self) -> float:
        """:attr:`total_s` as a fraction of the period."""
        return self.total_s / self.period_s


def tick_latency(
    budget: Budget, *, answer: str = "wait", air: AirParams | None = None
) -> TickLatency:
    """The latency of one tick of ``budget``'s robots (module docstring, "Latency").

    By unicast: the first TICK through the host UART, each robot's request and reply on the
    air one after the other (the gateway writes the TICKs back to back, so the UARTs overlap
    the air), then the last robot's UART both ways with its radio's packetization timeout and
    its RX frame and TX status through the host UART; answering at once, up to the last
    robot's request through its UART, with every other robot's reply on the air before it
    (the worst order). By broadcast: the BCAST frames through
    the host UART and the air, all of them through a robot's UART; then, waiting for the
    replies, the reply's UART and packetization, the busiest tick's replies on the air and the
    last RX frame. The largest request and reply stand for every robot's.
    """
    air = air or AirParams()
    tx, rx, status = FRAME_BYTES[budget.family]
    robots = budget.robots
    dt = budget.dt
    if not robots:
        return TickLatency(0.0, "answers", dt)
    request = max(r.request_bytes for r in robots)
    reply = max(r.reply_bytes for r in robots)
    back = uart_s(reply + air.packetization_chars, ROBOT_BAUD)
    if budget.mode != "broadcast":
        # every robot's request on the air, and every robot's reply before the last request
        air_s = sum(air.mean_unicast_s(r.request_bytes) for r in robots)
        air_s += sum(air.mean_unicast_s(r.reply_bytes) for r in robots[:-1])
        outputs = uart_s(tx + request, budget.baud) + air_s + uart_s(request, ROBOT_BAUD)
        if answer == "at_once":  # the last robot's own reply is not waited for
            return TickLatency(outputs, "outputs", dt)
        last = air.mean_unicast_s(robots[-1].reply_bytes) + back
        return TickLatency(outputs + last + uart_s(rx + reply + status, budget.baud), "answers", dt)
    frames = bcast_frame_sizes([r.section_bytes for r in robots])
    outputs = sum(uart_s(tx + f, budget.baud) + air.mean_broadcast_s(f) for f in frames)
    outputs += uart_s(sum(frames), ROBOT_BAUD)
    if answer == "at_once":
        return TickLatency(outputs, "outputs", dt)
    busiest = max(_reply_ticks(robots), key=len)
    replies = sum(air.mean_unicast_s(r.reply_bytes) for r in busiest)
    return TickLatency(outputs + back + replies + uart_s(rx + reply, budget.baud), "answers", dt)


def latency_messages(budget: Budget, *, answer: str = "wait") -> list[str]:
    """Warnings for a realtime run whose tick latency (:func:`tick_latency`) is over
    :data:`LATENCY_WARN_FRACTION` of the period: by how much, and what would fit."""
    latency = tick_latency(budget, answer=answer)
    if latency.fraction <= LATENCY_WARN_FRACTION:
        return []
    n = len(budget.robots)
    if latency.waits_for == "answers":
        waited = "every agent has its answer"
        late = (
            "every tick will be late"
            if latency.fraction > 1.0
            else "expect late ticks (little room for the air's backoff and the host's jitter)"
        )
    else:
        waited = "every robot drives the tick's outputs"
        late = (
            "each tick's outputs will reach the robots after the next tick is due"
            if latency.fraction > 1.0
            else "expect some ticks' outputs to reach robots after the next tick is due"
        )
    return [
        f"XBee latency: ~{latency.total_s * 1e3:.1f} ms from a tick's start until {waited} "
        f"({latency.radio_s * 1e3:.1f} ms through the UARTs and the air, "
        f"{HOST_ALLOWANCE_S * 1e3:g} ms for the host), {latency.fraction:.0%} of the "
        f"{latency.period_s * 1e3:.1f} ms period, for {n} robots {_how(budget)}"
        f"{' answering at once' if latency.waits_for == 'outputs' else ''} at "
        f"{budget.rate_hz:g} Hz: {late} in realtime; to fit below "
        f"{LATENCY_WARN_FRACTION:.0%}: {_latency_advice(budget, answer, latency)}"
    ]


def _latency_advice(budget: Budget, answer: str, latency: TickLatency) -> str:
    limit = LATENCY_WARN_FRACTION
    parts = [f"rate_hz <= {math.floor(limit / latency.total_s * 10) / 10:g} Hz"]
    fitting = 0
    for count in range(len(budget.robots) - 1, 0, -1):
        fewer = budget_for(
            budget.robots[:count],
            mode=budget.mode,
            rate_hz=budget.rate_hz,
            baud=budget.baud,
            family=budget.family,
        )
        if tick_latency(fewer, answer=answer).fraction <= limit:
            fitting = count
            break
    if fitting:
        parts.append(f"at most {fitting} robot{'s' if fitting > 1 else ''} on this coordinator")
    options: list[tuple[str, Budget, str]] = []
    if answer != "at_once":
        options.append(('[gateway] answer = "at_once"', budget, "at_once"))
    if budget.mode != "broadcast":
        robots = [replace(r, reply_every=5) for r in budget.robots]
        packed = broadcast_budget(
            robots, rate_hz=budget.rate_hz, baud=budget.baud, family=budget.family
        )
        options.append(('[gateway] mode = "broadcast" with reply_every = 5', packed, "wait"))
        options.append(('the same with answer = "at_once"', packed, "at_once"))
    for what, other, how in options:
        fraction = tick_latency(other, answer=how).fraction
        if fraction <= limit and _worst(other) <= FAIL_FRACTION:
            parts.insert(0, f"{what} ({fraction:.0%} of the period)")
            break
    parts.append("a second coordinator on another channel")
    return "; ".join(parts)

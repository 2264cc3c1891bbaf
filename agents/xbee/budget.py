"""The radio budget of one XBee gateway: host UART bytes and air time per tick. Pure.

Per tick and per robot, unicast (one TICK request, one reply), with the frame sizes of
:mod:`.api_frames` and the air model of :mod:`.air`:

* host UART out (host -> coordinator): a TX Request around the TICK frame (802.15.4: 15 B +
  payload; ZigBee/DigiMesh: 18 B + payload);
* host UART in (coordinator -> host): an RX Packet around the reply (15 B + payload; 16 B) and
  a TX Status (7 B; 11 B);
* air (one channel, both directions share it): an acknowledged unicast for the request and one
  for the reply, each at its mean time (:meth:`~.air.AirParams.mean_unicast_s`).

A budget over 100 % of the tick period fails ``hilswarm check`` (the ticks cannot all go
through); over 70 % it warns (no room for retries). Each message says what overflows, by how
much, and what would fit: a lower rate, fewer robots, a faster baud.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from hilswarm.agents.link.board import PinConfig, PinMode
from hilswarm.agents.link.codec import (
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


@dataclass(frozen=True)
class RobotTraffic:
    """What one robot exchanges per tick.

    Attributes:
        name: agent name.
        request_bytes: TICK frame [B].
        reply_bytes: reply frame [B].
    """

    name: str
    request_bytes: int
    reply_bytes: int


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
    """

    rate_hz: float
    baud: int
    family: FrameFamily
    robots: tuple[RobotTraffic, ...]
    uart_out_s: float
    uart_in_s: float
    air_request_s: float
    air_reply_s: float

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


def _advice(budget: Budget, resource: str, fraction: float) -> str:
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
            f"({fraction:.0%}) for {n} robots by unicast at {budget.rate_hz:g} Hz, "
            f"{budget.baud} baud"
        )
        if fraction > FAIL_FRACTION:
            errors.append(
                f"{head}: over by {fraction - 1:.0%}; to fit: {_advice(budget, resource, fraction)}"
            )
        else:
            warnings.append(
                f"{head}: little room for retries; to fit below {WARN_FRACTION:.0%}: "
                f"{_advice(budget, resource, fraction / WARN_FRACTION)}"
            )
    return errors, warnings

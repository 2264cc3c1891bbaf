"""Servo: an RC servo on a Timer1 pin (9 or 10), commanded by angle."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from hilswarm.agents.devices.base import Actuator, number_option
from hilswarm.agents.errors import DeviceError
from hilswarm.agents.link.board import SERVO_MAX_US, SERVO_MIN_US, PinMode
from hilswarm.agents.pins import PinManager

__all__ = ["Servo"]

#: Arduino Servo library defaults: 544 µs at 0 deg, 2400 µs at 180 deg.
DEFAULT_MIN_PULSE_US = 544
DEFAULT_MAX_PULSE_US = 2400


class Servo(Actuator):
    """An RC servo; its pulses come from Timer1, so only pins 9 and 10 can carry it.

    The angle [deg] maps linearly to the pulse width [µs]: ``min_angle_deg`` <-> ``min_pulse_us``
    and ``max_angle_deg`` <-> ``max_pulse_us`` (defaults: the Arduino Servo library's 0-180 deg
    over 544-2400 µs). Commands are clipped to ``angle_limits_deg`` (default: the whole mapped
    range), the device-level range of what the linkage tolerates.

    Roles: ``pin`` (SERVO mode). A servo on 9 disables PWM on 10 and vice versa.

    Args:
        pins: the vehicle's PinManager.
        name: device name.
        pinout: ``{"pin": 9}`` or ``{"pin": 10}``.
        min_pulse_us, max_pulse_us: pulse widths [µs] at the two ends of the mapping
            (500..2500, min < max).
        min_angle_deg, max_angle_deg: angles [deg] at the two ends of the mapping (min < max).
        angle_limits_deg: ``(lo, hi)`` [deg] commands are clipped to, inside the mapping.
        neutral_deg: the safe angle [deg] (default: middle of the limits).

    Safe state: the neutral angle.
    """

    roles = ("pin",)

    def __init__(
        self,
        pins: PinManager,
        name: str,
        pinout: Mapping[str, int | str],
        *,
        min_pulse_us: int = DEFAULT_MIN_PULSE_US,
        max_pulse_us: int = DEFAULT_MAX_PULSE_US,
        min_angle_deg: float = 0.0,
        max_angle_deg: float = 180.0,
        angle_limits_deg: tuple[float, float] | None = None,
        neutral_deg: float | None = None,
        **options: Any,
    ) -> None:
        who = f"Servo {name!r}"
        lo_us = number_option(min_pulse_us, f"{who}: min_pulse_us")
        hi_us = number_option(max_pulse_us, f"{who}: max_pulse_us")
        if not SERVO_MIN_US <= lo_us < hi_us <= SERVO_MAX_US:
            raise DeviceError(
                f"{who}: pulse range {min_pulse_us!r}..{max_pulse_us!r} µs must satisfy "
                f"{SERVO_MIN_US} <= min_pulse_us < max_pulse_us <= {SERVO_MAX_US}"
            )
        lo_deg = number_option(min_angle_deg, f"{who}: min_angle_deg")
        hi_deg = number_option(max_angle_deg, f"{who}: max_angle_deg")
        if not lo_deg < hi_deg:
            raise DeviceError(
                f"{who}: min_angle_deg {min_angle_deg!r} must be below max_angle_deg "
                f"{max_angle_deg!r}"
            )
        if angle_limits_deg is None:
            limit_lo, limit_hi = lo_deg, hi_deg
        else:
            try:
                raw_lo, raw_hi = angle_limits_deg
            except (TypeError, ValueError):
                raise DeviceError(
                    f"{who}: angle_limits_deg must be (lo, hi) [deg], got {angle_limits_deg!r}"
                ) from None
            limit_lo = number_option(raw_lo, f"{who}: angle_limits_deg lo")
            limit_hi = number_option(raw_hi, f"{who}: angle_limits_deg hi")
            if not lo_deg <= limit_lo <= limit_hi <= hi_deg:
                raise DeviceError(
                    f"{who}: angle_limits_deg {angle_limits_deg!r} must lie inside the mapped "
                    f"range {lo_deg}..{hi_deg} deg with lo <= hi"
                )
        neutral = (limit_lo + limit_hi) / 2 if neutral_deg is None else neutral_deg
        neutral = number_option(neutral, f"{who}: neutral_deg")
        if not limit_lo <= neutral <= limit_hi:
            raise DeviceError(
                f"{who}: neutral_deg {neutral_deg!r} outside the angle limits "
                f"{limit_lo}..{limit_hi} deg"
            )
        self.pulse_range_us: tuple[float, float] = (lo_us, hi_us)
        self.angle_range_deg: tuple[float, float] = (lo_deg, hi_deg)
        self.angle_limits_deg: tuple[float, float] = (limit_lo, limit_hi)
        self.neutral_deg: float = neutral
        self._angle_deg = neutral
        super().__init__(pins, name, pinout, **options)

    def role_mode(self, role: str) -> PinMode:
        """The only role, ``pin``, is a servo output."""
        return PinMode.SERVO

    def role_safe_value(self, role: str) -> int:
        """The neutral pulse width [µs]."""
        return self.angle_to_pulse(self.neutral_deg)

    def angle_to_pulse(self, angle_deg: float) -> int:
        """Pulse width [µs, rounded] for ``angle_deg`` [deg] (clipped to the angle limits)."""
        angle = min(max(angle_deg, self.angle_limits_deg[0]), self.angle_limits_deg[1])
        (a0, a1), (p0, p1) = self.angle_range_deg, self.pulse_range_us
        return round(p0 + (angle - a0) * (p1 - p0) / (a1 - a0))

    def pulse_to_angle(self, pulse_us: float) -> float:
        """Angle [deg] of a pulse width ``pulse_us`` [µs] (inverse of the linear mapping)."""
        (a0, a1), (p0, p1) = self.angle_range_deg, self.pulse_range_us
        return a0 + (pulse_us - p0) * (a1 - a0) / (p1 - p0)

    def actuate(self, angle_deg: float) -> float:
        """Turn to ``angle_deg`` [deg], clipped to the angle limits.

        Returns:
            The angle [deg] actually commanded (after clipping, before pulse rounding).

        Raises:
            DeviceError: the angle is not a finite number.
        """
        angle = number_option(angle_deg, f"Servo {self.name!r}: angle_deg")
        angle = min(max(angle, self.angle_limits_deg[0]), self.angle_limits_deg[1])
        self.write("pin", self.angle_to_pulse(angle))
        self._angle_deg = angle
        return angle

    @property
    def angle_deg(self) -> float:
        """The angle [deg] last commanded."""
        return self._angle_deg

    def safe(self) -> None:
        """Turn to the neutral angle."""
        self.actuate(self.neutral_deg)

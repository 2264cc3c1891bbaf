"""HBridgeMotor: one or more DC motors behind H-bridges (direction pins + PWM enable)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from hilswarm.agents.devices.base import Actuator
from hilswarm.agents.errors import DeviceError
from hilswarm.agents.link.board import PWM_MAX, PinMode
from hilswarm.agents.pins import PinManager

__all__ = ["HBridgeMotor"]

_SUFFIXES = ("fwd", "back", "pwm")


class HBridgeMotor(Actuator):
    """DC motors driven through H-bridges, any number of them (thesis A.2.2).

    Each motor ``m`` uses three roles: ``<m>_fwd`` and ``<m>_back`` (digital direction inputs of
    the bridge) and ``<m>_pwm`` (PWM enable). A command is a *signed duty* in wire units
    (-255..255): positive drives ``fwd`` high, negative drives ``back`` high, 0 coasts with both
    low. Commands beyond ``max_duty`` (the device-level range, e.g. what the motor tolerates)
    are clipped.

    Args:
        pins: the vehicle's PinManager.
        name: device name (e.g. ``"drive"``).
        pinout: role -> pin for every ``<m>_fwd``, ``<m>_back``, ``<m>_pwm``.
        motors: motor names, e.g. ``("left", "right")``.
        max_duty: largest duty magnitude the device ever drives (0-255), one value for all
            motors or a mapping motor -> value.

    Safe state: both direction pins low, duty 0 (every motor coasts).
    """

    def __init__(
        self,
        pins: PinManager,
        name: str,
        pinout: Mapping[str, int | str],
        *,
        motors: Sequence[str],
        max_duty: int | Mapping[str, int] = PWM_MAX,
        **options: Any,
    ) -> None:
        if isinstance(motors, str) or not isinstance(motors, Sequence) or not motors:
            raise DeviceError(
                f"HBridgeMotor {name!r}: motors must be a non-empty sequence of names, "
                f"got {motors!r}"
            )
        for motor in motors:
            if not isinstance(motor, str) or not motor.isidentifier():
                raise DeviceError(
                    f"HBridgeMotor {name!r}: motor name {motor!r} must be an identifier"
                )
        if len(set(motors)) != len(motors):
            raise DeviceError(f"HBridgeMotor {name!r}: motor names repeat: {list(motors)}")
        self.motors: tuple[str, ...] = tuple(motors)
        limits = max_duty if isinstance(max_duty, Mapping) else dict.fromkeys(motors, max_duty)
        unknown = [m for m in limits if m not in self.motors]
        if unknown:
            raise DeviceError(f"HBridgeMotor {name!r}: max_duty for unknown motor(s) {unknown}")
        self.max_duty: dict[str, int] = {}
        for motor in self.motors:
            limit = limits.get(motor, PWM_MAX)
            if isinstance(limit, bool) or not isinstance(limit, int) or not 0 <= limit <= PWM_MAX:
                raise DeviceError(
                    f"HBridgeMotor {name!r}: max_duty of motor {motor!r} must be an int "
                    f"0..{PWM_MAX}, got {limit!r}"
                )
            self.max_duty[motor] = limit
        self._duty: dict[str, int] = dict.fromkeys(self.motors, 0)
        super().__init__(pins, name, pinout, **options)
        # Per tick: each motor's (fwd, back, pwm) binders, looked up once.
        binders = self._binders
        self._motor_binders: dict[str, tuple[str, str, str]] = {
            motor: (binders[f"{motor}_fwd"], binders[f"{motor}_back"], binders[f"{motor}_pwm"])
            for motor in self.motors
        }

    def required_roles(self) -> tuple[str, ...]:
        """``<m>_fwd``, ``<m>_back``, ``<m>_pwm`` for every motor ``m``."""
        return tuple(f"{motor}_{suffix}" for motor in self.motors for suffix in _SUFFIXES)

    def role_mode(self, role: str) -> PinMode:
        """Direction roles are digital outputs, ``*_pwm`` roles are PWM."""
        return PinMode.PWM if role.endswith("_pwm") else PinMode.DIGITAL_OUT

    def actuate(self, motor: str, command: float) -> int:
        """Drive ``motor`` with a signed duty ``command`` (wire units, -255..255).

        The command is rounded to an integer and clipped to ``±max_duty[motor]``.

        Returns:
            The signed duty actually staged (after clipping).

        Raises:
            DeviceError: unknown motor, or a command that is not a finite number.
        """
        if motor not in self._duty:
            raise DeviceError(
                f"HBridgeMotor {self.name!r} has no motor {motor!r}; motors are {self.motors}"
            )
        try:
            value = float(command)
        except (TypeError, ValueError):
            raise DeviceError(
                f"HBridgeMotor {self.name!r}, motor {motor!r}: command {command!r} is not a number"
            ) from None
        if not math.isfinite(value):
            raise DeviceError(
                f"HBridgeMotor {self.name!r}, motor {motor!r}: command {command!r} is not finite"
            )
        limit = self.max_duty[motor]
        duty = max(-limit, min(limit, round(value)))
        if self._binders:  # bound: straight to the PinManager (it checks every value)
            fwd, back, pwm = self._motor_binders[motor]
            write = self.pins.write
            write(fwd, 1 if duty > 0 else 0)
            write(back, 1 if duty < 0 else 0)
            write(pwm, duty if duty >= 0 else -duty)
        else:  # released: Device.write names the missing role
            self.write(f"{motor}_fwd", 1 if duty > 0 else 0)
        self._duty[motor] = duty
        return duty

    def duty(self, motor: str) -> int:
        """The signed duty last staged for ``motor`` (wire units)."""
        if motor not in self._duty:
            raise DeviceError(
                f"HBridgeMotor {self.name!r} has no motor {motor!r}; motors are {self.motors}"
            )
        return self._duty[motor]

    def safe(self) -> None:
        """Both direction pins low and duty 0 on every motor."""
        for motor in self.motors:
            self.actuate(motor, 0)

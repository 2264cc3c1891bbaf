"""OutputPin: one plain digital or PWM output (enable lines, LEDs, standby pins)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from hilswarm.agents.devices.base import Actuator
from hilswarm.agents.errors import DeviceError
from hilswarm.agents.link.board import PWM_MAX, PinMode
from hilswarm.agents.pins import PinManager

__all__ = ["OutputPin"]

_MODES = {"digital": PinMode.DIGITAL_OUT, "pwm": PinMode.PWM}


class OutputPin(Actuator):
    """A single output pin, digital (0/1) or PWM (duty 0..``max_value``).

    Keeps the device interface even for a bare pin (thesis A.2.2: never drive board pins
    directly). Role: ``pin``.

    Args:
        pins: the vehicle's PinManager.
        name: device name (e.g. ``"standby"``).
        pinout: ``{"pin": <pin>}``.
        mode: ``"digital"`` (default) or ``"pwm"``.
        safe_value: value in safe mode (wire units; default 0).
        max_value: device-level upper limit of PWM commands (0..255, default 255); values
            above it are clipped. Not used in digital mode.
    """

    roles = ("pin",)

    def __init__(
        self,
        pins: PinManager,
        name: str,
        pinout: Mapping[str, int | str],
        *,
        mode: str = "digital",
        safe_value: int = 0,
        max_value: int | None = None,
        **options: Any,
    ) -> None:
        who = f"OutputPin {name!r}"
        if mode not in _MODES:
            raise DeviceError(f"{who}: mode must be one of {sorted(_MODES)}, got {mode!r}")
        self.mode: PinMode = _MODES[mode]
        if self.mode is PinMode.DIGITAL_OUT:
            if max_value is not None:
                raise DeviceError(f"{who}: max_value applies to mode 'pwm' only")
            self.max_value: int = 1
        else:
            top = PWM_MAX if max_value is None else max_value
            if isinstance(top, bool) or not isinstance(top, int) or not 0 <= top <= PWM_MAX:
                raise DeviceError(
                    f"{who}: max_value must be an int 0..{PWM_MAX}, got {max_value!r}"
                )
            self.max_value = top
        if isinstance(safe_value, bool):
            safe_value = int(safe_value)
        if not isinstance(safe_value, int) or not 0 <= safe_value <= self.max_value:
            raise DeviceError(
                f"{who}: safe_value must be an int 0..{self.max_value}, got {safe_value!r}"
            )
        self.safe_value: int = safe_value
        self._value = safe_value
        super().__init__(pins, name, pinout, **options)

    def role_mode(self, role: str) -> PinMode:
        """DIGITAL_OUT or PWM, as configured."""
        return self.mode

    def role_safe_value(self, role: str) -> int:
        """The configured safe value."""
        return self.safe_value

    def actuate(self, value: float | bool) -> int:
        """Set the pin: a bool or 0/1 (digital), or a duty 0..255 (PWM, clipped to max_value).

        Returns:
            The value staged (wire units).

        Raises:
            DeviceError: not a finite number, or a digital value other than 0/1.
        """
        who = f"OutputPin {self.name!r}"
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise DeviceError(f"{who}: value {value!r} is not a number") from None
        if not math.isfinite(number):
            raise DeviceError(f"{who}: value {value!r} is not finite")
        if self.mode is PinMode.DIGITAL_OUT:
            if number not in (0.0, 1.0):
                raise DeviceError(f"{who}: digital value must be 0/1 or a bool, got {value!r}")
            wire = int(number)
        else:
            wire = max(0, min(self.max_value, round(number)))
        self.write("pin", wire)
        self._value = wire
        return wire

    @property
    def value(self) -> int:
        """The value last staged (wire units)."""
        return self._value

    def safe(self) -> None:
        """Stage the safe value."""
        self.actuate(self.safe_value)

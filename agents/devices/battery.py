"""Battery: battery voltage via a resistor divider on an analog pin, with a low-voltage event."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from hilswarm.agents.devices.base import Sensor, number_option
from hilswarm.agents.errors import DeviceError
from hilswarm.agents.link.board import ADC_MAX, PinMode
from hilswarm.agents.pins import PinManager

__all__ = ["Battery", "LowBatteryEvent"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class LowBatteryEvent:
    """The battery voltage fell below its threshold (the thesis' ``LO_BATT``).

    Attributes:
        device: name of the Battery device.
        volts: the battery voltage that crossed [V].
        low_v: the threshold [V].
    """

    device: str
    volts: float
    low_v: float


LowBatteryListener = Callable[[LowBatteryEvent], None]


class Battery(Sensor):
    """Battery voltage measured through a divider on an analog pin.

    ``sense()`` converts the last ADC sample to the battery voltage
    ``volts = counts / 1023 * vref_v * multiplier`` [V] (``multiplier`` undoes the divider, e.g.
    3 for a 1:3 divider). When the voltage falls below ``low_v`` every listener gets a
    :class:`LowBatteryEvent`, once per crossing: the event re-arms only after the voltage has
    risen back to at least ``low_v + hysteresis_v``.

    Role: ``pin`` (ANALOG_IN, A0-A5).

    Args:
        pins: the vehicle's PinManager.
        name: device name.
        pinout: ``{"pin": "A0"}``.
        vref_v: ADC reference [V] (default: the board profile's, 5 V or 3.3 V on the Fio).
        multiplier: battery volts per ADC-pin volt (> 0, default 1).
        low_v: low-battery threshold [V], or ``None`` for no event.
        hysteresis_v: re-arm margin above ``low_v`` [V] (>= 0, default 0).
    """

    roles = ("pin",)

    def __init__(
        self,
        pins: PinManager,
        name: str,
        pinout: Mapping[str, int | str],
        *,
        vref_v: float | None = None,
        multiplier: float = 1.0,
        low_v: float | None = None,
        hysteresis_v: float = 0.0,
        **options: Any,
    ) -> None:
        who = f"Battery {name!r}"
        raw_vref = pins.profile.vref_v if vref_v is None else vref_v
        self.vref_v: float = number_option(raw_vref, f"{who}: vref_v", positive=True)
        self.multiplier = number_option(multiplier, f"{who}: multiplier", positive=True)
        self.low_v: float | None = (
            None if low_v is None else number_option(low_v, f"{who}: low_v", positive=True)
        )
        if isinstance(hysteresis_v, bool) or not isinstance(hysteresis_v, int | float):
            raise DeviceError(f"{who}: hysteresis_v must be a number >= 0, got {hysteresis_v!r}")
        if not math.isfinite(hysteresis_v) or hysteresis_v < 0:
            raise DeviceError(f"{who}: hysteresis_v must be a number >= 0, got {hysteresis_v!r}")
        self.hysteresis_v: float = float(hysteresis_v)
        self._listeners: list[LowBatteryListener] = []
        self._armed = True
        self._volts: float | None = None
        super().__init__(pins, name, pinout, **options)

    def role_mode(self, role: str) -> PinMode:
        """The only role, ``pin``, is an analog input."""
        return PinMode.ANALOG_IN

    def add_listener(self, listener: LowBatteryListener) -> None:
        """Call ``listener(event)`` on every low-battery crossing."""
        if not callable(listener):
            raise DeviceError(f"Battery {self.name!r}: listener {listener!r} is not callable")
        self._listeners.append(listener)

    def remove_listener(self, listener: LowBatteryListener) -> None:
        """Stop calling ``listener`` (no error if it was not registered)."""
        if listener in self._listeners:
            self._listeners.remove(listener)

    def counts_to_volts(self, counts: int) -> float:
        """Battery voltage [V] for an ADC sample ``counts`` (0..1023)."""
        return counts / ADC_MAX * self.vref_v * self.multiplier

    def sense(self) -> float:
        """Battery voltage [V] from the last sample; fires the low-battery event on a crossing."""
        volts = self.counts_to_volts(self.read("pin"))
        self._volts = volts
        if self.low_v is not None:
            if volts < self.low_v:
                if self._armed:
                    self._armed = False
                    event = LowBatteryEvent(self.name, volts, self.low_v)
                    logger.warning("battery %r low: %.3f V < %.3f V", self.name, volts, self.low_v)
                    for listener in list(self._listeners):
                        listener(event)
            elif volts >= self.low_v + self.hysteresis_v:
                self._armed = True
        return volts

    @property
    def volts(self) -> float | None:
        """The voltage [V] of the last sense(), or ``None`` before the first."""
        return self._volts

    @property
    def is_low(self) -> bool:
        """True after a low crossing, until the voltage has recovered (event re-armed)."""
        return not self._armed

"""Device, Actuator, Sensor and InOut: the thesis' device layer (§2.2.3, A.2.7).

A device is a named group of pins with a meaning (a motor, a servo, a battery divider). It binds
its pins with the :class:`~hilswarm.agents.pins.PinManager` when it is constructed, one binder per
role, named ``"<device>.<role>"``, and from then on talks to the board only through those binders.
Writing a new device takes two steps:

1. declare the pin roles (class attribute ``roles`` or :meth:`Device.required_roles`) and the mode
   and safe value of each (:meth:`Device.role_mode`, :meth:`Device.role_safe_value`);
2. implement ``actuate()`` (an :class:`Actuator`), ``sense()`` (a :class:`Sensor`) or both
   (an :class:`InOut`) with :meth:`Device.write` / :meth:`Device.read`.

A malformed pinout (missing or unknown role, a pin spec that is not a pin) raises
:class:`~hilswarm.agents.errors.DeviceError` naming the device and role; a pin rule violation
(pin taken, no PWM there, ...) raises the PinManager's
:class:`~hilswarm.agents.errors.PinError`, naming the binder and thus device and role.
"""

from __future__ import annotations

import math
import re
from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any, ClassVar

from hilswarm.agents.errors import DeviceError, PinError
from hilswarm.agents.link.board import PinMode
from hilswarm.agents.pins import PinManager, parse_pin

__all__ = ["Actuator", "Device", "InOut", "Sensor", "number_option"]


def number_option(value: object, what: str, *, positive: bool = False) -> float:
    """``value`` as a finite float (``> 0`` when ``positive``), else a ``DeviceError``.

    Device options (reference voltages, pulse widths, angles) are checked with this, so a bad
    one is refused with a message naming the option and the value.
    """
    expected = "a number > 0" if positive else "a number"
    if isinstance(value, bool):
        raise DeviceError(f"{what}: expected {expected}, got {value!r}")
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise DeviceError(f"{what}: expected {expected}, got {value!r}") from None
    if not math.isfinite(number) or (positive and number <= 0):
        finite = "a finite number > 0" if positive else "a finite number"
        raise DeviceError(f"{what}: expected {finite}, got {value!r}")
    return number


_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")


class Device(ABC):
    """A named group of board pins bound through a :class:`PinManager`.

    Args:
        pins: the vehicle's PinManager.
        name: device name, unique per vehicle (letters, digits, ``_``, ``-``).
        pinout: role -> pin spec (13, ``"D13"``, ``"A0"``), exactly the device's roles.
        **options: none are accepted by the base class; subclasses take theirs as keyword
            arguments, anything left over is reported as an unknown option.

    Raises:
        DeviceError: bad name, unknown option, malformed pinout, name already in use.
        PinError: a pin rule is broken (the binder in the message names device and role).
    """

    #: Pin roles the device needs (subclasses with per-instance roles override required_roles).
    roles: ClassVar[tuple[str, ...]] = ()

    def __init__(
        self, pins: PinManager, name: str, pinout: Mapping[str, int | str], **options: Any
    ) -> None:
        kind = type(self).__name__
        if not isinstance(pins, PinManager):
            raise DeviceError(f"{kind} {name!r}: pins must be a PinManager, got {pins!r}")
        if not isinstance(name, str) or not _NAME.match(name):
            raise DeviceError(
                f"{kind}: device name must be letters, digits, '_' or '-' "
                f"(starting with a letter or '_'), got {name!r}"
            )
        if options:
            raise DeviceError(
                f"{kind} {name!r}: unknown option(s) {sorted(options)}; "
                f"see the {kind} docstring for the options it takes"
            )
        if name in pins.devices():
            raise DeviceError(
                f"{kind} {name!r}: a device of that name already holds pins "
                f"{pins.find_device(name)}; device names must be unique"
            )
        self.pins: PinManager = pins
        self.name: str = name
        self._pinout: dict[str, int] = {}
        self._binders: dict[str, str] = {}  # role -> binder of every bound role (per-tick I/O)
        parsed = self._parse_pinout(pinout)
        for role, pin in parsed.items():
            mode = self.role_mode(role)
            try:
                pins.assign(
                    pin,
                    device=name,
                    binder=self.binder(role),
                    mode=mode,
                    safe_value=self.role_safe_value(role),
                )
            except PinError:
                if self._pinout:
                    pins.release(device=name)
                    self._pinout.clear()
                    self._binders.clear()
                raise
            self._pinout[role] = pin
            self._binders[role] = self.binder(role)

    # ------------------------------------------------------------------ pinout
    def required_roles(self) -> tuple[str, ...]:
        """The pin roles this device needs (default: the class attribute ``roles``)."""
        return tuple(self.roles)

    @abstractmethod
    def role_mode(self, role: str) -> PinMode:
        """The pin mode of ``role``."""

    def role_safe_value(self, role: str) -> int:
        """Safe value of ``role`` in wire units (default 0: digital low, PWM off)."""
        return 0

    def _parse_pinout(self, pinout: Mapping[str, int | str]) -> dict[str, int]:
        kind = type(self).__name__
        if not isinstance(pinout, Mapping):
            raise DeviceError(
                f"{kind} {self.name!r}: pinout must map role -> pin, got {type(pinout).__name__}"
            )
        needed = self.required_roles()
        unknown = [role for role in pinout if role not in needed]
        if unknown:
            raise DeviceError(
                f"{kind} {self.name!r}: unknown pin role(s) {unknown}; roles are {list(needed)}"
            )
        missing = [role for role in needed if role not in pinout]
        if missing:
            raise DeviceError(
                f"{kind} {self.name!r}: pinout lacks role(s) {missing}; roles are {list(needed)}"
            )
        parsed: dict[str, int] = {}
        for role in needed:
            spec = pinout[role]
            if isinstance(spec, bool) or not isinstance(spec, int | str):
                raise DeviceError(
                    f"{kind} {self.name!r}, role {role!r}: pin {spec!r} is not a pin spec "
                    "(expected 13, 'D13' or 'A0')"
                )
            try:
                parsed[role] = parse_pin(spec, self.pins.profile)
            except PinError as exc:
                raise DeviceError(f"{kind} {self.name!r}, role {role!r}: {exc}") from None
        return parsed

    def binder(self, role: str) -> str:
        """The binder name of ``role``: ``"<device>.<role>"``."""
        return f"{self.name}.{role}"

    @property
    def pinout(self) -> dict[str, int]:
        """Role -> pin number of every bound role."""
        return dict(self._pinout)

    def pin(self, role: str) -> int:
        """The pin number bound to ``role``.

        Raises:
            DeviceError: unknown role.
        """
        try:
            return self._pinout[role]
        except KeyError:
            raise DeviceError(
                f"{type(self).__name__} {self.name!r} has no role {role!r}; "
                f"roles are {list(self._pinout)}"
            ) from None

    # ------------------------------------------------------------------ I/O
    def write(self, role: str, value: int) -> None:
        """Stage ``value`` (wire units) on ``role``'s pin (sent at the next exchange)."""
        binder = self._binders.get(role)
        if binder is None:
            self.pin(role)  # raises DeviceError naming the roles
            binder = self.binder(role)
        self.pins.write(binder, value)

    def read(self, role: str) -> int:
        """The last sample (wire units) of ``role``'s pin."""
        binder = self._binders.get(role)
        if binder is None:
            self.pin(role)  # raises DeviceError naming the roles
            binder = self.binder(role)
        return self.pins.read(binder)

    def release(self) -> None:
        """Give every pin back to the PinManager. Idempotent."""
        if self._pinout:
            self.pins.release(device=self.name)
            self._pinout.clear()
            self._binders.clear()

    def __repr__(self) -> str:
        pins = ", ".join(f"{role}={pin}" for role, pin in self._pinout.items())
        return f"{type(self).__name__}({self.name!r}, {pins})"


class Actuator(Device):
    """A device the host writes to: motors, servos, output pins."""

    @abstractmethod
    def actuate(self, *args: Any) -> Any:
        """Drive the actuator (device-specific arguments and units)."""

    def safe(self) -> None:
        """Stage the safe value of every output role (override for a device-specific safe state)."""
        for role in self._pinout:
            if self.role_mode(role).is_output:
                self.write(role, self.role_safe_value(role))


class Sensor(Device):
    """A device the host samples: batteries, switches, analog sensors."""

    @abstractmethod
    def sense(self) -> Any:
        """Convert the last samples into a measurement (device-specific units)."""


class InOut(Actuator, Sensor):
    """A device with both written and sampled pins (e.g. an ultrasonic ranger)."""

"""PinManager and board profiles: the hardware abstraction layer between devices and a board.

The :class:`PinManager` is the thesis' PinManager (§2.2.2) on top of the batched board link.
Devices bind pins to *binders* (``"<device>.<role>"``); from then on they only use the binder,
never the pin number. Every rule of the thesis is checked when a pin is bound, and every
violation raises :class:`~hilswarm.agents.errors.PinError` naming the pin, the binder, the
device and the conflict:

* the pin must exist on the board profile, and must not be one of the serial pins 0/1;
* a pin is bound to at most one binder until it is released; binder names are unique;
* an output is never read and an input is never written;
* PWM only on PWM-capable pins, servo only on servo pins, analog input only on analog pins;
* a servo on pin 9 disables PWM on pin 10 and vice versa (Timer1 makes the servo pulses), in
  whichever order the two pins are bound.

Values are staged with :meth:`PinManager.write` and sent all at once by
:meth:`PinManager.exchange`, which also samples every input pin: one board round trip per tick.
"""

from __future__ import annotations

import logging
import operator
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from hilswarm.agents.errors import BoardConnectionError, PinError, ProtocolError
from hilswarm.agents.link.board import (
    ADC_MAX,
    ANALOG_PIN_BASE,
    MODE_CAPABILITY,
    PIN_COUNT,
    PWM_MAX,
    SERVO_MAX_US,
    SERVO_MIN_US,
    Board,
    BoardInfo,
    Capability,
    PinConfig,
    PinMode,
    TickReply,
    pin_name,
)

logger = logging.getLogger(__name__)

__all__ = [
    "PROFILES",
    "BoardProfile",
    "PinAssignment",
    "PinManager",
    "describe",
    "get_profile",
    "parse_pin",
    "value_range",
]


@dataclass(frozen=True)
class BoardProfile:
    """What one kind of board offers.

    Attributes:
        name: profile name (``"uno"``, ``"duemilanove"``, ``"fio"``).
        pins: every pin number the board has (Arduino numbering, A0 = 14).
        pwm_pins: pins with hardware PWM.
        servo_pins: pins that can carry servo pulses (Timer1 outputs).
        analog_pins: pins with an ADC channel (also usable as digital pins).
        serial_pins: pins of the serial link to the host, never bindable.
        vref_v: ADC reference voltage [V] (full scale of an analog sample).
        timer1_pairs: pairs of pins sharing the timer that makes servo pulses; a servo on one
            pin of a pair disables PWM on the other.
    """

    name: str
    pins: tuple[int, ...]
    pwm_pins: frozenset[int]
    servo_pins: frozenset[int]
    analog_pins: frozenset[int]
    serial_pins: frozenset[int]
    vref_v: float
    timer1_pairs: tuple[tuple[int, int], ...] = ((9, 10),)

    def has_pin(self, pin: int) -> bool:
        """True if ``pin`` exists on this board (serial pins included)."""
        return pin in self.pins

    def timer1_partner(self, pin: int) -> int | None:
        """The pin whose PWM a servo on ``pin`` disables (and vice versa), or ``None``."""
        for a, b in self.timer1_pairs:
            if pin == a:
                return b
            if pin == b:
                return a
        return None

    def capability(self, pin: int) -> Capability:
        """The HELLO capability flags this board reports for ``pin``."""
        if pin not in self.pins:
            return Capability.NONE
        if pin in self.serial_pins:
            return Capability.RESERVED
        caps = Capability.DIGITAL_IN | Capability.DIGITAL_OUT
        if pin in self.pwm_pins:
            caps |= Capability.PWM
        if pin in self.servo_pins:
            caps |= Capability.SERVO
        if pin in self.analog_pins:
            caps |= Capability.ANALOG_IN
        return caps

    def capabilities(self) -> tuple[Capability, ...]:
        """Capability flags of pins ``0 .. PIN_COUNT-1``, as HELLO reports them."""
        return tuple(self.capability(pin) for pin in range(PIN_COUNT))


def _atmega328_profile(name: str, vref_v: float) -> BoardProfile:
    return BoardProfile(
        name=name,
        pins=tuple(range(PIN_COUNT)),
        pwm_pins=frozenset({3, 5, 6, 9, 10, 11}),
        servo_pins=frozenset({9, 10}),
        analog_pins=frozenset(range(ANALOG_PIN_BASE, PIN_COUNT)),
        serial_pins=frozenset({0, 1}),
        vref_v=vref_v,
    )


#: Board profiles by name. The Fio runs at 3.3 V, so its ADC reference is 3.3 V.
PROFILES: dict[str, BoardProfile] = {
    "uno": _atmega328_profile("uno", 5.0),
    "duemilanove": _atmega328_profile("duemilanove", 5.0),
    "fio": _atmega328_profile("fio", 3.3),
}


def get_profile(profile: BoardProfile | str) -> BoardProfile:
    """Return ``profile`` itself or the profile of that name.

    Raises:
        PinError: unknown profile name.
    """
    if isinstance(profile, BoardProfile):
        return profile
    try:
        return PROFILES[profile]
    except (KeyError, TypeError):
        raise PinError(
            f"unknown board profile {profile!r}; expected one of {', '.join(sorted(PROFILES))}"
        ) from None


_PIN_SPEC = re.compile(r"^\s*([AaDd]?)\s*(\d+)\s*$")


def parse_pin(spec: int | str, profile: BoardProfile | str = "uno") -> int:
    """Turn a pin spec into a pin number: ``13`` -> 13, ``"D13"`` -> 13, ``"A0"`` -> 14.

    Args:
        spec: a pin number, ``"D<n>"``, ``"A<n>"`` or a decimal string.
        profile: the board the pin belongs to (checked for existence).

    Raises:
        PinError: malformed spec or a pin the board lacks.
    """
    board = get_profile(profile)
    if isinstance(spec, bool):
        raise PinError(f"pin spec {spec!r} is a bool; expected 13, 'D13' or 'A0'")
    if isinstance(spec, str):
        match = _PIN_SPEC.match(spec)
        if match is None:
            raise PinError(f"malformed pin spec {spec!r}; expected 13, 'D13' or 'A0'")
        prefix, number = match.group(1).upper(), int(match.group(2))
        pin = ANALOG_PIN_BASE + number if prefix == "A" else number
        if prefix == "A" and number >= len(board.analog_pins):
            raise PinError(
                f"board {board.name!r} has no analog pin {spec!r} "
                f"(analog pins A0-A{len(board.analog_pins) - 1})"
            )
    else:
        try:
            pin = operator.index(spec)
        except TypeError:
            raise PinError(
                f"pin spec {spec!r} ({type(spec).__name__}) is not a pin; "
                "expected 13, 'D13' or 'A0'"
            ) from None
    if not board.has_pin(pin):
        raise PinError(
            f"board {board.name!r} has no pin {spec!r} "
            f"(pins {min(board.pins)}-{max(board.pins)}, A0 = {ANALOG_PIN_BASE})"
        )
    return pin


def value_range(mode: PinMode) -> tuple[int, int]:
    """Inclusive range of wire values for ``mode`` (outputs: writes; inputs: samples)."""
    if mode is PinMode.DIGITAL_OUT or mode in (PinMode.DIGITAL_IN, PinMode.DIGITAL_IN_PULLUP):
        return (0, 1)
    if mode is PinMode.PWM:
        return (0, PWM_MAX)
    if mode is PinMode.SERVO:
        return (SERVO_MIN_US, SERVO_MAX_US)
    if mode is PinMode.ANALOG_IN:
        return (0, ADC_MAX)
    raise PinError(f"pin mode {mode.name} carries no values")


@dataclass(frozen=True, slots=True)
class PinAssignment:
    """One bound pin.

    Attributes:
        pin: pin number (A0 = 14).
        device: name of the device owning the pin.
        binder: unique name the device uses for the pin (``"<device>.<role>"``).
        mode: pin mode.
        safe_value: value driven on safe mode / watchdog / e-stop, in wire units (outputs).
    """

    pin: int
    device: str
    binder: str
    mode: PinMode
    safe_value: int = 0

    @property
    def label(self) -> str:
        """``"pin D9 (binder 'servo.pin' of device 'servo', SERVO)"`` for messages."""
        return (
            f"pin {pin_name(self.pin)} (binder {self.binder!r} of device {self.device!r}, "
            f"{self.mode.name})"
        )


def _as_int_value(value: object, what: str) -> int:
    if isinstance(value, bool):
        return int(value)
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise PinError(f"{what}: value {value!r} is not an integer (wire units)") from None


class PinManager:
    """Binds board pins to binders, enforces the pin rules and batches board I/O per tick.

    Args:
        profile: board profile or its name.
    """

    def __init__(self, profile: BoardProfile | str = "uno") -> None:
        self.profile: BoardProfile = get_profile(profile)
        self._by_pin: dict[int, PinAssignment] = {}
        self._by_binder: dict[str, PinAssignment] = {}
        self._staged: dict[int, int] = {}
        self._samples: dict[int, int] | None = None
        self._board: Board | None = None
        self._watchdog_s = 0.0
        self._configured_snapshot: tuple[PinConfig, ...] | None = None
        self._last_reply: TickReply | None = None
        # Per-tick fast paths, kept up to date by assign() and release(): every rule is
        # checked once there, so write/read/exchange only look values up.
        self._layout_version = 0  # bumped by every assign() and release()
        self._attached_version = -1  # layout the board was configured with
        self._output_specs: dict[str, tuple[int, int, int]] = {}  # binder -> (pin, lo, hi)
        self._input_pins: dict[str, int] = {}  # binder -> pin
        self._reads: tuple[int, ...] = ()  # input pins sampled by exchange(), ascending

    # ------------------------------------------------------------------ binding
    def assign(
        self,
        pin: int | str,
        *,
        device: str,
        binder: str,
        mode: PinMode,
        safe_value: int = 0,
    ) -> None:
        """Bind ``pin`` to ``binder`` of ``device`` in ``mode``.

        Args:
            pin: pin spec (13, ``"D13"``, ``"A0"``).
            device: owning device name.
            binder: unique binder name (``"<device>.<role>"`` by convention).
            mode: pin mode (not ``UNUSED``).
            safe_value: safe output value in wire units (ignored for inputs, must be 0 there).

        Raises:
            PinError: any rule violation; the message names pin, binder, device and conflict.
        """
        who = f"binder {binder!r} of device {device!r}"
        if not isinstance(device, str) or not device:
            raise PinError(f"pin {pin!r} for binder {binder!r}: device name must be non-empty")
        if not isinstance(binder, str) or not binder:
            raise PinError(f"pin {pin!r} for device {device!r}: binder name must be non-empty")
        try:
            number = parse_pin(pin, self.profile)
        except PinError as exc:
            raise PinError(f"{who}: {exc}") from None
        label = pin_name(number)
        try:
            mode = PinMode(mode)
        except ValueError:
            raise PinError(f"{who}, pin {label}: unknown pin mode {mode!r}") from None
        if mode is PinMode.UNUSED:
            raise PinError(f"{who}, pin {label}: cannot bind a pin as UNUSED (release it instead)")
        if number in self.profile.serial_pins:
            raise PinError(
                f"{who}: pin {label} is reserved for the serial link to the host "
                f"(serial pins {sorted(self.profile.serial_pins)})"
            )
        if binder in self._by_binder:
            other = self._by_binder[binder]
            raise PinError(
                f"{who}, pin {label}: binder name {binder!r} is already used by "
                f"{other.label}; binder names must be unique"
            )
        if number in self._by_pin:
            other = self._by_pin[number]
            raise PinError(
                f"{who}: pin {label} is already bound to {other.label}; release it first"
            )
        self._check_capability(number, mode, who)
        self._check_timer1(number, mode, who)
        safe = self._check_safe_value(number, mode, safe_value, who)
        assignment = PinAssignment(number, device, binder, mode, safe)
        self._by_pin[number] = assignment
        self._by_binder[binder] = assignment
        if mode.is_output:
            self._staged[number] = safe
            self._output_specs[binder] = (number, *value_range(mode))
        else:
            self._input_pins[binder] = number
        self._layout_changed()
        if logger.isEnabledFor(logging.DEBUG):
            logger.debug("bound %s", assignment.label)

    def _layout_changed(self) -> None:
        self._layout_version += 1
        self._reads = tuple(sorted(self._input_pins.values()))

    def _check_capability(self, pin: int, mode: PinMode, who: str) -> None:
        label = pin_name(pin)
        if mode is PinMode.PWM and pin not in self.profile.pwm_pins:
            raise PinError(
                f"{who}: pin {label} has no PWM on board {self.profile.name!r} "
                f"(PWM pins {sorted(self.profile.pwm_pins)})"
            )
        if mode is PinMode.SERVO and pin not in self.profile.servo_pins:
            raise PinError(
                f"{who}: pin {label} cannot drive a servo on board {self.profile.name!r} "
                f"(servo pins {sorted(self.profile.servo_pins)})"
            )
        if mode is PinMode.ANALOG_IN and pin not in self.profile.analog_pins:
            raise PinError(
                f"{who}: pin {label} has no analog input on board {self.profile.name!r} "
                f"(analog pins {', '.join(pin_name(p) for p in sorted(self.profile.analog_pins))})"
            )

    def _check_timer1(self, pin: int, mode: PinMode, who: str) -> None:
        partner = self.profile.timer1_partner(pin)
        if partner is None or partner not in self._by_pin:
            return
        other = self._by_pin[partner]
        if mode is PinMode.PWM and other.mode is PinMode.SERVO:
            raise PinError(
                f"{who}: no PWM on pin {pin_name(pin)}: {other.label} drives a servo and "
                f"Timer1 servo pulses disable PWM on pin {pin_name(pin)}"
            )
        if mode is PinMode.SERVO and other.mode is PinMode.PWM:
            raise PinError(
                f"{who}: no servo on pin {pin_name(pin)}: {other.label} uses PWM and a servo "
                f"on pin {pin_name(pin)} would disable PWM on pin {pin_name(partner)} (Timer1)"
            )

    def _check_safe_value(self, pin: int, mode: PinMode, safe_value: object, who: str) -> int:
        what = f"{who}, pin {pin_name(pin)} ({mode.name}) safe value"
        value = _as_int_value(safe_value, what)
        if not mode.is_output:
            if value != 0:
                raise PinError(f"{what}: inputs have no safe value, got {value}")
            return 0
        lo, hi = value_range(mode)
        if not lo <= value <= hi:
            raise PinError(f"{what}: {value} is outside {lo}..{hi}")
        return value

    def release(self, *, binder: str | None = None, device: str | None = None) -> None:
        """Release one binder's pin, or every pin of a device (exactly one of the two).

        Raises:
            PinError: neither or both given, or nothing bound under that name.
        """
        if (binder is None) == (device is None):
            raise PinError("release() needs exactly one of binder= or device=")
        if binder is not None:
            if binder not in self._by_binder:
                raise PinError(f"cannot release binder {binder!r}: no pin is bound to it")
            victims = [self._by_binder[binder]]
        else:
            victims = [a for a in self._by_pin.values() if a.device == device]
            if not victims:
                raise PinError(f"cannot release device {device!r}: no pin is bound to it")
        for assignment in victims:
            del self._by_pin[assignment.pin]
            del self._by_binder[assignment.binder]
            self._output_specs.pop(assignment.binder, None)
            self._input_pins.pop(assignment.binder, None)
            self._staged.pop(assignment.pin, None)
            if self._samples is not None:
                self._samples.pop(assignment.pin, None)
            logger.debug("released %s", assignment.label)
        self._layout_changed()

    # ------------------------------------------------------------------ lookups
    def is_assigned(self, pin: int | str) -> bool:
        """True if ``pin`` (13, ``"D13"``, ``"A0"``) is bound to a binder."""
        return parse_pin(pin, self.profile) in self._by_pin

    def assignment_of(self, pin: int | str) -> PinAssignment:
        """The assignment holding ``pin``.

        Raises:
            PinError: the pin is not bound.
        """
        number = parse_pin(pin, self.profile)
        try:
            return self._by_pin[number]
        except KeyError:
            raise PinError(f"pin {pin_name(number)} is not bound to any binder") from None

    def find_device(self, device: str) -> dict[str, int]:
        """Binder -> pin of every pin bound by ``device``.

        Raises:
            PinError: no pin is bound to that device.
        """
        found = {a.binder: a.pin for a in self._by_pin.values() if a.device == device}
        if not found:
            known = sorted(self.devices())
            raise PinError(f"no pins are bound to device {device!r}; devices: {known}")
        return found

    def find_binder(self, binder: str) -> PinAssignment:
        """The assignment (pin, device, binder, mode, safe value) of ``binder``.

        Raises:
            PinError: unknown binder.
        """
        try:
            return self._by_binder[binder]
        except (KeyError, TypeError):
            raise PinError(
                f"unknown binder {binder!r}; binders: {sorted(self._by_binder)}"
            ) from None

    def used_pins(self) -> list[int]:
        """Every bound pin number, ascending."""
        return sorted(self._by_pin)

    def devices(self) -> list[str]:
        """Names of every device holding at least one pin, in binding order."""
        return list(dict.fromkeys(a.device for a in self._by_binder.values()))

    def assignments(self) -> list[PinAssignment]:
        """Every assignment, by ascending pin."""
        return [self._by_pin[pin] for pin in sorted(self._by_pin)]

    def pin_configs(self) -> list[PinConfig]:
        """The board configuration of every bound pin (ascending pin)."""
        return [PinConfig(a.pin, a.mode, a.safe_value) for a in self.assignments()]

    # ------------------------------------------------------------------ values
    def write(self, binder: str, value: int) -> None:
        """Stage ``value`` (wire units) for the output bound to ``binder``; sent by exchange().

        Raises:
            PinError: unknown binder, binder is an input, or value out of range for the mode
                (digital 0/1, PWM 0-255, servo 500-2500 µs).
        """
        spec = self._output_specs.get(binder)
        if spec is not None and type(value) is int:  # common case; anything else: full checks
            pin, lo, hi = spec
            if lo <= value <= hi:
                self._staged[pin] = value
                return
        assignment = self.find_binder(binder)
        if not assignment.mode.is_output:
            raise PinError(f"cannot write {assignment.label}: it is an input")
        number = _as_int_value(value, f"write to {assignment.label}")
        lo, hi = value_range(assignment.mode)
        if not lo <= number <= hi:
            raise PinError(f"write to {assignment.label}: value {number} is outside {lo}..{hi}")
        self._staged[assignment.pin] = number

    def staged(self, binder: str) -> int:
        """The value currently staged for the output ``binder`` (wire units)."""
        assignment = self.find_binder(binder)
        if not assignment.mode.is_output:
            raise PinError(f"{assignment.label} is an input: it has no staged value")
        return self._staged[assignment.pin]

    def read(self, binder: str) -> int:
        """The sample (wire units) of the input ``binder`` taken by the last exchange().

        Raises:
            PinError: unknown binder, binder is an output, or no exchange has sampled it yet.
        """
        pin = self._input_pins.get(binder)
        if pin is not None and self._samples is not None:
            value = self._samples.get(pin)
            if value is not None:
                return value
        assignment = self.find_binder(binder)
        if assignment.mode.is_output:
            raise PinError(f"cannot read {assignment.label}: it is an output")
        if self._samples is None or assignment.pin not in self._samples:
            raise PinError(f"no sample of {assignment.label} yet: exchange() with the board first")
        return self._samples[assignment.pin]

    def drive_safe(self) -> None:
        """Stage every output's safe value (sent by the next exchange())."""
        for assignment in self._by_pin.values():
            if assignment.mode.is_output:
                self._staged[assignment.pin] = assignment.safe_value

    @property
    def outputs(self) -> dict[int, int]:
        """Staged value of every output, by pin (wire units)."""
        return dict(sorted(self._staged.items()))

    # ------------------------------------------------------------------ board
    @property
    def board(self) -> Board | None:
        """The attached board, or ``None``."""
        return self._board

    @property
    def last_reply(self) -> TickReply | None:
        """The reply of the last exchange (or ``None``)."""
        return self._last_reply

    def attach(self, board: Board, *, watchdog_s: float) -> BoardInfo:
        """Open ``board``, check it can do what every bound pin needs, and configure it.

        Args:
            board: the board to drive (opened here).
            watchdog_s: link watchdog timeout [s]; 0 disables it.

        Raises:
            PinError: the board lacks a capability a bound pin needs (names pin and capability).
        """
        info = board.open()
        caps = info.capabilities
        for assignment in self.assignments():
            needed = MODE_CAPABILITY[assignment.mode]
            have = caps[assignment.pin] if assignment.pin < len(caps) else Capability.NONE
            if Capability.RESERVED in have or needed not in have:
                raise PinError(
                    f"board {board.url!r} (id {info.board_id}) cannot serve {assignment.label}: "
                    f"pin {pin_name(assignment.pin)} reports {have!r}, needs {needed.name}"
                )
        configs = self.pin_configs()
        board.configure(configs, watchdog_s=watchdog_s)
        self._board = board
        self._watchdog_s = watchdog_s
        self._configured_snapshot = tuple(configs)
        self._attached_version = self._layout_version
        self._samples = None
        return info

    def detach(self) -> None:
        """Forget the board (does not close it)."""
        self._board = None
        self._configured_snapshot = None
        self._attached_version = -1

    def _require_board(self) -> Board:
        board = self._board
        if board is not None and self._attached_version == self._layout_version:
            return board  # nothing was bound or released since attach()
        if board is None:
            raise BoardConnectionError("no board attached to the PinManager: call attach() first")
        if self._configured_snapshot != tuple(self.pin_configs()):
            raise PinError(
                "pin assignments changed since attach(): call attach() again to reconfigure "
                f"board {board.url!r}"
            )
        self._attached_version = self._layout_version  # bound and released back: same layout
        return board

    def exchange(self) -> TickReply:
        """Send every output's staged value and sample every input, in one board exchange.

        Raises:
            BoardConnectionError: no board attached.
            PinError: pins were bound or released since attach().
            ProtocolError: the reply lacks a sample that was asked for.
        """
        board = self._board
        if board is None or self._attached_version != self._layout_version:
            board = self._require_board()  # raises, or accepts an unchanged layout
        reads = self._reads
        reply = board.exchange(dict(self._staged), reads)
        samples = reply.samples
        try:
            self._samples = {pin: int(samples[pin]) for pin in reads}
        except KeyError:
            missing = [pin_name(pin) for pin in reads if pin not in samples]
            raise ProtocolError(
                f"board {board.url!r} reply {reply.seq} lacks samples of pins {missing}"
            ) from None
        self._last_reply = reply
        return reply

    def estop(self) -> TickReply | None:
        """Stage safe values and, with a board attached, e-stop it now (latched on the board)."""
        self.drive_safe()
        if self._board is None:
            return None
        return self._board.estop()

    def samples(self) -> Mapping[int, int]:
        """Samples of the last exchange by pin (empty before any exchange)."""
        return dict(self._samples or {})

    def __repr__(self) -> str:
        return f"PinManager({self.profile.name!r}, pins={self.used_pins()})"


def describe(assignments: Sequence[PinAssignment]) -> str:
    """Multi-line human table of assignments (for ``hilswarm check``)."""
    return "\n".join(
        f"{pin_name(a.pin):>4}  {a.mode.name:<17} {a.binder}  (safe {a.safe_value})"
        for a in assignments
    )

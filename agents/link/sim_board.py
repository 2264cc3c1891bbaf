"""``sim://`` — an in-process simulated board with the firmware's semantics, only stricter.

:class:`SimBoard` answers the same requests as the hilswarm firmware (``docs/protocol.md``)
without any bytes on a wire. It applies the same checks and raises
:class:`~hilswarm.agents.errors.BoardRequestError` with the :class:`ErrorCode` the firmware would
send, and refuses a few things the wire cannot even express (values the codec could not encode,
duplicate reads). It keeps its own board clock: every :meth:`SimBoard.exchange` advances it by
``dt``; :meth:`SimBoard.advance_time` lets tests model link silence. The link watchdog and the
e-stop latch are modelled against that clock.

A :class:`PinPlant` closes the loop: on each exchange the board applies the writes, calls
``plant.advance(outputs, dt)`` (outputs in wire units by pin) and samples the analog voltages
the plant returns: ``counts = round(volts / vref_v * 1023)``, clipped to 0..1023.

Watchdog model: with ``watchdog_s > 0`` the outputs go to their safe values at the moment the
silence since the last valid frame (HELLO, CONFIG, TICK, ESTOP) *exceeds* ``watchdog_s``. With
exchanges every ``dt`` the silence is ``dt``, so ``dt > watchdog_s`` trips on every tick, as it
would on hardware. A TICK after a trip writes the outputs again and its reply reports
``WATCHDOG_TRIPPED`` once.
"""

from __future__ import annotations

import logging
import math
import operator
from collections.abc import Mapping, Sequence
from typing import Any, Protocol, runtime_checkable
from urllib.parse import parse_qsl, urlsplit

import numpy as np
from hilswarm.agents.errors import (
    BoardConnectionError,
    BoardRequestError,
    LinkUrlError,
    PlantError,
)
from hilswarm.agents.link.board import (
    ADC_MAX,
    PIN_COUNT,
    PROTOCOL_VERSION,
    Board,
    BoardInfo,
    BoardStatus,
    Capability,
    ErrorCode,
    PinConfig,
    PinMode,
    TickReply,
    pin_name,
)
from hilswarm.agents.pins import PROFILES, BoardProfile, get_profile, parse_pin, value_range

logger = logging.getLogger(__name__)

__all__ = ["SIM_FIRMWARE_VERSION", "PinPlant", "SimBoard", "board_from_url"]

#: Firmware version the simulated board reports in HELLO.
SIM_FIRMWARE_VERSION = (1, 0)
#: Largest watchdog timeout the CONFIG message can carry [ms] (u16).
WATCHDOG_MAX_MS = 0xFFFF


@runtime_checkable
class PinPlant(Protocol):
    """A physical model around a board's pins.

    ``advance(outputs, dt)`` gets every output pin's wire value (digital 0/1, PWM duty 0-255,
    servo pulse [µs]) held during the next ``dt`` [s], advances the model by ``dt`` and returns
    the voltage [V] on input pins by pin number (pins not returned keep their last voltage).
    ``pose()`` returns ``[x, y, z (m, world frame), roll, pitch, yaw (rad)]``.
    """

    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        """Advance by ``dt`` [s] with ``outputs`` held; return input voltages [V] by pin."""
        ...

    def pose(self) -> np.ndarray:
        """Current pose ``[x, y, z (m, world), roll, pitch, yaw (rad)]``."""
        ...


def _refuse(code: ErrorCode, message: str, pin: int | None = None) -> BoardRequestError:
    where = f" (pin {pin_name(pin)})" if pin is not None and 0 <= pin < PIN_COUNT else ""
    return BoardRequestError(f"{code.name}{where}: {message}", code=int(code), pin=pin)


def _as_pin(value: object) -> int | None:
    if isinstance(value, bool):
        return None
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        return None


def _is_real(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _mode_range(mode: PinMode) -> tuple[int, int]:
    """Wire values a pin in ``mode`` takes: an output's write range, anything for the rest."""
    if mode.is_output:
        return value_range(mode)
    return (0, 0xFFFF)  # inputs and unused pins: the u16 safe field is ignored


class SimBoard(Board):
    """An in-process board with the firmware's semantics (see the module docstring).

    Args:
        profile: board profile name or :class:`~hilswarm.agents.pins.BoardProfile`
            (capabilities and ADC reference voltage).
        plant: optional model closing the loop around the pins.
        dt: board time advanced per exchange [s] (the control period), > 0.
        board_id: id reported by HELLO (0-65535).
        url: URL reported in messages and recordings.
    """

    def __init__(
        self,
        profile: BoardProfile | str = "uno",
        *,
        plant: PinPlant | None = None,
        dt: float,
        board_id: int = 0,
        url: str = "sim://",
    ) -> None:
        try:
            self.profile = get_profile(profile)
        except ValueError as exc:
            raise LinkUrlError(f"sim board {url!r}: {exc}") from None
        if not _is_real(dt) or dt <= 0:
            raise LinkUrlError(f"sim board {url!r}: dt must be a finite time > 0 [s], got {dt!r}")
        board_number = _as_pin(board_id)
        if board_number is None or not 0 <= board_number <= 0xFFFF:
            raise LinkUrlError(f"sim board {url!r}: board_id must be 0-65535, got {board_id!r}")
        if plant is not None and not isinstance(plant, PinPlant):
            raise LinkUrlError(
                f"sim board {url!r}: plant {plant!r} lacks advance(outputs, dt) and pose()"
            )
        self.url = url
        self.plant = plant
        self.dt = float(dt)
        self.board_id = board_number
        self._capabilities: tuple[Capability, ...] = self.profile.capabilities()
        self._open = False
        self._info: BoardInfo | None = None
        self._time_s = 0.0
        self._boot_time_s = 0.0
        self._seq = 0
        self._exchanges = 0
        self._volts: dict[int, float] = {}
        self._digital_levels: dict[int, int] = {}
        self._boot(hw_watchdog=False)

    # ------------------------------------------------------------------ state
    def _boot(self, *, hw_watchdog: bool) -> None:
        self._config: dict[int, PinConfig] | None = None
        # Per-configuration tables of the TICK fast path (see _tick_fast_checks).
        self._write_ranges: dict[int, tuple[int, int]] = {}
        self._input_pins: frozenset[int] = frozenset()
        self._outputs: dict[int, int] = {}
        self._watchdog_s = 0.0
        self._last_frame_s = self._time_s
        self._watchdog_armed = False
        self._estopped = False
        self._events = BoardStatus.OK
        self._boot_flags = BoardStatus.RESET
        if hw_watchdog:
            self._boot_flags |= BoardStatus.HW_WATCHDOG_RESET
        self._boot_time_s = self._time_s

    @property
    def status(self) -> BoardStatus:
        """Current flags (latched and pending events), without consuming the events."""
        flags = self._boot_flags | self._events
        if self._estopped:
            flags |= BoardStatus.ESTOPPED
        if self._config is None:
            flags |= BoardStatus.NOT_CONFIGURED
        return flags

    def _take_status(self) -> BoardStatus:
        if not (self._events or self._boot_flags or self._estopped) and self._config is not None:
            return BoardStatus.OK  # the common reply: nothing to report
        flags = self.status
        self._events = BoardStatus.OK  # WATCHDOG_TRIPPED and RX_ERRORS are reported once
        return flags

    @property
    def board_time_s(self) -> float:
        """Board clock [s since the last boot]."""
        return self._time_s - self._boot_time_s

    @property
    def time_s(self) -> float:
        """Simulated time since the SimBoard was created [s] (does not restart on reboot)."""
        return self._time_s

    @property
    def outputs(self) -> dict[int, int]:
        """Current wire value of every configured output, by pin (ascending)."""
        return dict(sorted(self._outputs.items()))

    @property
    def configuration(self) -> dict[int, PinConfig]:
        """The configured pins (empty before CONFIG)."""
        return dict(sorted((self._config or {}).items()))

    @property
    def watchdog_s(self) -> float:
        """Configured link watchdog timeout [s] (0 = disabled), at the wire's 1 ms resolution."""
        return self._watchdog_s

    @property
    def estopped(self) -> bool:
        """True while the e-stop is latched."""
        return self._estopped

    @property
    def exchange_count(self) -> int:
        """Number of TICK exchanges accepted so far."""
        return self._exchanges

    def _require_open(self) -> None:
        if not self._open:
            raise BoardConnectionError(f"sim board {self.url!r} is not open: call open() first")

    def _next_seq(self) -> int:
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFF
        return seq

    def _frame_received(self) -> None:
        self._last_frame_s = self._time_s
        self._watchdog_armed = self._config is not None and self._watchdog_s > 0

    # ------------------------------------------------------------------ Board API
    def open(self) -> BoardInfo:
        """HELLO: report protocol version, firmware version, id and capabilities."""
        self._open = True
        self._next_seq()
        self._info = BoardInfo(
            protocol_version=PROTOCOL_VERSION,
            firmware_version=SIM_FIRMWARE_VERSION,
            board_id=self.board_id,
            capabilities=self._capabilities,
        )
        self._boot_flags = BoardStatus.OK  # HELLO clears RESET and HW_WATCHDOG_RESET
        self._frame_received()
        return self._info

    @property
    def info(self) -> BoardInfo:
        """The last HELLO result."""
        if self._info is None:
            raise BoardConnectionError(f"sim board {self.url!r} has not been opened")
        return self._info

    def configure(self, pins: Sequence[PinConfig], *, watchdog_s: float) -> None:
        """CONFIG: validate the whole request like the firmware, then replace the configuration.

        Raises:
            BoardRequestError: BAD_LENGTH, BAD_PIN (out of range, reserved, listed twice),
                BAD_MODE (unknown mode or missing capability), PIN_CONFLICT (servo on one
                Timer1 pin with PWM on the other), BAD_VALUE (safe value or watchdog out of
                range). Nothing changes when a request is refused.
        """
        self._require_open()
        self._next_seq()
        self._frame_received()  # like the firmware: any checked frame feeds the watchdog
        watchdog_ms = self._check_watchdog(watchdog_s)
        entries = list(pins)
        if len(entries) > PIN_COUNT:
            raise _refuse(ErrorCode.BAD_LENGTH, f"{len(entries)} pins listed, at most {PIN_COUNT}")
        for index, entry in enumerate(entries):
            if not isinstance(entry, PinConfig):
                raise _refuse(ErrorCode.BAD_LENGTH, f"entry {index} is not a PinConfig: {entry!r}")
        seen: set[int] = set()
        for entry in entries:
            pin = _as_pin(entry.pin)
            if pin is None or not 0 <= pin < PIN_COUNT:
                raise _refuse(
                    ErrorCode.BAD_PIN, f"no pin {entry.pin!r} (pins 0-{PIN_COUNT - 1})", pin
                )
            if Capability.RESERVED in self._capabilities[pin]:
                raise _refuse(ErrorCode.BAD_PIN, "pin is reserved (serial link)", pin)
            if pin in seen:
                raise _refuse(ErrorCode.BAD_PIN, "pin listed twice in CONFIG", pin)
            seen.add(pin)
        modes: dict[int, PinMode] = {}
        for entry in entries:
            try:
                mode = PinMode(entry.mode)
            except ValueError:
                raise _refuse(
                    ErrorCode.BAD_MODE, f"unknown mode {entry.mode!r}", entry.pin
                ) from None
            needed = _MODE_NEEDS.get(mode)
            if needed is not None and needed not in self._capabilities[entry.pin]:
                raise _refuse(
                    ErrorCode.BAD_MODE,
                    f"mode {mode.name} needs {needed.name}, pin has "
                    f"{self._capabilities[entry.pin]!r}",
                    entry.pin,
                )
            modes[entry.pin] = mode
        for pin, mode in modes.items():
            partner = self.profile.timer1_partner(pin)
            if mode is PinMode.SERVO and partner is not None and modes.get(partner) is PinMode.PWM:
                raise _refuse(
                    ErrorCode.PIN_CONFLICT,
                    f"SERVO on {pin_name(pin)} with PWM on {pin_name(partner)} (Timer1)",
                    partner,
                )
        for entry in entries:
            lo, hi = _mode_range(modes[entry.pin])
            value = _as_pin(entry.safe_value)
            if value is None or not lo <= value <= hi:
                raise _refuse(
                    ErrorCode.BAD_VALUE,
                    f"safe value {entry.safe_value!r} outside {lo}..{hi} for "
                    f"{modes[entry.pin].name}",
                    entry.pin,
                )
        self._config = {
            entry.pin: PinConfig(entry.pin, modes[entry.pin], int(entry.safe_value))
            for entry in entries
            if modes[entry.pin] is not PinMode.UNUSED
        }
        self._outputs = {
            pin: config.safe_value for pin, config in self._config.items() if config.mode.is_output
        }
        self._write_ranges = {
            pin: _mode_range(config.mode)
            for pin, config in self._config.items()
            if config.mode.is_output
        }
        self._input_pins = frozenset(
            pin for pin, config in self._config.items() if config.mode.is_input
        )
        self._watchdog_s = watchdog_ms / 1000.0
        self._estopped = False
        self._take_status()  # the CONFIG reply carries (and consumes) the status
        self._frame_received()
        logger.debug(
            "%s configured %d pins, watchdog %d ms", self.url, len(self._config), watchdog_ms
        )

    def _check_watchdog(self, watchdog_s: float) -> int:
        if not _is_real(watchdog_s) or watchdog_s < 0:
            raise _refuse(ErrorCode.BAD_VALUE, f"watchdog_s must be >= 0 [s], got {watchdog_s!r}")
        watchdog_ms = round(watchdog_s * 1000.0)
        if watchdog_ms > WATCHDOG_MAX_MS:
            raise _refuse(
                ErrorCode.BAD_VALUE,
                f"watchdog_s {watchdog_s} s exceeds {WATCHDOG_MAX_MS / 1000} s (u16 milliseconds)",
            )
        return watchdog_ms

    def exchange(self, writes: Mapping[int, int], reads: Sequence[int]) -> TickReply:
        """TICK: validate, apply ``writes`` (unless e-stopped), advance ``dt``, sample ``reads``.

        Raises:
            BoardRequestError: NOT_CONFIGURED, BAD_PIN (write to a pin that is not a configured
                output, read of a pin that is not a configured input, a pin read twice),
                BAD_VALUE (value outside the mode's range: 0/1, 0-255, 500-2500 µs).
        """
        if not self._open:
            self._require_open()
        seq = self._next_seq()
        self._frame_received()  # like the firmware: a refused request still feeds the watchdog
        if self._config is None:
            raise _refuse(ErrorCode.NOT_CONFIGURED, "TICK before any CONFIG")
        fast = self._tick_fast_checks(writes, reads)
        if fast is None:
            checked, read_pins = self._tick_checks(writes, reads)
        else:
            checked, read_pins = fast
        if not self._estopped:
            self._outputs.update(checked)
        self._exchanges += 1
        self._frame_received()
        self._advance(self.dt)
        samples = {pin: self._sample(pin) for pin in read_pins}
        return TickReply(seq, self._take_status(), self.board_time_s, samples)

    def _tick_fast_checks(
        self, writes: Mapping[int, int], reads: Sequence[int]
    ) -> tuple[Mapping[int, int], list[int]] | None:
        """The TICK checks for a request that passes them all (the common case), or ``None``.

        Every write goes to a configured output with an ``int`` value in its mode's range, every
        read to a configured input, none twice: then the request is valid and its writes and
        (sorted) reads are returned. Anything else, or anything unusual (bool or numpy
        numbers), returns ``None`` and :meth:`_tick_checks` decides, with the firmware's order
        of checks and error codes.
        """
        ranges = self._write_ranges
        for pin, value in writes.items():
            bounds = ranges.get(pin)
            if bounds is None or type(pin) is not int or type(value) is not int:
                return None
            if not bounds[0] <= value <= bounds[1]:
                return None
        inputs = self._input_pins
        for pin in reads:
            if type(pin) is not int or pin not in inputs:
                return None
        read_pins = sorted(reads)
        for i in range(1, len(read_pins)):
            if read_pins[i] == read_pins[i - 1]:
                return None
        return writes, read_pins

    def _tick_checks(
        self, writes: Mapping[int, int], reads: Sequence[int]
    ) -> tuple[Mapping[int, int], list[int]]:
        """Check a TICK request like the firmware; return its writes and sorted reads."""
        config = self._config
        if config is None:  # exchange() checked it; keep the type checker calm
            raise _refuse(ErrorCode.NOT_CONFIGURED, "TICK before any CONFIG")
        # Same order as the firmware: dout bits, then rmask, then PWM/servo writes.
        checked: dict[int, int] = {}
        later: list[tuple[int | None, object]] = []
        for raw_pin, raw_value in writes.items():
            pin = _as_pin(raw_pin)
            entry = config.get(pin) if pin is not None else None
            if entry is None or entry.mode is not PinMode.DIGITAL_OUT:
                later.append((pin, raw_value))
                continue
            value = _as_pin(raw_value)
            if value is None or value not in (0, 1):
                raise _refuse(ErrorCode.BAD_VALUE, f"digital level {raw_value!r} is not 0/1", pin)
            checked[entry.pin] = value
        read_pins: list[int] = []
        for raw_pin in reads:
            pin = _as_pin(raw_pin)
            entry = config.get(pin) if pin is not None else None
            if entry is None or not entry.mode.is_input:
                what = "unconfigured" if entry is None else entry.mode.name
                raise _refuse(ErrorCode.BAD_PIN, f"read of a pin that is {what}", pin)
            if entry.pin in read_pins:
                raise _refuse(ErrorCode.BAD_PIN, "pin read twice in one TICK", entry.pin)
            read_pins.append(entry.pin)
        for pin, raw_value in later:
            entry = config.get(pin) if pin is not None else None
            if entry is None or not entry.mode.is_output:
                what = "unconfigured" if entry is None else entry.mode.name
                raise _refuse(ErrorCode.BAD_PIN, f"write to a pin that is {what}", pin)
            value = _as_pin(raw_value)
            lo, hi = _mode_range(entry.mode)
            if value is None or not lo <= value <= hi:
                raise _refuse(
                    ErrorCode.BAD_VALUE,
                    f"value {raw_value!r} outside {lo}..{hi} for {entry.mode.name}",
                    pin,
                )
            checked[entry.pin] = value
        return checked, sorted(read_pins)

    def estop(self) -> TickReply:
        """ESTOP: drive every output safe now and latch until the next configure()."""
        self._require_open()
        seq = self._next_seq()
        self._estopped = True
        self._drive_safe()
        self._frame_received()
        return TickReply(seq, self._take_status(), self.board_time_s, {})

    def close(self) -> None:
        """Release the (simulated) link. Idempotent; the board keeps its state like hardware."""
        self._open = False

    # ------------------------------------------------------------------ time, plant, samples
    def advance_time(self, seconds: float) -> None:
        """Let ``seconds`` of board time pass without any frame (link silence).

        The plant keeps running with the outputs held (in steps of at most ``dt``) and the
        watchdog trips at the exact moment the silence exceeds its timeout.
        """
        if not _is_real(seconds) or seconds < 0:
            raise ValueError(f"advance_time: seconds must be finite and >= 0, got {seconds!r}")
        self._advance(float(seconds))

    def _advance(self, seconds: float) -> None:
        remaining = seconds
        # Every pass consumes a step (exactly the remainder at the end), or trips the
        # watchdog, which happens at most once until the next frame: the loop ends.
        while remaining > 0.0:
            step = min(self.dt, remaining)
            if self._watchdog_armed:
                trip_at = self._last_frame_s + self._watchdog_s
                if trip_at < self._time_s + step:
                    before = min(max(trip_at - self._time_s, 0.0), remaining)
                    if before > 0.0:
                        self._step_plant(before)
                        remaining -= before
                    self._trip_watchdog()
                    continue
            self._step_plant(step)
            remaining -= step

    def _trip_watchdog(self) -> None:
        self._watchdog_armed = False
        self._drive_safe()
        self._events |= BoardStatus.WATCHDOG_TRIPPED
        logger.info(
            "%s link watchdog tripped at board time %.3f s: outputs safe",
            self.url,
            self.board_time_s,
        )

    def _drive_safe(self) -> None:
        for pin, entry in (self._config or {}).items():
            if entry.mode.is_output:
                self._outputs[pin] = entry.safe_value

    def _step_plant(self, step: float) -> None:
        if self.plant is not None:
            volts = self.plant.advance(dict(self._outputs), step)
            for pin, value in volts.items():
                if (
                    type(pin) is int
                    and 0 <= pin < PIN_COUNT
                    and type(value) is float
                    and math.isfinite(value)
                ):  # the common case: checked without conversions
                    self._volts[pin] = value
                    continue
                number = _as_pin(pin)
                volt = float(value)
                if number is None or not 0 <= number < PIN_COUNT:
                    raise PlantError(f"plant {self.plant!r} returned a voltage for no pin {pin!r}")
                if not math.isfinite(volt):
                    raise PlantError(
                        f"plant {self.plant!r} returned {value!r} V for pin {pin_name(number)}"
                    )
                self._volts[number] = volt
        self._time_s += step

    def _sample(self, pin: int) -> int:
        mode = self._config[pin].mode if self._config else PinMode.UNUSED
        vref = self.profile.vref_v
        if mode is PinMode.ANALOG_IN:
            counts = round(self._volts.get(pin, 0.0) / vref * ADC_MAX)
            return min(max(counts, 0), ADC_MAX)
        if pin in self._digital_levels:
            return self._digital_levels[pin]
        if pin in self._volts:
            return 1 if self._volts[pin] >= vref / 2 else 0
        return 1 if mode is PinMode.DIGITAL_IN_PULLUP else 0

    # ------------------------------------------------------------------ test hooks
    def set_analog_input(self, pin: int | str, volts: float) -> None:
        """Put ``volts`` [V] on ``pin`` (13, ``"A0"``) until the plant reports another voltage.

        Raises:
            ValueError: unknown pin or non-finite voltage.
        """
        number = parse_pin(pin, self.profile)
        if not _is_real(volts):
            raise ValueError(
                f"set_analog_input: voltage for pin {pin!r} must be finite, got {volts!r}"
            )
        self._volts[number] = float(volts)

    def set_digital_input(self, pin: int | str, level: int | bool) -> None:
        """Hold the digital input ``pin`` (13, ``"A0"``) at ``level`` (0/1) for later samples.

        Raises:
            ValueError: unknown pin or a level other than 0/1.
        """
        number = parse_pin(pin, self.profile)
        if level not in (0, 1):
            raise ValueError(f"set_digital_input: level for pin {pin!r} must be 0/1, got {level!r}")
        self._digital_levels[number] = int(level)

    def power_cycle(self, *, hw_watchdog: bool = False) -> None:
        """Reboot: configuration lost, board clock restarts, RESET (and HW_WATCHDOG_RESET)."""
        self._boot(hw_watchdog=hw_watchdog)

    def __repr__(self) -> str:
        return f"SimBoard({self.profile.name!r}, url={self.url!r}, dt={self.dt})"


_MODE_NEEDS: dict[PinMode, Capability] = {
    PinMode.DIGITAL_IN: Capability.DIGITAL_IN,
    PinMode.DIGITAL_IN_PULLUP: Capability.DIGITAL_IN,
    PinMode.DIGITAL_OUT: Capability.DIGITAL_OUT,
    PinMode.PWM: Capability.PWM,
    PinMode.SERVO: Capability.SERVO,
    PinMode.ANALOG_IN: Capability.ANALOG_IN,
}


def parse_url(url: str) -> tuple[str, dict[str, Any]]:
    """Parse ``sim://[profile][?board_id=N]`` into ``(profile, options)`` without building.

    Raises:
        LinkUrlError: wrong scheme, unknown profile or query key, bad board id.
    """
    parts = urlsplit(url)
    if parts.scheme.lower() != "sim":
        raise LinkUrlError(f"{url!r} is not a sim:// URL")
    profile = (parts.netloc or parts.path.strip("/") or "uno").lower()
    if profile not in PROFILES:
        raise LinkUrlError(
            f"{url!r}: unknown board profile {profile!r}; known: {', '.join(sorted(PROFILES))}"
        )
    options: dict[str, Any] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key != "board_id":
            raise LinkUrlError(f"{url!r}: unknown option {key!r} (known: board_id)")
        if key in options:
            raise LinkUrlError(f"{url!r}: option {key!r} given twice")
        if not value.isdigit() or not 0 <= int(value) <= 0xFFFF:
            raise LinkUrlError(f"{url!r}: board_id must be an integer 0-65535, got {value!r}")
        options[key] = int(value)
    return profile, options


def validate_url(url: str, *, local: bool = True) -> None:
    """Check ``url`` as :func:`board_from_url` would (``local`` changes nothing here)."""
    del local
    parse_url(url)


def board_from_url(url: str, **options: Any) -> SimBoard:
    """Build a :class:`SimBoard` from ``sim://[profile][?board_id=N]``.

    ``options`` go to :class:`SimBoard` (``plant=``, ``dt=``, ...).

    Raises:
        LinkUrlError: wrong scheme, unknown profile or query key, bad board id.
    """
    profile, from_url = parse_url(url)
    if "board_id" in from_url and "board_id" in options:
        raise LinkUrlError(f"{url!r}: board_id given both in the URL and as an option")
    if "profile" in options:
        raise LinkUrlError(f"{url!r}: give the profile in the URL (sim://<profile>), not as option")
    return SimBoard(profile, url=url, **from_url, **options)

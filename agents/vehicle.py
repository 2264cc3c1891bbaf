"""The Vehicle contract: the thesis' DSSLVehicle (§2.1.2, §2.2.4, appendix A.2) in Python.

A vehicle is a collection of devices on one board plus the glue between a controller's vectors
and those devices. A concrete vehicle declares, as class attributes, its sizes and names
(``n_inputs``, ``n_outputs``, ``input_names``, ``output_names``), its board ``profile`` and
``default_pinout`` (device -> role -> pin), and implements three methods:

* :meth:`Vehicle.setup_devices` — build the devices (usually with :meth:`Vehicle.add_device`);
* :meth:`Vehicle.read_outputs` — devices (and pose) -> output vector ``y``;
* :meth:`Vehicle.actuate` — input vector ``u`` (already limited) -> device calls.

Everything else is done here once for every vehicle: class checks at definition time, pinout
overrides from configuration, vehicle-level input limits (on top of the devices' own ranges),
calibration curves, telemetry, battery watch and safe mode, and the one board exchange per tick.

An incomplete subclass fails when it is *defined* (sizes, names, pinout shape) or, for missing
methods, when it is *constructed*, with a :class:`VehicleDefinitionError` saying what is missing.
An intermediate base class whose sizes are only known per instance is declared with
``class MyBase(Vehicle, abstract=True)``; its checks then run at construction.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from hilswarm.agents.calibration import Calibration
from hilswarm.agents.devices.base import Actuator, Device
from hilswarm.agents.devices.battery import Battery, LowBatteryEvent
from hilswarm.agents.errors import (
    BoardError,
    CalibrationError,
    HilswarmError,
    VehicleDefinitionError,
    VehicleError,
)
from hilswarm.agents.link.board import Board, BoardInfo, TickReply
from hilswarm.agents.pins import PROFILES, PinManager
from hilswarm.agents.telemetry import Telemetry
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from hilswarm.agents.link.sim_board import PinPlant
    from hilswarm.agents.sim.plant import PoseSource

__all__ = ["BATTERY_CHANNEL", "SafeModeListener", "Vehicle"]

logger = logging.getLogger(__name__)

#: Telemetry channel of battery voltages [V] (one field per Battery device), if any.
BATTERY_CHANNEL = "battery"

SafeModeListener = Callable[[str], None]

_MISSING = object()
_FLOAT64 = np.dtype(np.float64)


def _names_problems(owner: Any, names_attr: str, size_attr: str) -> list[str]:
    names = getattr(owner, names_attr, _MISSING)
    size = getattr(owner, size_attr, _MISSING)
    if names is _MISSING:
        return [f"{names_attr} is missing (a tuple of {size_attr} names)"]
    if isinstance(names, str) or not isinstance(names, Sequence):
        return [f"{names_attr} must be a tuple of names, got {names!r}"]
    problems = []
    bad = [n for n in names if not isinstance(n, str) or not n]
    if bad:
        problems.append(f"{names_attr} holds non-names {bad!r}")
    if len(set(names)) != len(names):
        problems.append(f"{names_attr} repeats names: {list(names)}")
    if isinstance(size, int) and not isinstance(size, bool) and len(names) != size:
        problems.append(f"{names_attr} has {len(names)} names but {size_attr} = {size}")
    return problems


def _pinout_problems(pinout: object, where: str) -> list[str]:
    if not isinstance(pinout, Mapping):
        return [f"{where} must map device -> role -> pin, got {type(pinout).__name__}"]
    problems = []
    for device, roles in pinout.items():
        if not isinstance(device, str) or not device:
            problems.append(f"{where}: device name {device!r} is not a non-empty string")
            continue
        if not isinstance(roles, Mapping):
            problems.append(f"{where}[{device!r}] must map role -> pin, got {type(roles).__name__}")
            continue
        for role, pin in roles.items():
            if not isinstance(role, str) or not role:
                problems.append(f"{where}[{device!r}]: role {role!r} is not a non-empty string")
            elif isinstance(pin, bool) or not isinstance(pin, int | str):
                problems.append(
                    f"{where}[{device!r}][{role!r}] = {pin!r} is not a pin (13, 'D13', 'A0')"
                )
    return problems


def _definition_problems(owner: Any) -> list[str]:
    """Everything wrong with the class-level declarations of ``owner`` (class or instance)."""
    problems: list[str] = []
    for attr, what in (("n_inputs", "control inputs"), ("n_outputs", "outputs")):
        value = getattr(owner, attr, _MISSING)
        if value is _MISSING:
            problems.append(f"{attr} is missing (an int: number of {what})")
        elif isinstance(value, bool) or not isinstance(value, int) or value < 0:
            problems.append(f"{attr} must be an int >= 0, got {value!r}")
    problems += _names_problems(owner, "input_names", "n_inputs")
    problems += _names_problems(owner, "output_names", "n_outputs")
    profile = getattr(owner, "profile", _MISSING)
    if profile not in PROFILES:
        problems.append(f"profile {profile!r} is not a board profile ({sorted(PROFILES)})")
    needs_board = getattr(owner, "needs_board", True)
    if not isinstance(needs_board, bool):
        problems.append(f"needs_board must be a bool, got {needs_board!r}")
    pinout = getattr(owner, "default_pinout", _MISSING)
    if pinout is _MISSING:
        if needs_board:
            problems.append("default_pinout is missing (a dict: device -> role -> pin)")
    else:
        problems += _pinout_problems(pinout, "default_pinout")
    limits = getattr(owner, "default_limits", {})
    names = getattr(owner, "input_names", ())
    if not isinstance(limits, Mapping):
        problems.append(f"default_limits must map input name -> (lo, hi), got {limits!r}")
    elif isinstance(names, Sequence):
        unknown = [key for key in limits if key not in names]
        if unknown:
            problems.append(f"default_limits names unknown input(s) {unknown}")
    params = getattr(owner, "default_params", {})
    if not isinstance(params, Mapping):
        problems.append(f"default_params must be a mapping, got {params!r}")
    return problems


class Vehicle(ABC):
    """Base class of every vehicle (see the module docstring).

    Class attributes (declare them in the subclass):
        n_inputs, n_outputs: sizes of ``u`` and ``y``.
        input_names, output_names: names of the entries of ``u`` and ``y`` (units in the docs
            of the subclass, e.g. ``"v_left"`` [m/s]).
        input_units, output_units: entry name -> unit (``{"v_left": "m/s"}``), recorded in
            the MCAP schemas and shown on plot axes; an entry without one has no unit.
        profile: board profile name (``"uno"``, ``"duemilanove"``, ``"fio"``).
        default_pinout: device -> role -> pin (13, ``"D13"``, ``"A0"``).
        needs_board: False for vehicles without hardware (simulated plants).
        needs_pose: True for vehicles whose outputs come from motion capture
            (``pose_source``): on a real board the experiment needs a ``[mocap]`` table.
        default_limits: input name -> ``(lo, hi)`` vehicle-level limits on ``u``.
        default_params: vehicle parameters and their defaults (``params=`` may change them).

    Args:
        name: vehicle (agent) name, used in messages and telemetry topics.
        pinout: overrides merged over ``default_pinout`` (device -> role -> pin); an unknown
            device or role is an error.
        limits: input name -> ``(lo, hi)``, merged over ``default_limits``.
        calibration: a :class:`Calibration`, or the path of a calibration TOML file.
        params: overrides of ``default_params`` (unknown keys are an error).
        initial_state: the state a simulated plant starts from (see simulated_hardware()).
        dt: control period [s], > 0.

    Raises:
        VehicleDefinitionError: the class is incomplete (missing methods/attributes) or
            setup_devices() left a pinout entry unused.
        VehicleError: a bad name, override, limit, parameter, state or period.
        CalibrationError: an unreadable calibration or one naming unknown inputs.
        PinError, DeviceError: the devices' pins break a rule (e.g. two devices on one pin).
    """

    n_inputs: ClassVar[int]
    n_outputs: ClassVar[int]
    input_names: ClassVar[tuple[str, ...]]
    output_names: ClassVar[tuple[str, ...]]
    input_units: ClassVar[Mapping[str, str]] = {}
    output_units: ClassVar[Mapping[str, str]] = {}
    profile: ClassVar[str] = "uno"
    default_pinout: ClassVar[Mapping[str, Mapping[str, int | str]]]
    needs_board: ClassVar[bool] = True
    needs_pose: ClassVar[bool] = False
    default_limits: ClassVar[Mapping[str, tuple[float, float]]] = {}
    default_params: ClassVar[Mapping[str, Any]] = {}

    _deferred_checks: ClassVar[bool] = True

    def __init_subclass__(cls, *, abstract: bool = False, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._deferred_checks = abstract
        if abstract:
            return
        problems = _definition_problems(cls)
        if problems:
            raise VehicleDefinitionError(
                f"vehicle class {cls.__qualname__} is incomplete:\n  - "
                + "\n  - ".join(problems)
                + "\n(an intermediate base class whose sizes are set per instance is declared "
                f"as `class {cls.__name__}(Vehicle, abstract=True)`)"
            )

    def __new__(cls, *args: Any, **kwargs: Any) -> Vehicle:
        missing = sorted(getattr(cls, "__abstractmethods__", ()))
        if missing:
            raise VehicleDefinitionError(
                f"cannot construct vehicle {cls.__qualname__}: it does not implement "
                + ", ".join(f"{name}()" for name in missing)
                + " (abstract methods of Vehicle: setup_devices, read_outputs, actuate)"
            )
        return super().__new__(cls)

    def __init__(
        self,
        *,
        name: str | None = None,
        pinout: Mapping[str, Mapping[str, int | str]] | None = None,
        limits: Mapping[str, Sequence[float]] | None = None,
        calibration: Calibration | str | Path | None = None,
        params: Mapping[str, Any] | None = None,
        initial_state: Sequence[float] | None = None,
        dt: float | None = None,
    ) -> None:
        cls = type(self)
        if cls._deferred_checks:
            problems = _definition_problems(self)
            if problems:
                raise VehicleDefinitionError(
                    f"vehicle {cls.__qualname__} is incomplete:\n  - " + "\n  - ".join(problems)
                )
        self.name: str = self._check_name(cls.__name__ if name is None else name)
        self.dt: float | None = self._check_dt(dt)
        self.initial_state: np.ndarray | None = self._check_state(initial_state)
        self.params: dict[str, Any] = self._merge_params(params)
        self.pinout: dict[str, dict[str, int | str]] = self._merge_pinout(pinout)
        self._lo, self._hi = self._merge_limits(limits)
        self.calibration: Calibration | None = self._load_calibration(calibration)
        self.pins: PinManager = PinManager(self.profile)
        self.telemetry: Telemetry = Telemetry()
        self.devices: dict[str, Device] = {}
        self.pose_source: PoseSource | None = None
        self._u = np.zeros(self.n_inputs)
        self._y = np.full(self.n_outputs, np.nan)
        self._k = -1
        self._t = math.nan
        self._safe_mode = False
        self._safe_reason: str | None = None
        self._safe_listeners: list[SafeModeListener] = []
        self.ignored_applies = 0
        self._update_device_lists()

        self.setup_devices()
        self._collect_devices()
        unused = [device for device in self.pinout if device not in self.pins.devices()]
        if unused:
            raise VehicleDefinitionError(
                f"vehicle {self.name!r} ({cls.__qualname__}): setup_devices() built no device "
                f"for pinout entr{'y' if len(unused) == 1 else 'ies'} {unused}"
            )
        self._update_device_lists()
        for battery in self.batteries:
            battery.add_listener(self._on_low_battery)
        if self.batteries:
            self.telemetry.add_channel(BATTERY_CHANNEL, [b.name for b in self.batteries])
        self.setup_telemetry()

    # ------------------------------------------------------------------ construction helpers
    @staticmethod
    def _check_name(name: object) -> str:
        if not isinstance(name, str) or not name or "/" in name:
            raise VehicleError(f"vehicle name must be a non-empty string without '/', got {name!r}")
        return name

    def _check_dt(self, dt: object) -> float | None:
        if dt is None:
            return None
        if isinstance(dt, bool) or not isinstance(dt, int | float) or not math.isfinite(dt):
            raise VehicleError(
                f"vehicle {self.name!r}: dt must be a finite time > 0 [s], got {dt!r}"
            )
        if dt <= 0:
            raise VehicleError(f"vehicle {self.name!r}: dt must be > 0 [s], got {dt!r}")
        return float(dt)

    def _check_state(self, state: Sequence[float] | None) -> np.ndarray | None:
        if state is None:
            return None
        try:
            array = np.asarray(state, dtype=np.float64)
        except (TypeError, ValueError):
            raise VehicleError(
                f"vehicle {self.name!r}: initial_state must be numbers, got {state!r}"
            ) from None
        if array.ndim != 1 or not np.all(np.isfinite(array)):
            raise VehicleError(
                f"vehicle {self.name!r}: initial_state must be a flat list of finite numbers, "
                f"got {state!r}"
            )
        return array

    def _merge_params(self, params: Mapping[str, Any] | None) -> dict[str, Any]:
        merged = dict(self.default_params)
        if params is None:
            return merged
        if not isinstance(params, Mapping):
            raise VehicleError(f"vehicle {self.name!r}: params must be a mapping, got {params!r}")
        unknown = sorted(key for key in params if key not in merged)
        if unknown:
            raise VehicleError(
                f"vehicle {self.name!r}: unknown parameter(s) {unknown}; "
                f"{type(self).__name__} takes {sorted(merged) or 'no parameters'}"
            )
        merged.update(params)
        return merged

    def _merge_pinout(
        self, overrides: Mapping[str, Mapping[str, int | str]] | None
    ) -> dict[str, dict[str, int | str]]:
        default = getattr(self, "default_pinout", {})
        merged = {device: dict(roles) for device, roles in default.items()}
        if overrides is None:
            return merged
        problems = _pinout_problems(overrides, "pinout override")
        if problems:
            raise VehicleError(f"vehicle {self.name!r}: " + "; ".join(problems))
        for device, roles in overrides.items():
            if device not in merged:
                raise VehicleError(
                    f"vehicle {self.name!r}: pinout override names unknown device {device!r}; "
                    f"devices are {sorted(merged)}"
                )
            for role, pin in roles.items():
                if role not in merged[device]:
                    raise VehicleError(
                        f"vehicle {self.name!r}: pinout override names unknown role {role!r} "
                        f"of device {device!r}; roles are {sorted(merged[device])}"
                    )
                merged[device][role] = pin
        return merged

    def _merge_limits(
        self, overrides: Mapping[str, Sequence[float]] | None
    ) -> tuple[np.ndarray, np.ndarray]:
        lo = np.full(self.n_inputs, -np.inf)
        hi = np.full(self.n_inputs, np.inf)
        if overrides is not None and not isinstance(overrides, Mapping):
            raise VehicleError(
                f"vehicle {self.name!r}: limits must map input name -> (lo, hi), got {overrides!r}"
            )
        for source in (self.default_limits, overrides or {}):
            for key, bounds in source.items():
                if key not in self.input_names:
                    raise VehicleError(
                        f"vehicle {self.name!r}: limits name unknown input {key!r}; "
                        f"inputs are {list(self.input_names)}"
                    )
                try:
                    low, high = (float(b) for b in bounds)
                except (TypeError, ValueError):
                    raise VehicleError(
                        f"vehicle {self.name!r}: limits[{key!r}] must be (lo, hi), got {bounds!r}"
                    ) from None
                if math.isnan(low) or math.isnan(high) or low > high:
                    raise VehicleError(
                        f"vehicle {self.name!r}: limits[{key!r}] = {bounds!r} needs lo <= hi"
                    )
                index = self.input_names.index(key)
                lo[index], hi[index] = low, high
        return lo, hi

    def _load_calibration(self, calibration: Calibration | str | Path | None) -> Calibration | None:
        if calibration is None:
            return None
        if isinstance(calibration, str | Path):
            calibration = Calibration.from_file(calibration)
        if not isinstance(calibration, Calibration):
            raise CalibrationError(
                f"vehicle {self.name!r}: calibration must be a Calibration or a file path, "
                f"got {calibration!r}"
            )
        calibration.check_names(self.input_names)
        return calibration

    def add_device(self, device_class: type[Device], name: str, **options: Any) -> Any:
        """Build ``device_class(self.pins, name, self.pinout[name], **options)`` and keep it.

        Raises:
            VehicleDefinitionError: ``name`` has no entry in the pinout.
            VehicleError: two devices of that name.
        """
        if name not in self.pinout:
            raise VehicleDefinitionError(
                f"vehicle {self.name!r}: no pinout for device {name!r}: add it to "
                f"{type(self).__name__}.default_pinout (devices there: {sorted(self.pinout)})"
            )
        if name in self.devices:
            raise VehicleError(f"vehicle {self.name!r}: device {name!r} is added twice")
        device = device_class(self.pins, name, self.pinout[name], **options)
        self.devices[name] = device
        self._update_device_lists()
        return device

    def _collect_devices(self) -> None:
        for value in vars(self).values():
            if isinstance(value, Device) and value.name not in self.devices:
                self.devices[value.name] = value
        self._update_device_lists()

    def _update_device_lists(self) -> None:
        # Per-tick work reads these instead of scanning the devices (built with the devices).
        self._batteries: tuple[Battery, ...] = tuple(
            d for d in self.devices.values() if isinstance(d, Battery)
        )
        self._battery_volts = np.empty(len(self._batteries))  # one tick's voltages [V]
        # Limits as floats, and whether any is finite (no clipping work without limits).
        self._lo_list: list[float] = self._lo.tolist()
        self._hi_list: list[float] = self._hi.tolist()
        self._limited = any(math.isfinite(v) for v in self._lo_list + self._hi_list)

    # ------------------------------------------------------------------ subclass interface
    @abstractmethod
    def setup_devices(self) -> None:
        """Build the devices from ``self.pinout`` (use :meth:`add_device`)."""

    def setup_telemetry(self) -> None:
        """Add the vehicle's own channels to ``self.telemetry`` (default: none)."""
        return

    @abstractmethod
    def read_outputs(self) -> ArrayLike:
        """Devices (and ``pose_source``) -> the output vector ``y`` (``n_outputs`` values)."""

    @abstractmethod
    def actuate(self, u: np.ndarray) -> ArrayLike | None:
        """Turn ``u`` (within the vehicle limits) into device calls.

        May return the input actually applied (e.g. after device-level clipping, converted back
        through the calibration); ``None`` means ``u`` itself.
        """

    def record_telemetry(self, k: int, t: float, y: np.ndarray) -> None:
        """Append the vehicle's own channels for tick ``k`` at time ``t`` [s] (default: none)."""
        return

    def simulated_hardware(
        self, *, initial_state: Sequence[float] | None, dt: float
    ) -> PinPlant | None:
        """A pin-level model of this vehicle's hardware for ``sim://`` boards (default: none)."""
        return None

    def safe_inputs(self) -> np.ndarray:
        """The input vector that corresponds to safe mode (default: zeros)."""
        return np.zeros(self.n_inputs)

    # ------------------------------------------------------------------ devices
    @property
    def actuators(self) -> list[Actuator]:
        """Every actuator device."""
        return [d for d in self.devices.values() if isinstance(d, Actuator)]

    @property
    def batteries(self) -> list[Battery]:
        """Every Battery device."""
        return list(self._batteries)

    @property
    def limits(self) -> dict[str, tuple[float, float]]:
        """Vehicle-level limits ``(lo, hi)`` per input name (±inf: none)."""
        return {
            name: (float(self._lo[i]), float(self._hi[i]))
            for i, name in enumerate(self.input_names)
        }

    def to_pwm(self, name: str, u: float) -> float:
        """Signed PWM [wire units] for input ``name`` at ``u``, through the calibration."""
        if self.calibration is None or name not in self.calibration:
            raise VehicleError(
                f"vehicle {self.name!r} has no calibration curve for input {name!r}: "
                "pass calibration= (a Calibration or a TOML file)"
            )
        return float(self.calibration.to_pwm(name, u))

    def to_u(self, name: str, pwm: float) -> float:
        """Input value of ``name`` for a signed PWM [wire units], through the calibration."""
        if self.calibration is None or name not in self.calibration:
            raise VehicleError(
                f"vehicle {self.name!r} has no calibration curve for input {name!r}: "
                "pass calibration= (a Calibration or a TOML file)"
            )
        return float(self.calibration.to_u(name, pwm))

    # ------------------------------------------------------------------ the tick
    def connect(self, board: Board, *, watchdog_s: float = 0.5, prime: bool = True) -> BoardInfo:
        """Open and configure ``board`` for this vehicle's pins.

        Args:
            board: the board (any transport).
            watchdog_s: link watchdog [s]; 0 disables it.
            prime: do one exchange right away (safe outputs) so that the first sense() has
                samples; on a ``sim://`` board that exchange advances the board clock by dt.

        Raises:
            VehicleError: the vehicle needs no board.
            PinError: the board lacks a capability one of the pins needs.
        """
        if not self.needs_board:
            raise VehicleError(f"vehicle {self.name!r} ({type(self).__name__}) uses no board")
        info = self.pins.attach(board, watchdog_s=watchdog_s)
        if self._safe_mode:
            self.pins.estop()
        if prime:
            self.pins.exchange()
        return info

    def sense(self, k: int, t: float) -> np.ndarray:
        """Read ``y_k`` at tick ``k``, time ``t`` [s]; record telemetry; watch the batteries.

        Raises:
            VehicleError: read_outputs() returned the wrong number of values.
        """
        raw = self.read_outputs()
        if type(raw) is np.ndarray and raw.dtype == _FLOAT64 and raw.shape == (self.n_outputs,):
            y = raw  # the common case: already a float vector of the right size
        else:
            try:
                y = np.asarray(raw, dtype=np.float64)
            except (TypeError, ValueError):
                raise VehicleError(
                    f"vehicle {self.name!r}: read_outputs() returned {raw!r}, not numbers"
                ) from None
            if y.shape != (self.n_outputs,):
                raise VehicleError(
                    f"vehicle {self.name!r}: read_outputs() returned shape {y.shape}, expected "
                    f"({self.n_outputs},) = {self.output_names}"
                )
        self._y = y.copy()
        self._k, self._t = k, t
        if self._batteries:
            volts = self._battery_volts
            for i, battery in enumerate(self._batteries):
                volts[i] = battery.sense()
            self.telemetry[BATTERY_CHANNEL].append(k, t, volts)
        record_pose = getattr(self.pose_source, "record", None)  # a mocap pose source's row
        if record_pose is not None:
            record_pose(k, t)
        self.record_telemetry(k, t, y.copy())
        return y

    def check_batteries(self) -> list[float]:
        """Sense every battery [V] (a low one puts the vehicle in safe mode)."""
        return [battery.sense() for battery in self._batteries]

    def apply(self, u: ArrayLike) -> None:
        """Limit ``u`` and stage it on the devices (sent by the next exchange()).

        Ignored (and counted in ``ignored_applies``) once in safe mode.

        Raises:
            VehicleError: wrong shape or non-finite values (names the input).
        """
        if type(u) is np.ndarray and u.dtype == _FLOAT64 and u.shape == (self.n_inputs,):
            vector = u  # the common case: no conversion
        else:
            try:
                vector = np.asarray(u, dtype=np.float64)
            except (TypeError, ValueError):
                raise VehicleError(f"vehicle {self.name!r}: u = {u!r} is not numbers") from None
            if vector.shape != (self.n_inputs,):
                raise VehicleError(
                    f"vehicle {self.name!r}: u has shape {vector.shape}, expected "
                    f"({self.n_inputs},) = {self.input_names}"
                )
        values = vector.tolist()  # plain floats: cheaper than numpy on a few entries
        for i, value in enumerate(values):
            if not math.isfinite(value):
                raise VehicleError(
                    f"vehicle {self.name!r}: u[{i}] ({self.input_names[i]}) = {value} is not finite"
                )
        if self._safe_mode:
            self.ignored_applies += 1
            if self.ignored_applies == 1:
                logger.warning(
                    "vehicle %r is in safe mode (%s): apply(%s) ignored",
                    self.name,
                    self._safe_reason,
                    values,
                )
            return
        if self._limited:  # np.clip's result, element by element (min(max(u, lo), hi))
            lo, hi = self._lo_list, self._hi_list
            values = [min(max(value, lo[i]), hi[i]) for i, value in enumerate(values)]
        applied = self.actuate(np.array(values, dtype=np.float64))
        if applied is None:
            self._u = np.array(values, dtype=np.float64)
            return
        if not (
            type(applied) is np.ndarray
            and applied.dtype == _FLOAT64
            and applied.shape == (self.n_inputs,)
        ):
            applied = np.asarray(applied, dtype=np.float64)
            if applied.shape != (self.n_inputs,):
                raise VehicleError(
                    f"vehicle {self.name!r}: actuate() returned shape {applied.shape}, expected "
                    f"({self.n_inputs},) or None"
                )
        self._u = applied.copy()

    def exchange(self) -> TickReply | None:
        """One board round trip: staged writes out, samples in (``None`` without a board)."""
        if not self.needs_board:
            return None
        return self.pins.exchange()

    @property
    def u(self) -> np.ndarray:
        """The last input as applied (after limits), a copy."""
        return self._u.copy()

    @property
    def y(self) -> np.ndarray:
        """The last sensed output, a copy (NaN before the first sense())."""
        return self._y.copy()

    # ------------------------------------------------------------------ safe mode
    @property
    def safe_mode(self) -> bool:
        """True once the vehicle entered safe mode (latched)."""
        return self._safe_mode

    @property
    def safe_mode_reason(self) -> str | None:
        """Why the vehicle entered safe mode (``None`` if it did not)."""
        return self._safe_reason

    def add_safe_mode_listener(self, listener: SafeModeListener) -> None:
        """Call ``listener(reason)`` when the vehicle enters safe mode."""
        if not callable(listener):
            raise VehicleError(f"vehicle {self.name!r}: listener {listener!r} is not callable")
        self._safe_listeners.append(listener)

    def enter_safe_mode(self, reason: str, *, fault: bool = True) -> None:
        """Drive every actuator to its safe state, latch safe mode and notify listeners.

        The safe values are staged and, with a board attached, the board is e-stopped at once
        (it holds the outputs safe until it is configured again). Later apply() calls are
        ignored. Entering again does nothing.

        Args:
            reason: why, for logs, status and listeners.
            fault: ``True`` (default) for faults (low battery, e-stop, lost link, errors),
                logged at WARNING; ``False`` for an orderly stop (the run completed, a stop was
                requested), logged at INFO.
        """
        if self._safe_mode:
            logger.debug("vehicle %r already in safe mode; new reason %r", self.name, reason)
            return
        self._safe_mode = True
        self._safe_reason = reason
        logger.log(
            logging.WARNING if fault else logging.INFO,
            "vehicle %r enters safe mode: %s",
            self.name,
            reason,
        )
        for actuator in self.actuators:
            try:
                actuator.safe()
            except HilswarmError as exc:
                logger.error("vehicle %r: %r could not go safe: %s", self.name, actuator, exc)
        self._u = self.safe_inputs()
        try:
            self.pins.estop()
        except BoardError as exc:
            logger.error(
                "vehicle %r: e-stop of the board failed (%s); safe values go out with the "
                "next exchange",
                self.name,
                exc,
            )
        for listener in list(self._safe_listeners):
            listener(reason)

    def _on_low_battery(self, event: LowBatteryEvent) -> None:
        self.enter_safe_mode(
            f"low battery: {event.device} at {event.volts:.3f} V < {event.low_v:.3f} V"
        )

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, devices={list(self.devices)})"

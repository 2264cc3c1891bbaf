"""SimulatedVehicle: a Vehicle whose "hardware" is a continuous-time plant model.

The thesis' ``SimulinkVehicle`` (§3.2.1): it inherits the whole Vehicle interface, but instead of
driving devices it integrates a plant model, so a :class:`~hilswarm.agents.control.ControlModel`
and a vehicle exchange ``u`` and ``y`` exactly as in hardware-in-the-loop runs — simulated HIL
(SHIL). Compare a SHIL run with the SIL simulation of the same loop: with Euler integration
they agree at every tick (``hilswarm.agents.sim.chapter3``).

Per tick: :meth:`Vehicle.apply` limits ``u`` and calls :meth:`SimulatedVehicle.actuate`, which
integrates the plant over exactly one control period ``dt`` with ``u`` held constant (Euler
by default, RK4 optional, ``substeps`` fixed steps); :meth:`Vehicle.sense` then returns the
plant output. There is no board (``needs_board = False``; ``exchange()`` returns ``None``). In
safe mode ``apply`` is ignored and ``exchange()`` advances the plant with the safe inputs.

Parameters (``params=``, TOML-like)::

    plant = "spring_mass_damper"     # registry name or "package.module:Class" (a ContinuousPlant)
    plant_params = { m = 1.0, k1 = 1.0 }   # keyword arguments of the plant class
    integrator = "euler"             # or "rk4" (or a plant's own, e.g. "exact")
    substeps = 1                     # fixed steps per control period

``initial_state`` is the plant state at tick 0 (default zeros), ``dt`` [s] is required.

Sizes: ``n_inputs``/``n_outputs`` and the names come from the plant, so they are *instance*
attributes; the class is declared ``abstract=True`` in the Vehicle sense, which moves the
Vehicle definition checks from class definition to construction (after the plant is built).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from hilswarm.agents.calibration import Calibration
from hilswarm.agents.errors import HilswarmError, VehicleError
from hilswarm.agents.registry import RegistryError, resolve_plant
from hilswarm.agents.sim.plant import METHODS, ContinuousPlant
from hilswarm.agents.vehicle import Vehicle
from numpy.typing import ArrayLike

__all__ = ["STATE_CHANNEL", "SimulatedVehicle"]

#: Telemetry channel of the plant state after each sense (fields: the plant's state names).
STATE_CHANNEL = "state"


class SimulatedVehicle(Vehicle, abstract=True):
    """A Vehicle that advances a :class:`ContinuousPlant` by one period per applied input.

    Takes the Vehicle constructor keywords (``name``, ``pinout``, ``limits``, ``calibration``,
    ``params``, ``initial_state``, ``dt``); see the module docstring for ``params``.

    Attributes:
        plant: the plant model.
        state: the plant state now (a copy), in the plant's units.
        time_s: plant time [s]: ``dt`` times the number of applied inputs.

    Raises:
        VehicleError: no ``dt``, an unknown plant or integrator, bad plant parameters, an
            initial state of the wrong size (all name the vehicle and the key).
    """

    needs_board: ClassVar[bool] = False
    default_pinout: ClassVar[Mapping[str, Mapping[str, int | str]]] = {}
    default_params: ClassVar[Mapping[str, Any]] = {
        "plant": "spring_mass_damper",
        "plant_params": {},
        "integrator": "euler",
        "substeps": 1,
    }

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
        label = f"vehicle {name or type(self).__name__!r} ({type(self).__name__})"
        merged = self._plant_settings(label, params)
        self.plant: ContinuousPlant = self._build_plant(label, merged)
        self.integrator: str = merged["integrator"]
        self.substeps: int = merged["substeps"]
        # Per-instance sizes and names, checked by Vehicle.__init__ (deferred checks).
        self.n_inputs = self.plant.n_inputs  # type: ignore[misc]
        self.n_outputs = self.plant.n_outputs  # type: ignore[misc]
        self.input_names = tuple(self.plant.input_names)  # type: ignore[misc]
        self.output_names = tuple(self.plant.output_names)  # type: ignore[misc]
        self.input_units = dict(getattr(self.plant, "input_units", {}))  # type: ignore[misc]
        self.output_units = dict(getattr(self.plant, "output_units", {}))  # type: ignore[misc]
        if dt is None:
            raise VehicleError(f"{label}: dt (the control period [s]) is required")
        super().__init__(
            name=name,
            pinout=pinout,
            limits=limits,
            calibration=calibration,
            params=params,
            initial_state=initial_state,
            dt=dt,
        )
        if self.initial_state is None:
            self._x = np.zeros(self.plant.n_states)
        elif self.initial_state.shape != (self.plant.n_states,):
            raise VehicleError(
                f"vehicle {self.name!r}: initial_state must have {self.plant.n_states} entries "
                f"{self.plant.state_names}, got {self.initial_state.shape[0]}"
            )
        else:
            self._x = self.initial_state.copy()
        self._time_s = 0.0
        self._advanced = False
        try:  # a zero-length step checks the method with the plant (some have "exact")
            self.plant.advance(
                0.0,
                self._x,
                np.zeros(self.n_inputs),
                0.0,
                method=self.integrator,
                substeps=self.substeps,
            )
        except HilswarmError as exc:
            raise VehicleError(
                f"vehicle {self.name!r}: params.integrator {self.integrator!r} / substeps "
                f"{self.substeps!r} do not suit plant {type(self.plant).__name__}: {exc}"
            ) from exc

    # ------------------------------------------------------------------ construction
    @classmethod
    def _plant_settings(cls, label: str, params: Mapping[str, Any] | None) -> dict[str, Any]:
        if params is not None and not isinstance(params, Mapping):
            raise VehicleError(f"{label}: params must be a mapping, got {params!r}")
        merged = {**cls.default_params, **(params or {})}
        if not isinstance(merged["integrator"], str):
            raise VehicleError(
                f"{label}: params.integrator must be a method name such as {METHODS}, "
                f"got {merged['integrator']!r}"
            )
        substeps = merged["substeps"]
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise VehicleError(f"{label}: params.substeps must be an int >= 1, got {substeps!r}")
        if not isinstance(merged["plant_params"], Mapping):
            raise VehicleError(
                f"{label}: params.plant_params must be a table of keyword arguments, "
                f"got {merged['plant_params']!r}"
            )
        return merged

    @staticmethod
    def _build_plant(label: str, settings: Mapping[str, Any]) -> ContinuousPlant:
        spec = settings["plant"]
        plant_params = dict(settings["plant_params"])
        if isinstance(spec, ContinuousPlant):
            if plant_params:
                raise VehicleError(f"{label}: params.plant_params given with a plant instance")
            return spec
        try:
            plant_class = resolve_plant(spec)
        except RegistryError as exc:
            raise VehicleError(f"{label}: params.plant: {exc}") from exc
        if isinstance(plant_class, type) and not issubclass(plant_class, ContinuousPlant):
            raise VehicleError(
                f"{label}: params.plant {spec!r} is {plant_class.__qualname__}, "
                "not a ContinuousPlant"
            )
        try:
            plant = plant_class(**plant_params)
        except TypeError as exc:
            raise VehicleError(
                f"{label}: params.plant_params do not fit plant {spec!r}: {exc}"
            ) from exc
        except HilswarmError as exc:
            raise VehicleError(f"{label}: params.plant_params: {exc}") from exc
        if not isinstance(plant, ContinuousPlant):
            raise VehicleError(
                f"{label}: params.plant {spec!r} is a {type(plant).__name__}, not a ContinuousPlant"
            )
        return plant

    # ------------------------------------------------------------------ Vehicle interface
    def setup_devices(self) -> None:
        """No devices: the plant model is the hardware."""
        return

    def setup_telemetry(self) -> None:
        """Channel ``"state"``: the plant state at every sense (fields: state names)."""
        if self.plant.n_states > 0:
            self.telemetry.add_channel(STATE_CHANNEL, self.plant.state_names)

    def record_telemetry(self, k: int, t: float, y: np.ndarray) -> None:
        if self.plant.n_states > 0:
            self.telemetry[STATE_CHANNEL].append(k, t, self._x)

    def read_outputs(self) -> np.ndarray:
        """The plant output ``y = output(t, x, u)`` with the input now held."""
        return np.asarray(self.plant.output(self._time_s, self._x.copy(), self.u), dtype=float)

    def actuate(self, u: np.ndarray) -> None:
        """Integrate the plant over one period ``dt`` with ``u`` held constant."""
        dt = self.dt
        if dt is None or not math.isfinite(dt):  # Vehicle.__init__ checked it; keep mypy calm
            raise VehicleError(f"vehicle {self.name!r}: no control period dt")
        self._x = self.plant.advance(
            self._time_s, self._x, u, dt, method=self.integrator, substeps=self.substeps
        )
        self._time_s += dt
        self._advanced = True

    def exchange(self) -> None:
        """End of the tick (no board). In safe mode, where apply() is ignored, the plant still
        advances one period with the safe inputs: the simulated world does not stop."""
        if self.safe_mode and not self._advanced:
            self.actuate(self.u)
        self._advanced = False

    # ------------------------------------------------------------------ plant access
    @property
    def state(self) -> np.ndarray:
        """The plant state now (a copy)."""
        return self._x.copy()

    @property
    def time_s(self) -> float:
        """Plant time [s] (``dt`` per applied input)."""
        return self._time_s

    def set_state(self, x: ArrayLike) -> None:
        """Put the plant in state ``x`` (e.g. a disturbance in a test).

        Raises:
            VehicleError: wrong size or non-finite.
        """
        state = np.asarray(x, dtype=np.float64).reshape(-1)
        if state.shape != (self.plant.n_states,) or not np.all(np.isfinite(state)):
            raise VehicleError(
                f"vehicle {self.name!r}: state must be {self.plant.n_states} finite numbers "
                f"{self.plant.state_names}, got {x!r}"
            )
        self._x = state

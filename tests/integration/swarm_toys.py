"""Tiny vehicle and controller used by the swarm runtime's integration tests.

``ToyIntegrator`` is a board-less single integrator ``x_{k+1} = x_k + dt u`` (x [m], u [m/s]);
``ToyConsensus`` drives it towards the mean of its neighbours' outputs
(``u = gain * sum_j (y_j - y)`` over neighbours with data) and counts the ticks at which a
neighbour had no data. Agent processes import this module through ``PYTHONPATH``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from hilswarm.agents.control import Controller, TickInput
from hilswarm.agents.devices import Battery, HBridgeMotor
from hilswarm.agents.vehicle import Vehicle


class ToyIntegrator(Vehicle):
    """``x_{k+1} = x_k + dt * u_k``; output ``x`` [m], input ``v`` [m/s]."""

    n_inputs: ClassVar[int] = 1
    n_outputs: ClassVar[int] = 1
    input_names: ClassVar[tuple[str, ...]] = ("v",)
    output_names: ClassVar[tuple[str, ...]] = ("x",)
    default_pinout: ClassVar[Mapping[str, Mapping[str, int | str]]] = {}
    needs_board: ClassVar[bool] = False

    def setup_devices(self) -> None:
        start = self.initial_state
        self.x = float(start[0]) if start is not None and len(start) else 0.0

    def read_outputs(self) -> np.ndarray:
        return np.array([self.x])

    def actuate(self, u: np.ndarray) -> None:
        self.x += float(self.dt) * float(u[0])


class ToyConsensus(Controller):
    """``u = gain * sum_j (y_j - y)``; state: [ticks with a neighbour missing].

    ``work_s`` [s] makes each step that long (a controller too slow for the rate).
    """

    n_states: ClassVar[int] = 1
    default_params: ClassVar[Mapping[str, Any]] = {"gain": 1.0, "work_s": 0.0}

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        merged = {**self.default_params, **params}
        if not isinstance(merged["gain"], int | float):
            from hilswarm.agents.errors import ControllerError

            raise ControllerError(f"gain must be a number, got {merged['gain']!r}")
        return merged

    def initial_state(self, params: Mapping[str, Any]) -> np.ndarray:
        return np.zeros(1)

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        if params["work_s"] > 0:
            time.sleep(params["work_s"])  # stands for slow control code, not for waiting
        total = 0.0
        missing = 0
        for value in tick.neighbours.values():
            if value is None:
                missing += 1
            else:
                total += float(value[0]) - float(tick.y[0])
        return np.array([params["gain"] * total]), x_hat + (1.0 if missing else 0.0)


class ToyCart(Vehicle):
    """Two H-bridge motors and a battery (the cart of docs/vehicles.md) on a real board link.

    Output: battery voltage [V]; inputs: signed duty of the left and right motor (-255..255).
    """

    n_inputs: ClassVar[int] = 2
    n_outputs: ClassVar[int] = 1
    input_names: ClassVar[tuple[str, ...]] = ("left", "right")
    output_names: ClassVar[tuple[str, ...]] = ("battery_v",)
    default_pinout: ClassVar[Mapping[str, Mapping[str, int | str]]] = {
        "battery": {"pin": "A0"},
        "drive": {
            "left_fwd": 4,
            "left_back": 7,
            "left_pwm": 5,
            "right_fwd": 8,
            "right_back": 12,
            "right_pwm": 6,
        },
    }

    def setup_devices(self) -> None:
        self.drive = self.add_device(HBridgeMotor, "drive", motors=("left", "right"))
        self.battery = self.add_device(Battery, "battery", multiplier=3.0, low_v=6.5)

    def read_outputs(self) -> np.ndarray:
        return np.array([self.battery.sense()])

    def actuate(self, u: np.ndarray) -> None:
        self.drive.actuate("left", u[0])
        self.drive.actuate("right", u[1])


class FullBattery:
    """A pin plant: 7.5 V on A0 through the cart's 1:3 divider, whatever the outputs."""

    def advance(self, outputs: Mapping[int, int], dt: float) -> dict[int, float]:
        return {14: 2.5}

    def pose(self) -> np.ndarray:
        return np.zeros(6)


class ToyDrive(Controller):
    """Drives both motors forward at ``duty`` (-255..255); no state."""

    n_states: ClassVar[int] = 0
    default_params: ClassVar[Mapping[str, Any]] = {"duty": 200.0}

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        return {**self.default_params, **params}

    def initial_state(self, params: Mapping[str, Any]) -> np.ndarray:
        return np.zeros(0)

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        return np.array([params["duty"], params["duty"]]), x_hat

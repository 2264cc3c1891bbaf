"""The Frisbee square of thesis §5.6 (Fig. 5.5), run three ways with the same controller.

The vehicle starts at the origin facing +x, drives to (0.25, 0.25), then around the square of
Code Sample 5.1 (its waypoints ``[1 1]; [0 1]; [0 0]; [1 0]``, scaled to ±0.25 m as in §5.6) and
back to the first corner to close it. Every run uses the :class:`WaypointController` in a
:class:`ControlModel`, stepped once per tick in the agent's order (sense ``y_k``, compute
``u_{k+1}``, apply, one board exchange / plant step of ``dt``):

* :func:`run_sil` — software in the loop: the controller and the exact differential-drive
  kinematics, continuous wheel speeds, perfect pose;
* :func:`run_sim_board` — the same controller through the vehicle: :class:`FrisbeeBot` on an
  in-process :class:`SimBoard` whose :class:`FrisbeePinPlant` reads the H-bridge pins (integer
  duty, inverse calibration), with the pose from a seeded noisy :class:`SimulatedMocap` — the
  thesis' HIL path with the robot replaced by its pin-level model;
* :func:`result_from_recording` — any run recorded by ``hilswarm run`` (the full runtime, or the
  real firmware in simavr), read back from its MCAP file.

A run has *finished* when the controller holds at the last waypoint (``x_hat`` phase 2).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from hilswarm.agents.control import ControlModel
from hilswarm.agents.controllers.waypoint import HOLDING, WaypointController
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.agents.sim.differential_drive import DifferentialDrive
from hilswarm.agents.sim.mocap import SimulatedMocap
from hilswarm.agents.vehicles.frisbee import FrisbeeBot

#: The start leg's target, then the square of Code Sample 5.1 scaled to ±0.25 m, closed [m].
SQUARE_WAYPOINTS: tuple[tuple[float, float], ...] = (
    (0.25, 0.25),
    (-0.25, 0.25),
    (-0.25, -0.25),
    (0.25, -0.25),
    (0.25, 0.25),
)
#: Control period of the reproduction [s] (20 Hz).
DEFAULT_DT = 0.05
#: Controller parameters shared by every run (mode and waypoints are added per run).
DEFAULT_PARAMS: Mapping[str, Any] = {
    "kp": 1.0,
    "ki": 0.5,
    "pointing_tolerance_rad": 0.1,
    "waypoint_tolerance_m": 0.005,
    "turn_gain": 3.0,
}


@dataclass(frozen=True)
class SquareRun:
    """One run of the square.

    Attributes:
        label: what ran (e.g. ``"SIL P"``).
        t: tick times [s], shape (n,).
        pose: sensed ``y = [x, y, psi]`` per tick [m, m, rad], shape (n, 3).
        waypoint_index: the controller's current waypoint per tick, shape (n,).
        finish_time_s: time [s] at which the controller first held at the last waypoint, or
            ``None`` if it never did within the run.
    """

    label: str
    t: np.ndarray
    pose: np.ndarray
    waypoint_index: np.ndarray
    finish_time_s: float | None

    def closest_approach(self, point: tuple[float, float]) -> float:
        """Smallest distance [m] between the sensed path and ``point``."""
        return float(np.min(np.hypot(self.pose[:, 0] - point[0], self.pose[:, 1] - point[1])))


def square_params(mode: str, **overrides: Any) -> dict[str, Any]:
    """Controller params of the square for mode ``"p"`` or ``"pi"`` (plus overrides)."""
    return {
        **DEFAULT_PARAMS,
        "waypoints": [list(p) for p in SQUARE_WAYPOINTS],
        "mode": mode,
        **overrides,
    }


def _finish(label: str, times: list[float], poses: list[Any], x_hats: list[Any]) -> SquareRun:
    x_hat = np.array(x_hats, dtype=float).reshape(len(x_hats), -1)
    holding = np.flatnonzero(x_hat[:, 1] == HOLDING) if len(x_hats) else np.array([], int)
    return SquareRun(
        label=label,
        t=np.array(times, dtype=float),
        pose=np.array(poses, dtype=float).reshape(len(poses), 3),
        waypoint_index=x_hat[:, 0].astype(int) if len(x_hats) else np.array([], int),
        finish_time_s=float(times[holding[0]]) if holding.size else None,
    )


def run_sil(
    mode: str,
    *,
    dt: float = DEFAULT_DT,
    max_time_s: float = 120.0,
    params: Mapping[str, Any] | None = None,
) -> SquareRun:
    """Controller + exact kinematics, perfect pose; stops once the controller holds."""
    model = ControlModel(
        WaypointController(),
        dt=dt,
        n_inputs=2,
        n_outputs=3,
        params=square_params(mode, **dict(params or {})),
    )
    plant = DifferentialDrive()
    state, u = np.zeros(3), np.zeros(2)
    times, poses, x_hats = [], [], []
    for k in range(round(max_time_s / dt) + 1):
        y = plant.output(k * dt, state)
        u = model.step(u, y, t=k * dt)
        times.append(k * dt)
        poses.append(y)
        x_hats.append(model.x_hat)
        if model.x_hat[1] == HOLDING:
            break
        state = plant.step(state, u, dt)
    return _finish(f"SIL {mode.upper()}", times, poses, x_hats)


def run_sim_board(
    mode: str,
    *,
    dt: float = DEFAULT_DT,
    max_time_s: float = 120.0,
    params: Mapping[str, Any] | None = None,
    noise_std_m: float = 0.0005,
    noise_std_rad: float = 0.005,
    seed: int = 0,
) -> SquareRun:
    """The controller through FrisbeeBot on a SimBoard (pin-level plant, noisy mocap)."""
    vehicle = FrisbeeBot(name="frisbee", dt=dt)
    plant = vehicle.simulated_hardware(initial_state=None, dt=dt)
    board = SimBoard(vehicle.profile, plant=plant, dt=dt)
    vehicle.pose_source = SimulatedMocap(
        plant, noise_std_m=noise_std_m, noise_std_rad=noise_std_rad, seed=seed
    )
    vehicle.connect(board, watchdog_s=0.5)  # primes: one idle exchange, as the runtime
    model = ControlModel(
        WaypointController(),
        dt=dt,
        n_inputs=2,
        n_outputs=3,
        params=square_params(mode, **dict(params or {})),
    )
    times, poses, x_hats = [], [], []
    for k in range(round(max_time_s / dt) + 1):
        y = vehicle.sense(k, k * dt)
        u_next = model.step(vehicle.u, y, t=k * dt)
        times.append(k * dt)
        poses.append(y)
        x_hats.append(model.x_hat)
        if model.x_hat[1] == HOLDING:
            break
        vehicle.apply(u_next)
        vehicle.exchange()
    return _finish(f"sim board {mode.upper()}", times, poses, x_hats)


def result_from_recording(path: str | Path, agent: str, *, label: str) -> SquareRun:
    """Read a ``hilswarm run`` recording: ``/<agent>/y`` and ``/<agent>/x_hat`` by tick.

    ``x_hat`` recorded at tick ``k`` is the controller's state after computing from ``y_k``.
    """
    y_by_k: dict[int, tuple[float, list[float]]] = {}
    x_by_k: dict[int, list[float]] = {}
    for topic, _, message in iter_messages(path, [f"/{agent}/y", f"/{agent}/x_hat"]):
        if topic.endswith("/y"):
            y_by_k[int(message["k"])] = (float(message["t"]), message["values"])
        else:
            x_by_k[int(message["k"])] = message["values"]
    ticks = sorted(k for k in y_by_k if k + 1 in x_by_k)
    return _finish(
        label,
        [y_by_k[k][0] for k in ticks],
        [y_by_k[k][1] for k in ticks],
        [x_by_k[k + 1] for k in ticks],
    )

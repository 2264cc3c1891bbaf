"""The three simulation scenarios of thesis §4.5, shared by the tests and the reproduction script.

* ``descend`` (§4.5.1) — descend 1 m: from altitude 2 m (z = -2) to altitude 1 m (z = -1).
* ``turn`` (§4.5.2) — at (1, 1) facing +x, turn in place to face the origin (ψ = -135°).
* ``forward`` (§4.5.3) — from (1, 1) at altitude 1 m, heading -125° (10° off the bearing of
  the origin), fly to (0, 0) at altitude 1 m.

World frame NED (z down; altitude = -z), see :mod:`hilswarm.agents.sim.blimp`. Each run is a
software-in-the-loop simulation: :class:`~hilswarm.agents.control.ControlModel` runs
:class:`~hilswarm.agents.controllers.blimp_flight.BlimpFlightController` once per tick on the
plant's output, the input is held over the tick and :class:`BlimpPlant` is integrated with RK4.
Unlike the thesis (which removed the hardware limits for the forward flight and stopped it at
5 s because the inputs thrashed), every scenario keeps the limits (±0.0637 N, μ ∈ [-π, 0]) and
runs until the blimp has settled.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from hilswarm.agents.control import ControlModel
from hilswarm.agents.controllers.blimp_flight import BlimpFlightController, Mode, StateIndex
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.blimp import BlimpPlant, wrap_angle
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS

__all__ = [
    "SCENARIOS",
    "Scenario",
    "ScenarioResult",
    "reversal_count",
    "run_board_scenario",
    "run_scenario",
    "saturation_count",
]


@dataclass(frozen=True)
class Scenario:
    """One §4.5 scenario.

    Attributes:
        name: short name.
        title: what it reproduces.
        initial_pose: ``[x, y, z, ψ]`` at rest [m, world NED; rad].
        params: controller parameters (waypoint, heading, ...).
        duration_s: simulated time [s].
    """

    name: str
    title: str
    initial_pose: tuple[float, float, float, float]
    params: Mapping[str, Any]
    duration_s: float


SCENARIOS: dict[str, Scenario] = {
    "descend": Scenario(
        name="descend",
        title="§4.5.1 vertical motion: descend 1 m",
        initial_pose=(0.0, 0.0, -2.0, 0.0),
        params={"waypoint": (0.0, 0.0, -1.0)},
        duration_s=25.0,
    ),
    "turn": Scenario(
        name="turn",
        title="§4.5.2 turn in place at (1, 1) from facing +x to facing the origin (-135°)",
        initial_pose=(1.0, 1.0, -1.0, 0.0),
        params={"waypoint": (1.0, 1.0, -1.0), "heading": math.atan2(-1.0, -1.0)},
        duration_s=25.0,
    ),
    "forward": Scenario(
        name="forward",
        title="§4.5.3 forward flight from (1, 1, 1) to (0, 0, 1) starting 10° off",
        initial_pose=(1.0, 1.0, -1.0, math.radians(-125.0)),
        params={"waypoint": (0.0, 0.0, -1.0)},
        duration_s=40.0,
    ),
}


@dataclass
class ScenarioResult:
    """Time histories of one run (row k = tick k, before the input u_{k+1} is applied).

    Attributes:
        scenario: the scenario run.
        t: time [s], shape (N,).
        states: plant state (12) at t, shape (N, 12) — see :class:`BlimpPlant`.
        inputs: input applied from t to t + dt, shape (N, 3): [T_l, T_r (N), μ (rad)].
        modes: controller mode at t (:class:`Mode` values), shape (N,).
        dt: control period [s].
    """

    scenario: Scenario
    t: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    modes: np.ndarray
    dt: float
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def final_state(self) -> np.ndarray:
        """Plant state at the end [12]."""
        return self.states[-1]

    def final_error(self) -> dict[str, float]:
        """End errors: horizontal distance [m], altitude [m], heading [rad], speed [m/s]."""
        target = np.asarray(self.scenario.params["waypoint"], dtype=float)
        x = self.final_state
        heading = self.scenario.params.get("heading")
        if heading is None:
            heading = self.extras.get("hold_heading", x[5])
        return {
            "distance_m": float(np.hypot(x[0] - target[0], x[1] - target[1])),
            "altitude_m": float(x[2] - target[2]),
            "heading_rad": float(wrap_angle(x[5] - heading)),
            "speed_m_s": float(np.linalg.norm(x[6:9])),
            "yaw_rate_rad_s": float(x[11]),
        }

    def saturations(self) -> dict[str, int]:
        """Ticks at which each thrust sat at ±thrust_limit_n, and ticks with the servo at an
        end stop of its travel (μ = -π or μ = 0; μ = 0 is *by design* the forward-thrust
        angle, so ``servo_end_stop`` counts time spent thrusting forward, not a problem).
        """
        p = DEFAULT_BLIMP_PARAMS
        counts = saturation_count(
            self.inputs,
            lower=(-p.thrust_limit_n, -p.thrust_limit_n, p.thrust_angle_min_rad),
            upper=(p.thrust_limit_n, p.thrust_limit_n, p.thrust_angle_max_rad),
        )
        counts["servo_end_stop"] = counts.pop("thrust_angle")
        return counts

    def reversals(self, modes: Sequence[Mode] | None = None) -> dict[str, int]:
        """Input direction reversals (chattering), optionally only inside ``modes``."""
        mask = None if modes is None else np.isin(self.modes, [int(m) for m in modes])
        p = DEFAULT_BLIMP_PARAMS
        spans = (
            2 * p.thrust_limit_n,
            2 * p.thrust_limit_n,
            p.thrust_angle_max_rad - p.thrust_angle_min_rad,
        )
        return {
            name: reversal_count(self.inputs[:, i], threshold=0.01 * spans[i], mask=mask)
            for i, name in enumerate(("thrust_left", "thrust_right", "thrust_angle"))
        }

    def mode_switches(self) -> int:
        """Number of mode changes during the run."""
        return int(np.count_nonzero(np.diff(self.modes)))


def saturation_count(
    inputs: np.ndarray, *, lower: Sequence[float], upper: Sequence[float], tol: float = 1e-9
) -> dict[str, int]:
    """Per input, the number of samples at (or beyond) a limit."""
    names = ("thrust_left", "thrust_right", "thrust_angle")
    return {
        name: int(
            np.count_nonzero((inputs[:, i] <= lower[i] + tol) | (inputs[:, i] >= upper[i] - tol))
        )
        for i, name in enumerate(names)
    }


def reversal_count(signal: np.ndarray, *, threshold: float, mask: np.ndarray | None = None) -> int:
    """How often a signal changes direction by steps larger than ``threshold``.

    Only increments larger than ``threshold`` in magnitude count as moves; a reversal is a move
    whose sign is opposite to the previous move. Thrashing (bang-bang chattering) gives about
    one reversal per sample; a smooth manoeuvre gives a handful.
    """
    values = np.asarray(signal, dtype=float)
    steps = np.diff(values)
    if mask is not None:
        keep = np.asarray(mask, dtype=bool)
        steps = steps[keep[1:] & keep[:-1]]
    moves = np.sign(steps[np.abs(steps) > threshold])
    return int(np.count_nonzero(moves[1:] != moves[:-1]))


def run_scenario(
    scenario: Scenario | str,
    *,
    dt: float = 0.05,
    substeps: int = 2,
    duration_s: float | None = None,
    controller_params: Mapping[str, Any] | None = None,
) -> ScenarioResult:
    """Simulate a scenario (software in the loop) and return its histories.

    Args:
        scenario: a :class:`Scenario` or a name in :data:`SCENARIOS`.
        dt: control period [s].
        substeps: RK4 steps per control period.
        duration_s: override the scenario's duration [s].
        controller_params: extra/overriding controller parameters (e.g. a coarse schedule).

    Raises:
        PlantError: unknown scenario name.
    """
    if isinstance(scenario, str):
        if scenario not in SCENARIOS:
            raise PlantError(
                f"unknown blimp scenario {scenario!r}; expected one of {sorted(SCENARIOS)}"
            )
        scenario = SCENARIOS[scenario]
    plant = BlimpPlant()
    controller = BlimpFlightController()
    params = {**scenario.params, **(controller_params or {})}
    model = ControlModel(controller, dt=dt, n_inputs=3, n_outputs=4, params=params)
    span_s = duration_s if duration_s is not None else scenario.duration_s
    steps = round(span_s / dt)
    x = plant.initial_state(scenario.initial_pose)
    u = np.array([0.0, 0.0, 0.0])
    t = np.arange(steps + 1) * dt
    states = np.empty((steps + 1, 12))
    inputs = np.empty((steps + 1, 3))
    modes = np.empty(steps + 1, dtype=int)
    for k in range(steps + 1):
        states[k] = x
        y = plant.output(t[k], x)
        u = plant.saturate(model.step(u, y, t=t[k]))
        inputs[k] = u
        modes[k] = int(model.x_hat[StateIndex.MODE])
        if k < steps:
            x = plant.advance(t[k], x, u, dt, method="rk4", substeps=substeps)
    extras = {"hold_heading": float(model.x_hat[StateIndex.HOLD_PSI])}
    return ScenarioResult(scenario, t, states, inputs, modes, dt, extras)


def run_board_scenario(
    scenario: Scenario | str,
    *,
    dt: float = 0.05,
    duration_s: float | None = None,
    controller_params: Mapping[str, Any] | None = None,
    vehicle_params: Mapping[str, Any] | None = None,
) -> ScenarioResult:
    """Run a scenario through the whole pin-level chain (simulated hardware in the loop).

    :class:`~hilswarm.agents.vehicles.blimpduino.Blimpduino` on a ``sim://fio``
    :class:`~hilswarm.agents.link.sim_board.SimBoard` whose plant is the vehicle's
    :class:`~hilswarm.agents.sim.blimp.BlimpPinPlant`: thrusts become PWM duties through the
    calibration, the servo angle a pulse width, and back. Tick order as in an agent:
    sense y_k, controller, apply u_{k+1}, exchange (the plant advances dt). The pose comes
    straight from the plant (noise-free motion capture).
    """
    from hilswarm.agents.link.sim_board import SimBoard  # noqa: PLC0415 - avoid a cycle
    from hilswarm.agents.vehicles.blimpduino import Blimpduino  # noqa: PLC0415

    if isinstance(scenario, str):
        if scenario not in SCENARIOS:
            raise PlantError(
                f"unknown blimp scenario {scenario!r}; expected one of {sorted(SCENARIOS)}"
            )
        scenario = SCENARIOS[scenario]
    vehicle = Blimpduino(name="blimp", dt=dt, params=vehicle_params)
    plant = vehicle.simulated_hardware(initial_state=scenario.initial_pose, dt=dt)
    board = SimBoard("fio", plant=plant, dt=dt)
    vehicle.pose_source = plant
    vehicle.connect(board, watchdog_s=0.5)
    params = {**scenario.params, **(controller_params or {})}
    model = ControlModel(BlimpFlightController(), dt=dt, n_inputs=3, n_outputs=4, params=params)
    span_s = duration_s if duration_s is not None else scenario.duration_s
    steps = round(span_s / dt)
    t = np.arange(steps + 1) * dt
    states = np.empty((steps + 1, 12))
    inputs = np.empty((steps + 1, 3))
    modes = np.empty(steps + 1, dtype=int)
    for k in range(steps + 1):
        states[k] = plant.state
        y = vehicle.sense(k, float(t[k]))
        vehicle.apply(model.step(vehicle.u, y, t=float(t[k])))
        inputs[k] = vehicle.u
        modes[k] = int(model.x_hat[StateIndex.MODE])
        if k < steps:
            vehicle.exchange()
    board.close()
    extras = {
        "hold_heading": float(model.x_hat[StateIndex.HOLD_PSI]),
        "battery_v": float(plant.battery.volts),
        "safe_mode": vehicle.safe_mode,
    }
    return ScenarioResult(scenario, t, states, inputs, modes, dt, extras)

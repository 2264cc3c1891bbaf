"""Blimpduino flight controller: the mode logic of thesis §4.4.3 around gain-scheduled LQR.

Input ``y`` = ``[x, y, z, ψ]`` (position [m, world NED, z down], heading [rad]) — what motion
capture gives. Output ``u`` = ``[T_left, T_right, μ]`` (thrusts [N], thrust angle [rad]).

**Estimator.** Velocities are not measured: an α-β tracker per navigation coordinate
(ψ wrapped) estimates the world velocity and yaw rate; body velocities follow by rotating
with ψ (roll and pitch are assumed zero, as in the thesis' reduced model).

**Mode machine** (explicit, in :func:`next_mode`; precedence top to bottom, each with
hysteresis — a mode is *entered* beyond the ``*_enter`` threshold and *left* only inside the
smaller ``*_exit`` threshold, so measurement noise cannot toggle it):

=========  ===============================================  =============================
mode       entered when                                     left when
=========  ===============================================  =============================
VERTICAL   |z - z_wp| > z_enter                             |z - z_wp| < z_exit and |ż| small
TURN       |heading error| > heading_enter                  |error| < heading_exit, |ψ̇| small
FORWARD    horizontal distance > distance_enter             distance to go < distance_exit
HOLD       otherwise (at the waypoint, heading held)        one of the above is needed
=========  ===============================================  =============================

The heading error in TURN is to the bearing of the waypoint when it is far, else to the
``heading`` parameter (or the heading held on arrival). FORWARD flies a straight leg from
where it started to the waypoint, correcting small heading errors on the fly.

**Control law** per mode, with the gain schedule of
:mod:`~hilswarm.agents.controllers.blimp_trim`: ``T = T* - K(V, ψ) (s - s_ref)`` where s is
the estimated reduced state ``[u, v, w, r, x, y, z, ψ]``; the thrust angle is set by the mode
(VERTICAL: μ = -π/2, thrust up; others: μ = 0, thrust forward). In FORWARD the speed
reference is ``min(cruise_speed, distance_to_go / approach_time_s)`` and the gains are
interpolated at that airspeed; the position reference is the closest point of the leg, so
only the cross-track error is fed back.

**No chattering.** The thesis' forward-flight simulation thrashed its inputs and was cut at
5 s. Here: hysteresis on every mode switch; μ never changes inside a mode; the thrust is
rate-limited (``thrust_rate_n_s``) and the servo slews at ``servo_rate_rad_s``; while the
servo is still slewing towards the mode's angle the thrusts are faded in smoothly over the last
``blend_angle`` of the slew (:func:`servo_blend`), instead of thrusting in a wrong direction.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from enum import IntEnum
from typing import Any, ClassVar

import numpy as np
from hilswarm.agents.control import Controller, TickInput, param_vector
from hilswarm.agents.controllers.blimp_trim import (
    DEFAULT_GRID,
    DEFAULT_WEIGHTS,
    MODE_THRUST_ANGLE,
    FlightMode,
    GainSchedule,
    ModeWeights,
    ScheduleGrid,
    gain_schedule,
)
from hilswarm.agents.errors import ControllerError
from hilswarm.agents.sim.blimp import wrap_angle
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS

__all__ = [
    "BlimpFlightController",
    "Mode",
    "ModeInputs",
    "StateIndex",
    "next_mode",
    "servo_blend",
]


class Mode(IntEnum):
    """Flight modes (stored as a number in ``x_hat``)."""

    VERTICAL = 0
    TURN = 1
    FORWARD = 2
    HOLD = 3


#: The LQR each mode uses.
MODE_LQR: dict[Mode, FlightMode] = {
    Mode.VERTICAL: FlightMode.VERTICAL,
    Mode.TURN: FlightMode.HOVER,
    Mode.FORWARD: FlightMode.FORWARD,
    Mode.HOLD: FlightMode.HOVER,
}


class StateIndex(IntEnum):
    """Layout of the controller state ``x_hat``."""

    STARTED = 0  # 0 until the estimator has seen a measurement
    MODE = 1
    X = 2  # estimated position [m, world]
    Y = 3
    Z = 4
    PSI = 5  # estimated heading [rad]
    VX = 6  # estimated world velocity [m/s]
    VY = 7
    VZ = 8
    R = 9  # estimated yaw rate [rad/s]
    LEG_X = 10  # start of the forward leg [m, world]
    LEG_Y = 11
    HOLD_X = 12  # position held in TURN/HOLD [m, world]
    HOLD_Y = 13
    HOLD_PSI = 14  # heading held in HOLD when no heading parameter is given [rad]
    T_LEFT = 15  # last commanded input
    T_RIGHT = 16
    MU = 17
    SWITCHES = 18  # number of mode switches so far
    MODE_TIME = 19  # time spent in the current mode [s]


N_STATES = len(StateIndex)


class ModeInputs:
    """What the mode machine looks at in one tick (all errors as measured/estimated).

    Attributes:
        altitude_error: z - z_wp [m] (world z down).
        vertical_speed: ż [m/s].
        heading_error: target heading - ψ [rad, wrapped].
        yaw_rate: ψ̇ [rad/s].
        far: the waypoint is far enough horizontally to fly to it.
    """

    __slots__ = ("altitude_error", "far", "heading_error", "vertical_speed", "yaw_rate")

    def __init__(
        self,
        *,
        altitude_error: float,
        vertical_speed: float,
        heading_error: float,
        yaw_rate: float,
        far: bool,
    ) -> None:
        self.altitude_error = altitude_error
        self.vertical_speed = vertical_speed
        self.heading_error = heading_error
        self.yaw_rate = yaw_rate
        self.far = far


def servo_blend(angle_error: float, blend_angle: float) -> float:
    """Thrust scale 0..1 while the servo is ``angle_error`` [rad] from its target.

    0 beyond ``blend_angle``, 1 on target, smooth (raised cosine) in between.
    """
    fraction = min(abs(angle_error) / blend_angle, 1.0)
    return 0.5 * (1.0 + math.cos(math.pi * fraction))


def next_mode(mode: Mode, seen: ModeInputs, params: Mapping[str, Any]) -> Mode:
    """The mode machine of §4.4.3 with hysteresis (see module docstring)."""
    z_err = abs(seen.altitude_error)
    if z_err > params["z_enter"] or (
        mode is Mode.VERTICAL
        and not (z_err < params["z_exit"] and abs(seen.vertical_speed) < params["settle_speed"])
    ):
        return Mode.VERTICAL
    psi_err = abs(seen.heading_error)
    if psi_err > params["heading_enter"] or (
        mode is Mode.TURN
        and not (psi_err < params["heading_exit"] and abs(seen.yaw_rate) < params["settle_rate"])
    ):
        return Mode.TURN
    return Mode.FORWARD if seen.far else Mode.HOLD


class BlimpFlightController(Controller):
    """Waypoint flight of the Blimpduino: mode machine + gain-scheduled LQR (thesis §4.4).

    Parameters (replaceable at run time through ``ControlModel.set_params``):
        waypoint: ``[x, y, z]`` target [m, world NED; z = -altitude].
        heading: heading to hold at the waypoint [rad] (``None``: keep the arrival heading).
        cruise_speed: forward-flight airspeed [m/s] (within the schedule's airspeeds).
        approach_time_s: the speed reference is distance to go / this near the goal [s].
        z_enter, z_exit: altitude error thresholds of VERTICAL [m].
        heading_enter, heading_exit: heading error thresholds of TURN [rad].
        distance_enter, distance_exit: horizontal distance thresholds of FORWARD [m].
        settle_speed: |ż| below which VERTICAL may end [m/s].
        settle_rate: |ψ̇| below which TURN may end [rad/s].
        thrust_rate_n_s: largest change of a thrust command per second [N/s].
        servo_rate_rad_s: how fast the thrust angle command may slew [rad/s].
        blend_angle: thrust is faded in over the last ``blend_angle`` [rad] of a servo slew.
        estimator_alpha, estimator_beta: α-β tracker gains (0 < α <= 1, 0 < β <= 2).
        schedule_airspeeds, schedule_headings: the gain-schedule grid (coarser = faster).
        weights_vertical, weights_hover, weights_forward, weight_thrust_n: LQR weights as
            largest acceptable deviations (Bryson's rule, see ``ModeWeights``).
    """

    n_states: ClassVar[int] = N_STATES
    state_names: ClassVar[tuple[str, ...]] = tuple(index.name.lower() for index in StateIndex)
    state_units: ClassVar[Mapping[str, str]] = {
        **dict.fromkeys(("x", "y", "z", "leg_x", "leg_y", "hold_x", "hold_y"), "m"),
        **dict.fromkeys(("psi", "hold_psi", "mu"), "rad"),
        **dict.fromkeys(("vx", "vy", "vz"), "m/s"),
        "r": "rad/s",
        **dict.fromkeys(("t_left", "t_right"), "N"),
        "mode_time": "s",
    }
    default_params: ClassVar[Mapping[str, Any]] = {
        "waypoint": (0.0, 0.0, -1.0),
        "heading": None,
        "cruise_speed": 0.2,
        "approach_time_s": 2.0,
        "z_enter": 0.15,
        "z_exit": 0.02,
        "heading_enter": math.radians(20.0),
        "heading_exit": math.radians(2.0),
        "distance_enter": 0.2,
        "distance_exit": 0.03,
        "settle_speed": 0.005,
        "settle_rate": 0.01,
        "blend_angle": math.radians(20.0),
        "thrust_rate_n_s": 0.25,
        "servo_rate_rad_s": 3.0,
        "estimator_alpha": 0.8,
        "estimator_beta": 0.4,
        "schedule_airspeeds": DEFAULT_GRID.airspeeds,
        "schedule_headings": DEFAULT_GRID.headings,
        "weights_vertical": DEFAULT_WEIGHTS.vertical,
        "weights_hover": DEFAULT_WEIGHTS.hover,
        "weights_forward": DEFAULT_WEIGHTS.forward,
        "weight_thrust_n": DEFAULT_WEIGHTS.thrust_n,
    }

    _POSITIVE: ClassVar[tuple[str, ...]] = (
        "cruise_speed",
        "approach_time_s",
        "z_enter",
        "z_exit",
        "heading_enter",
        "heading_exit",
        "distance_enter",
        "distance_exit",
        "settle_speed",
        "settle_rate",
        "thrust_rate_n_s",
        "servo_rate_rad_s",
        "estimator_alpha",
        "estimator_beta",
        "blend_angle",
    )

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        merged = super().validate_params(params)
        merged["waypoint"] = param_vector(self, "waypoint", merged["waypoint"], 3)
        heading = merged["heading"]
        if heading is not None:
            if (
                isinstance(heading, bool)
                or not isinstance(heading, int | float)
                or not math.isfinite(heading)
            ):
                raise ControllerError(
                    f"{self.name}: parameter 'heading' must be a finite angle [rad] or None, "
                    f"got {heading!r}"
                )
            merged["heading"] = wrap_angle(float(heading))
        for name in self._POSITIVE:
            value = merged[name]
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not (math.isfinite(value) and value > 0)
            ):
                raise ControllerError(
                    f"{self.name}: parameter {name!r} must be a finite number > 0, got {value!r}"
                )
            merged[name] = float(value)
        for enter, leave in (
            ("z_enter", "z_exit"),
            ("heading_enter", "heading_exit"),
            ("distance_enter", "distance_exit"),
        ):
            if not merged[leave] < merged[enter]:
                raise ControllerError(
                    f"{self.name}: hysteresis needs {leave} ({merged[leave]}) < {enter} "
                    f"({merged[enter]})"
                )
        if merged["estimator_alpha"] > 1 or merged["estimator_beta"] > 2:
            raise ControllerError(
                f"{self.name}: estimator_alpha must be in (0, 1] and estimator_beta in (0, 2], "
                f"got {merged['estimator_alpha']} and {merged['estimator_beta']}"
            )
        try:
            grid = ScheduleGrid(
                airspeeds=tuple(float(v) for v in merged["schedule_airspeeds"]),
                headings=merged["schedule_headings"],
            )
        except (TypeError, ValueError) as exc:
            raise ControllerError(f"{self.name}: bad schedule grid: {exc}") from None
        merged["schedule_airspeeds"] = grid.airspeeds
        weights = {}
        for mode in FlightMode:
            key = f"weights_{mode.value}"
            size = len(getattr(DEFAULT_WEIGHTS, mode.value))
            vector = param_vector(self, key, merged[key], size)
            if np.any(vector <= 0):
                raise ControllerError(
                    f"{self.name}: parameter {key!r} must hold {size} deviations > 0, got {vector}"
                )
            weights[mode.value] = tuple(float(v) for v in vector)
            merged[key] = weights[mode.value]
        thrust_weight = merged["weight_thrust_n"]
        if (
            isinstance(thrust_weight, bool)
            or not isinstance(thrust_weight, int | float)
            or not (math.isfinite(thrust_weight) and thrust_weight > 0)
        ):
            raise ControllerError(
                f"{self.name}: parameter 'weight_thrust_n' must be > 0 [N], got {thrust_weight!r}"
            )
        merged["weight_thrust_n"] = float(thrust_weight)
        self.schedule(merged)  # build (or fetch) the gain schedule now, not at the first tick
        if not 0 < merged["cruise_speed"] <= grid.airspeeds[-1]:
            raise ControllerError(
                f"{self.name}: cruise_speed {merged['cruise_speed']} m/s must be within the "
                f"schedule's airspeeds (<= {grid.airspeeds[-1]} m/s)"
            )
        return merged

    def initial_state(self, params: Mapping[str, Any]) -> np.ndarray:
        state = np.zeros(N_STATES)
        state[StateIndex.MODE] = Mode.HOLD
        return state

    @staticmethod
    def schedule(params: Mapping[str, Any]) -> GainSchedule:
        """The (cached) gain schedule these parameters use."""
        grid = ScheduleGrid(
            airspeeds=tuple(params["schedule_airspeeds"]), headings=params["schedule_headings"]
        )
        weights = ModeWeights(
            vertical=params["weights_vertical"],
            hover=params["weights_hover"],
            forward=params["weights_forward"],
            thrust_n=params["weight_thrust_n"],
        )
        return gain_schedule(DEFAULT_BLIMP_PARAMS, grid, weights)

    # -- one tick ----------------------------------------------------------------------------

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        if tick.y.shape != (4,):
            raise ControllerError(
                f"{self.name}: y must be [x, y, z, yaw] (4 values), got shape {tick.y.shape}"
            )
        state = np.array(x_hat, dtype=float)
        self._estimate(state, tick.y, tick.u, tick.dt, params)
        mode = Mode(int(state[StateIndex.MODE]))
        waypoint = params["waypoint"]
        position = state[[StateIndex.X, StateIndex.Y]]
        psi = state[StateIndex.PSI]
        to_wp = waypoint[:2] - position
        distance = float(np.hypot(*to_wp))

        leg = state[[StateIndex.LEG_X, StateIndex.LEG_Y]]
        path_heading = math.atan2(*(waypoint[:2] - leg)[::-1])
        direction = np.array([math.cos(path_heading), math.sin(path_heading)])
        to_go = float(direction @ to_wp)
        far = distance > params["distance_enter"] or (
            mode is Mode.FORWARD and to_go > params["distance_exit"]
        )
        if far:
            target = path_heading if mode is Mode.FORWARD else math.atan2(to_wp[1], to_wp[0])
        elif params["heading"] is not None:
            target = params["heading"]
        else:
            target = path_heading if mode is Mode.FORWARD else state[StateIndex.HOLD_PSI]
        seen = ModeInputs(
            altitude_error=float(state[StateIndex.Z] - waypoint[2]),
            vertical_speed=float(state[StateIndex.VZ]),
            heading_error=wrap_angle(target - psi),
            yaw_rate=float(state[StateIndex.R]),
            far=far,
        )
        new_mode = next_mode(mode, seen, params)
        if new_mode is not mode:
            self._enter(
                state=state,
                mode=new_mode,
                previous=mode,
                far=far,
                waypoint=waypoint,
                path_heading=path_heading,
            )
            mode = new_mode
        else:
            state[StateIndex.MODE_TIME] += tick.dt
        u_next = self._control(state, mode, far, params, tick.dt)
        state[[StateIndex.T_LEFT, StateIndex.T_RIGHT, StateIndex.MU]] = u_next
        return u_next, state

    def _estimate(
        self,
        state: np.ndarray,
        y: np.ndarray,
        u: np.ndarray,
        dt: float,
        params: Mapping[str, Any],
    ) -> None:
        pos = [StateIndex.X, StateIndex.Y, StateIndex.Z, StateIndex.PSI]
        vel = [StateIndex.VX, StateIndex.VY, StateIndex.VZ, StateIndex.R]
        if not state[StateIndex.STARTED]:
            state[pos] = y
            state[vel] = 0.0
            state[StateIndex.STARTED] = 1.0
            state[[StateIndex.HOLD_X, StateIndex.HOLD_Y]] = y[:2]
            state[[StateIndex.LEG_X, StateIndex.LEG_Y]] = y[:2]
            state[StateIndex.HOLD_PSI] = y[3]
            state[[StateIndex.T_LEFT, StateIndex.T_RIGHT, StateIndex.MU]] = u
            return
        alpha, beta = params["estimator_alpha"], params["estimator_beta"]
        predicted = state[pos] + state[vel] * dt
        residual = y - predicted
        residual[3] = wrap_angle(residual[3])
        state[pos] = predicted + alpha * residual
        state[StateIndex.PSI] = wrap_angle(state[StateIndex.PSI])
        state[vel] = state[vel] + beta / dt * residual

    def _enter(
        self,
        *,
        state: np.ndarray,
        mode: Mode,
        previous: Mode,
        far: bool,
        waypoint: np.ndarray,
        path_heading: float,
    ) -> None:
        state[StateIndex.MODE] = mode
        state[StateIndex.MODE_TIME] = 0.0
        state[StateIndex.SWITCHES] += 1
        here = state[[StateIndex.X, StateIndex.Y]]
        if mode is Mode.FORWARD:
            state[[StateIndex.LEG_X, StateIndex.LEG_Y]] = here
        elif mode is Mode.HOLD:
            state[[StateIndex.HOLD_X, StateIndex.HOLD_Y]] = waypoint[:2]
            state[StateIndex.HOLD_PSI] = (
                path_heading if previous is Mode.FORWARD else state[StateIndex.PSI]
            )
        else:
            state[[StateIndex.HOLD_X, StateIndex.HOLD_Y]] = here if far else waypoint[:2]
            if previous is not Mode.HOLD:
                state[StateIndex.HOLD_PSI] = state[StateIndex.PSI]

    def _control(
        self, state: np.ndarray, mode: Mode, far: bool, params: Mapping[str, Any], dt: float
    ) -> np.ndarray:
        schedule = self.schedule(params)
        lqr_mode = MODE_LQR[mode]
        waypoint = params["waypoint"]
        psi = float(state[StateIndex.PSI])
        c, s = math.cos(psi), math.sin(psi)
        vx, vy = state[StateIndex.VX], state[StateIndex.VY]
        measured = np.array(
            [
                c * vx + s * vy,
                -s * vx + c * vy,
                state[StateIndex.VZ],
                state[StateIndex.R],
                state[StateIndex.X],
                state[StateIndex.Y],
                state[StateIndex.Z],
                psi,
            ]
        )
        reference = measured.copy()
        reference[:4] = 0.0
        airspeed = 0.0
        schedule_heading = psi
        if mode is Mode.VERTICAL:
            reference[6] = waypoint[2]
        elif mode is Mode.FORWARD:
            leg = state[[StateIndex.LEG_X, StateIndex.LEG_Y]]
            path = waypoint[:2] - leg
            length = float(np.hypot(*path))
            direction = path / length if length > 0 else np.array([c, s])
            path_heading = math.atan2(direction[1], direction[0])
            to_go = float(direction @ (waypoint[:2] - measured[4:6]))
            airspeed = min(params["cruise_speed"], max(to_go, 0.0) / params["approach_time_s"])
            reference[0] = airspeed
            closest = waypoint[:2] - to_go * direction
            reference[4:6] = closest
            reference[7] = path_heading
            schedule_heading = path_heading
        else:  # TURN / HOLD: hover at the held point, turn to the target heading
            reference[4:6] = state[[StateIndex.HOLD_X, StateIndex.HOLD_Y]]
            if mode is Mode.TURN and far:
                to_wp = waypoint[:2] - measured[4:6]
                reference[7] = math.atan2(to_wp[1], to_wp[0])
            elif params["heading"] is not None:
                reference[7] = params["heading"]
            else:
                reference[7] = state[StateIndex.HOLD_PSI]
        error = measured - reference
        error[7] = wrap_angle(error[7])
        gain = schedule.gain(lqr_mode, airspeed, schedule_heading)
        trim = schedule.trim_input(lqr_mode, airspeed, schedule_heading)
        thrusts = trim[:2] - gain @ error

        # Thrust angle: slew towards the mode's angle; blend thrust while the servo moves.
        target_mu = MODE_THRUST_ANGLE[lqr_mode]
        dt_rate = params["servo_rate_rad_s"] * dt
        previous_mu = state[StateIndex.MU]
        mu = previous_mu + min(max(target_mu - previous_mu, -dt_rate), dt_rate)
        thrusts = thrusts * servo_blend(mu - target_mu, params["blend_angle"])

        limit = DEFAULT_BLIMP_PARAMS.thrust_limit_n
        thrusts = np.clip(thrusts, -limit, limit)
        step = params["thrust_rate_n_s"] * dt
        previous = state[[StateIndex.T_LEFT, StateIndex.T_RIGHT]]
        thrusts = previous + np.clip(thrusts - previous, -step, step)
        return np.array([thrusts[0], thrusts[1], mu])

"""Rotate-then-drive waypoint control of a differential-drive vehicle (thesis §5.4).

The logic of the thesis' Frisbee controller:

* if the vehicle does not point at the current waypoint (bearing error above
  ``pointing_tolerance_rad``), pivot in place towards it along the shorter arc, until the error
  is below half that tolerance (the half is hysteresis, so the vehicle does not chatter between
  pivoting and driving at the tolerance's edge);
* otherwise drive straight at it, both wheels at the forward speed ``V`` given by a P or PI law
  on the distance ``e`` [m] to the waypoint (a SISO problem, input V, output e):
  ``V = kp e`` (mode ``"p"``) or ``V = kp e + ki ∫e dt`` (mode ``"pi"``), with the integral
  accumulated by the trapezoid rule, as in the thesis. Anti-windup: the integral restarts at
  every pivot and every new waypoint, and does not grow while V is at the speed limit;
* within ``waypoint_tolerance_m`` of a waypoint, switch to the next; at the last one stop and
  hold (if pushed more than twice the tolerance away, drive back).

Inputs ``u = [v_left, v_right]`` wheel speeds [m/s]; outputs ``y = [x, y, psi]`` (position [m,
world frame], heading [rad, from world x towards world y]). The waypoint list (param
``waypoints``, ``[[x, y], ...]`` [m, world frame]) may be replaced at run time: a new list
restarts at its first waypoint.

The controller state ``x_hat`` (recorded on ``/<agent>/x_hat``) is
``[waypoint_index, phase, integral_m_s, previous_error_m]`` with phase 0 = pivoting, 1 =
driving, 2 = holding at the last waypoint, ``previous_error_m`` = -1 when there is no previous
sample in this leg. A new waypoint list (``hilswarm set``) restarts that state at its first
waypoint (:meth:`WaypointController.params_changed`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
from hilswarm.agents.control import Controller, TickInput
from hilswarm.agents.errors import ControllerError
from hilswarm.agents.sim.differential_drive import (
    FRISBEE_GEOMETRY,
    scale_wheel_speeds,
    wheel_speeds,
    wrap_angle,
)

#: Names of the entries of x_hat.
X_HAT_FIELDS = ("waypoint_index", "phase", "integral_m_s", "previous_error_m")
#: Phases (x_hat[1]).
PIVOTING, DRIVING, HOLDING = 0, 1, 2
_NO_PREVIOUS = -1.0


def _positive(params: Mapping[str, Any], key: str, *, allow_zero: bool = False) -> float:
    value = params[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ControllerError(f"waypoint controller param {key!r} must be a number, got {value!r}")
    if value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ControllerError(f"waypoint controller param {key!r} must be {bound}, got {value!r}")
    return float(value)


def parse_waypoints(value: Any, *, owner: str = "waypoint controller") -> np.ndarray:
    """``[[x, y], ...]`` [m] -> array of shape (n, 2); raises ControllerError naming the entry."""
    if isinstance(value, str | bytes) or not isinstance(value, Sequence | np.ndarray):
        raise ControllerError(f"{owner} param 'waypoints' must be a list of [x, y], got {value!r}")
    if len(value) == 0:
        raise ControllerError(f"{owner} param 'waypoints' must hold at least one [x, y]")
    points = []
    for i, point in enumerate(value):
        try:
            x, y = (float(c) for c in point)
        except (TypeError, ValueError):
            raise ControllerError(
                f"{owner} param 'waypoints[{i}]' must be [x, y] in metres, got {point!r}"
            ) from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ControllerError(f"{owner} param 'waypoints[{i}]' is not finite: {point!r}")
        points.append((x, y))
    return np.array(points, dtype=float)


class WaypointController(Controller):
    """P or PI rotate-then-drive waypoint follower (thesis §5.4) for ``u = [v_left, v_right]``.

    Params:
        waypoints: ``[[x, y], ...]`` [m, world frame], visited in order; replaceable at run time.
        mode: ``"p"`` or ``"pi"``.
        kp: proportional gain [1/s] (forward speed per metre of distance).
        ki: integral gain [1/s²] (used in mode ``"pi"``).
        pointing_tolerance_rad: bearing error [rad] above which the vehicle pivots.
        waypoint_tolerance_m: distance [m] at which a waypoint counts as reached.
        turn_gain: pivot yaw rate per radian of bearing error [1/s].
        max_wheel_speed_m_s: wheel speed limit [m/s] (commands are scaled to it).
        track_width_m: wheel track [m] (converts yaw rate to wheel speeds).
    """

    n_states: ClassVar[int] = len(X_HAT_FIELDS)
    state_names: ClassVar[tuple[str, ...]] = X_HAT_FIELDS
    state_units: ClassVar[Mapping[str, str]] = {"integral_m_s": "m s", "previous_error_m": "m"}
    #: (validated waypoints, parsed points) of the last list step() saw.
    _route_cache: tuple[Any, list[tuple[float, float]]] | None = None
    default_params: ClassVar[Mapping[str, Any]] = {
        "waypoints": [[0.0, 0.0]],
        "mode": "p",
        "kp": 1.0,
        "ki": 0.2,
        "pointing_tolerance_rad": 0.1,
        "waypoint_tolerance_m": 0.005,
        "turn_gain": 3.0,
        "max_wheel_speed_m_s": FRISBEE_GEOMETRY.max_wheel_speed_m_s,
        "track_width_m": FRISBEE_GEOMETRY.track_width_m,
    }

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """Merge ``params`` over the defaults and check every value (raises ControllerError)."""
        merged = super().validate_params(params)
        # Immutable (x, y) pairs [m]: step() parses a list once and trusts it afterwards.
        merged["waypoints"] = tuple(
            (x, y) for x, y in parse_waypoints(merged["waypoints"]).tolist()
        )
        if merged["mode"] not in ("p", "pi"):
            raise ControllerError(
                f"waypoint controller param 'mode' must be 'p' or 'pi', got {merged['mode']!r}"
            )
        for key in ("kp", "turn_gain", "max_wheel_speed_m_s", "track_width_m"):
            merged[key] = _positive(merged, key)
        for key in ("ki", "waypoint_tolerance_m"):
            merged[key] = _positive(merged, key, allow_zero=True)
        merged["pointing_tolerance_rad"] = _positive(merged, "pointing_tolerance_rad")
        if merged["pointing_tolerance_rad"] >= math.pi:
            raise ControllerError(
                "waypoint controller param 'pointing_tolerance_rad' must be < π, "
                f"got {merged['pointing_tolerance_rad']!r}"
            )
        return merged

    def initial_state(self, params: Mapping[str, Any]) -> np.ndarray:
        """Start at waypoint 0, pivoting, with an empty integral."""
        del params
        return np.array([0.0, PIVOTING, 0.0, _NO_PREVIOUS])

    def params_changed(
        self, old: Mapping[str, Any], new: Mapping[str, Any], x_hat: np.ndarray
    ) -> np.ndarray:
        """A new waypoint list restarts at its first waypoint; other changes keep the state."""
        if old.get("waypoints") != new.get("waypoints"):
            return self.initial_state(new)
        return x_hat

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        """One tick: ``(u_{k+1} = [v_left, v_right] [m/s], x_hat_{k+1})``."""
        y = np.asarray(tick.y, dtype=float).reshape(-1)
        if y.size < 3:
            raise ControllerError(f"waypoint controller needs y = [x, y, psi], got {y!r}")
        x, y_pos, psi = y.tolist()[:3]
        waypoints = self._route(params["waypoints"])
        state = np.asarray(x_hat, dtype=float).tolist()
        index, phase, integral, previous = int(state[0]), int(state[1]), state[2], state[3]
        index = min(index, len(waypoints) - 1)
        tolerance = params["waypoint_tolerance_m"]

        target_x, target_y = waypoints[index]
        distance = math.hypot(target_x - x, target_y - y_pos)
        while distance <= tolerance and index < len(waypoints) - 1:
            index, phase, integral, previous = index + 1, PIVOTING, 0.0, _NO_PREVIOUS
            target_x, target_y = waypoints[index]
            distance = math.hypot(target_x - x, target_y - y_pos)
        last = index == len(waypoints) - 1
        if last and (distance <= tolerance or (phase == HOLDING and distance <= 2.0 * tolerance)):
            return np.zeros(2), np.array([index, HOLDING, 0.0, _NO_PREVIOUS])
        if phase == HOLDING:
            phase = PIVOTING

        bearing_error = wrap_angle(math.atan2(target_y - y_pos, target_x - x) - psi)
        pointing = params["pointing_tolerance_rad"]
        if abs(bearing_error) > pointing or (
            phase == PIVOTING and abs(bearing_error) > 0.5 * pointing
        ):
            yaw_rate = params["turn_gain"] * bearing_error
            v_left, v_right = wheel_speeds(0.0, yaw_rate, params["track_width_m"])
            v_left, v_right = scale_wheel_speeds(v_left, v_right, params["max_wheel_speed_m_s"])
            state = np.array([index, PIVOTING, 0.0, _NO_PREVIOUS])
            return np.array([v_left, v_right]), state

        speed, integral = self._forward_speed(distance, previous, integral, tick.dt, params)
        state = np.array([index, DRIVING, integral, distance])
        return np.array([speed, speed]), state

    def _route(self, value: Any) -> list[tuple[float, float]]:
        """The waypoints ``[(x, y), ...]`` [m], parsed once per list.

        Validated parameters hold an immutable tuple, so the parse is remembered for that very
        object; anything else (a list passed straight to step()) is parsed every time.
        """
        cached = self._route_cache
        if cached is not None and cached[0] is value:
            return cached[1]
        points = [(x, y) for x, y in parse_waypoints(value).tolist()]
        if type(value) is tuple and all(type(point) is tuple for point in value):
            self._route_cache = (value, points)
        return points

    @staticmethod
    def _forward_speed(
        error: float, previous: float, integral: float, dt: float, params: Mapping[str, Any]
    ) -> tuple[float, float]:
        """P/PI law on the distance error [m] -> (forward speed [m/s], new integral [m s])."""
        limit = params["max_wheel_speed_m_s"]
        if params["mode"] == "p":
            return min(params["kp"] * error, limit), 0.0
        if previous != _NO_PREVIOUS:
            candidate = integral + 0.5 * dt * (error + previous)  # trapezoid rule
            if params["kp"] * error + params["ki"] * candidate <= limit:
                integral = candidate  # conditional integration: no growth at the limit
        return min(params["kp"] * error + params["ki"] * integral, limit), float(integral)

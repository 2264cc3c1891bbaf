"""Keep a fixed offset from a leader: the lead/follow experiment of thesis §7.1, for a
differential-drive vehicle.

The follower hears its leader's output ``y = [x, y, psi]`` (position [m, world frame], heading
[rad]) as a neighbour and steers towards the *slot* that sits ``distance_m`` behind the leader
and ``lateral_m`` to the leader's left (negative: right), both measured in the leader's body
frame::

    slot = p_leader + R(psi_leader) [-distance_m, lateral_m]

Control law (a standard unicycle point-tracking law, smooth, no pivot phase), with ``d`` the
distance to the slot and ``e`` the bearing error to it:

* far from the slot (``d > tolerance_m``): forward speed ``V = v_ff + kp_distance d cos e``
  (negative when the slot is behind, so the follower backs up instead of turning round) and
  yaw rate ``ψ̇ = kp_heading e'``, where ``e'`` is the bearing error of whichever end
  (front or back) faces the slot;
* at the slot: ``V = v_ff``, ``ψ̇ = kp_heading (psi_leader - psi)`` (line up with the leader).

``v_ff`` is the leader's speed along the follower's heading, estimated from the last two
leader samples (zero until there are two). Wheel speeds are scaled together to the limit (the
path curvature is kept). When the leader's output is missing (``None``: no data this tick) the
follower stops (``u = [0, 0]``) and forgets its speed estimate.

``x_hat = [leader_x, leader_y, leader_psi, have_leader]``: the last leader sample and whether
it is valid (1) or not (0).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
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
X_HAT_FIELDS = ("leader_x", "leader_y", "leader_psi", "have_leader")


class OffsetFollower(Controller):
    """Follow the neighbour named by param ``leader`` at a fixed offset; ``u = [v_left, v_right]``.

    Params:
        leader: agent name of the leader (must be one of this agent's neighbours).
        distance_m: how far behind the leader [m, leader body frame].
        lateral_m: how far to the leader's left [m, leader body frame]; negative = right.
        kp_distance: forward speed per metre of along-track error [1/s].
        kp_heading: yaw rate per radian of heading error [1/s].
        tolerance_m: distance to the slot [m] below which the follower lines up with the leader.
        feedforward: add the leader's estimated speed (True) or not (False).
        max_wheel_speed_m_s: wheel speed limit [m/s].
        track_width_m: wheel track [m].
    """

    n_states: ClassVar[int] = len(X_HAT_FIELDS)
    state_names: ClassVar[tuple[str, ...]] = X_HAT_FIELDS
    state_units: ClassVar[Mapping[str, str]] = {
        "leader_x": "m",
        "leader_y": "m",
        "leader_psi": "rad",
    }
    default_params: ClassVar[Mapping[str, Any]] = {
        "leader": None,
        "distance_m": 0.3,
        "lateral_m": 0.0,
        "kp_distance": 1.0,
        "kp_heading": 3.0,
        "tolerance_m": 0.01,
        "feedforward": True,
        "max_wheel_speed_m_s": FRISBEE_GEOMETRY.max_wheel_speed_m_s,
        "track_width_m": FRISBEE_GEOMETRY.track_width_m,
    }

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """Merge over the defaults and check every value (raises ControllerError)."""
        merged = super().validate_params(params)
        leader = merged["leader"]
        if not isinstance(leader, str) or not leader:
            raise ControllerError(
                f"{self.name}: param 'leader' must be the leader agent's name, got {leader!r}"
            )
        if not isinstance(merged["feedforward"], bool):
            raise ControllerError(
                f"{self.name}: param 'feedforward' must be true or false, "
                f"got {merged['feedforward']!r}"
            )
        for key in (
            "distance_m",
            "lateral_m",
            "kp_distance",
            "kp_heading",
            "tolerance_m",
            "max_wheel_speed_m_s",
            "track_width_m",
        ):
            value = merged[key]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ControllerError(f"{self.name}: param {key!r} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ControllerError(f"{self.name}: param {key!r} must be finite, got {value!r}")
            if key not in ("distance_m", "lateral_m") and value <= 0:
                raise ControllerError(f"{self.name}: param {key!r} must be > 0, got {value!r}")
            merged[key] = float(value)
        return merged

    def slot(self, leader: np.ndarray, params: Mapping[str, Any]) -> tuple[float, float]:
        """Where the follower should be [m, world frame] for leader output ``[x, y, psi]``."""
        x, y, psi = float(leader[0]), float(leader[1]), float(leader[2])
        back, left = -params["distance_m"], params["lateral_m"]
        cos_psi, sin_psi = math.cos(psi), math.sin(psi)
        return x + back * cos_psi - left * sin_psi, y + back * sin_psi + left * cos_psi

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        """One tick: ``(u_{k+1} = [v_left, v_right] [m/s], x_hat_{k+1})``."""
        leader = tick.neighbours.get(params["leader"])
        if leader is None:
            return np.zeros(2), np.zeros(len(X_HAT_FIELDS))
        leader = np.asarray(leader, dtype=float).reshape(-1)
        own = np.asarray(tick.y, dtype=float).reshape(-1)
        for who, vector in (("leader " + repr(params["leader"]), leader), ("own", own)):
            if vector.size < 3 or not np.all(np.isfinite(vector[:3])):
                raise ControllerError(
                    f"{self.name}: {who} output must start with finite [x, y, psi], got {vector}"
                )
        x, y, psi = float(own[0]), float(own[1]), float(own[2])
        leader_psi = float(leader[2])

        feedforward = 0.0
        if params["feedforward"] and x_hat[3] == 1.0 and tick.dt > 0:
            leader_velocity = (leader[:2] - x_hat[:2]) / tick.dt
            feedforward = float(leader_velocity @ (math.cos(psi), math.sin(psi)))

        slot_x, slot_y = self.slot(leader, params)
        distance = math.hypot(slot_x - x, slot_y - y)
        if distance > params["tolerance_m"]:
            bearing_error = wrap_angle(math.atan2(slot_y - y, slot_x - x) - psi)
            speed = feedforward + params["kp_distance"] * distance * math.cos(bearing_error)
            facing_error = (
                bearing_error
                if math.cos(bearing_error) >= 0
                else wrap_angle(bearing_error + math.pi)
            )
            yaw_rate = params["kp_heading"] * facing_error
        else:
            speed = feedforward
            yaw_rate = params["kp_heading"] * wrap_angle(leader_psi - psi)

        v_left, v_right = wheel_speeds(speed, yaw_rate, params["track_width_m"])
        v_left, v_right = scale_wheel_speeds(v_left, v_right, params["max_wheel_speed_m_s"])
        return np.array([v_left, v_right]), np.array([leader[0], leader[1], leader_psi, 1.0])

"""The offset follower (lead/follow, thesis §7.1) against exact kinematics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.control import ControlModel, TickInput
from hilswarm.agents.controllers.follower import OffsetFollower
from hilswarm.agents.controllers.waypoint import WaypointController
from hilswarm.agents.errors import ControllerError
from hilswarm.agents.registry import resolve_controller
from hilswarm.agents.sim.differential_drive import DifferentialDrive, wrap_angle

DT = 0.05


def tick(y, neighbours, k=0):
    return TickInput(
        k=k, t=k * DT, dt=DT, u=np.zeros(2), y=np.array(y, float), neighbours=neighbours
    )


def test_registry_name():
    assert resolve_controller("follower") is OffsetFollower


def test_slot_is_behind_and_to_the_left_in_the_leader_frame():
    controller = OffsetFollower()
    params = controller.validate_params({"leader": "a", "distance_m": 0.3, "lateral_m": 0.1})
    # Leader at (1, 1) heading +y: behind is -y, its left is -x.
    assert controller.slot(np.array([1.0, 1.0, math.pi / 2]), params) == pytest.approx((0.9, 0.7))


def test_no_leader_data_stops():
    controller = OffsetFollower()
    params = controller.validate_params({"leader": "a"})
    x_hat = np.array([1.0, 2.0, 0.0, 1.0])
    for neighbours in ({"a": None}, {}):
        u, x_next = controller.step(tick([0, 0, 0], neighbours), x_hat, params)
        assert list(u) == [0.0, 0.0]
        assert x_next[3] == 0.0


def test_slot_behind_backs_up_instead_of_turning_round():
    controller = OffsetFollower()
    params = controller.validate_params({"leader": "a", "distance_m": 0.3})
    x_hat = controller.initial_state(params)
    # Leader at the origin heading +x; follower ahead of its slot at (0, 0), same heading.
    u, _ = controller.step(tick([0.0, 0, 0], {"a": np.array([0.0, 0, 0])}), x_hat, params)
    assert u[0] == pytest.approx(u[1]) and u[0] < 0


@pytest.mark.parametrize("lateral", [0.0, 0.15])
def test_follows_a_leader_driving_waypoints(lateral):
    leader_cm = ControlModel(
        WaypointController(),
        dt=DT,
        n_inputs=2,
        params={"waypoints": [[1.0, 0.0], [1.0, 1.0]], "kp": 1.0},
    )
    follower_cm = ControlModel(
        OffsetFollower(),
        dt=DT,
        n_inputs=2,
        params={"leader": "lead", "distance_m": 0.3, "lateral_m": lateral},
    )
    plant = DifferentialDrive()
    leader, follower = np.zeros(3), np.array([-0.5, -0.3, 0.5])
    u_l, u_f = np.zeros(2), np.zeros(2)
    for _ in range(1200):
        y_l, y_f = plant.output(0, leader), plant.output(0, follower)
        u_l = leader_cm.step(u_l, y_l)
        u_f = follower_cm.step(u_f, y_f, neighbours={"lead": y_l})
        leader, follower = plant.step(leader, u_l, DT), plant.step(follower, u_f, DT)
    slot = OffsetFollower().slot(plant.output(0, leader), follower_cm.params)
    assert np.hypot(*(follower[:2] - slot)) < 0.015
    assert abs(wrap_angle(follower[2] - leader[2])) < 0.05


def test_tracks_a_moving_leader_with_feedforward():
    follower_cm = ControlModel(
        OffsetFollower(), dt=DT, n_inputs=2, params={"leader": "lead", "distance_m": 0.3}
    )
    plant = DifferentialDrive()
    leader, follower = np.array([0.0, 0.0, 0.3]), np.array([-0.6, 0.2, 0.0])
    u_f = np.zeros(2)
    errors = []
    for _ in range(600):  # 30 s with the leader on a gentle constant-curvature arc
        y_l = plant.output(0, leader)
        u_f = follower_cm.step(u_f, plant.output(0, follower), neighbours={"lead": y_l})
        leader, follower = plant.step(leader, [0.08, 0.09], DT), plant.step(follower, u_f, DT)
        slot = OffsetFollower().slot(plant.output(0, leader), follower_cm.params)
        errors.append(np.hypot(*(follower[:2] - slot)))
    assert max(errors[-200:]) < 0.02


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({}, "leader"),
        ({"leader": ""}, "leader"),
        ({"leader": "a", "kp_heading": 0}, "kp_heading"),
        ({"leader": "a", "distance_m": "far"}, "distance_m"),
        ({"leader": "a", "feedforward": 1}, "feedforward"),
        ({"leader": "a", "speed": 1}, "unknown"),
    ],
)
def test_bad_params_are_named(params, match):
    with pytest.raises(ControllerError, match=match):
        OffsetFollower().validate_params(params)


def test_bad_leader_output_is_named():
    controller = OffsetFollower()
    params = controller.validate_params({"leader": "a"})
    with pytest.raises(ControllerError, match="leader 'a'"):
        controller.step(tick([0, 0, 0], {"a": np.array([1.0])}), np.zeros(4), params)

"""The rotate-then-drive P/PI waypoint controller (thesis §5.4) against exact kinematics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.control import ControlModel, TickInput
from hilswarm.agents.controllers.waypoint import (
    DRIVING,
    HOLDING,
    PIVOTING,
    WaypointController,
)
from hilswarm.agents.errors import ControllerError
from hilswarm.agents.registry import resolve_controller
from hilswarm.agents.sim.differential_drive import FRISBEE_GEOMETRY, DifferentialDrive

DT = 0.05
VMAX = FRISBEE_GEOMETRY.max_wheel_speed_m_s


def model(**params):
    return ControlModel(WaypointController(), dt=DT, n_inputs=2, n_outputs=3, params=params)


def tick(y, u=(0.0, 0.0), k=0):
    return TickInput(k=k, t=k * DT, dt=DT, u=np.array(u, float), y=np.array(y, float))


def run(cm, x0=(0.0, 0.0, 0.0), max_ticks=4000):
    plant, x, u = DifferentialDrive(), np.array(x0, float), np.zeros(2)
    poses, phases = [], []
    for _ in range(max_ticks):
        u = cm.step(u, plant.output(0.0, x))
        poses.append(x.copy())
        phases.append(cm.x_hat[1])
        if cm.x_hat[1] == HOLDING:
            break
        x = plant.step(x, u, DT)
    return np.array(poses), np.array(phases)


def test_registry_name():
    assert resolve_controller("waypoint") is WaypointController


def test_pivots_the_short_way_first():
    controller = WaypointController()
    params = controller.validate_params({"waypoints": [[0.0, 1.0]]})
    x_hat = controller.initial_state(params)
    # Target straight left of a vehicle heading along +x: turn left (counter-clockwise).
    u, x_next = controller.step(tick([0, 0, 0]), x_hat, params)
    assert x_next[1] == PIVOTING
    assert u[0] == pytest.approx(-u[1]) and u[1] > 0
    # Heading +x, target at bearing -100°: turn right even though |angle| > 90°.
    params = controller.validate_params({"waypoints": [[-0.17, -0.98]]})
    u, _ = controller.step(tick([0, 0, 0]), controller.initial_state(params), params)
    assert u[0] > 0 > u[1]
    # Heading 170°, target at -170°: the short way is +20°, across the ±π cut.
    target = (math.cos(math.radians(-170)), math.sin(math.radians(-170)))
    params = controller.validate_params({"waypoints": [list(target)]})
    u, _ = controller.step(
        tick([0, 0, math.radians(170)]), controller.initial_state(params), params
    )
    assert u[1] > 0 > u[0]


def test_drives_straight_when_pointed_p_law():
    controller = WaypointController()
    params = controller.validate_params({"waypoints": [[0.1, 0.0]], "kp": 0.5})
    x_hat = controller.initial_state(params)
    x_hat[1] = DRIVING
    u, x_next = controller.step(tick([0, 0, 0.02]), x_hat, params)
    assert u == pytest.approx([0.05, 0.05])
    assert x_next[1] == DRIVING
    # Far away: saturated at the wheel speed limit.
    params = controller.validate_params({"waypoints": [[5.0, 0.0]]})
    u, _ = controller.step(tick([0, 0, 0]), x_hat, params)
    assert u == pytest.approx([VMAX, VMAX])


def test_pi_integral_uses_the_trapezoid_rule():
    controller = WaypointController()
    params = controller.validate_params(
        {"waypoints": [[0.1, 0.0]], "mode": "pi", "kp": 0.5, "ki": 0.2}
    )
    x_hat = controller.initial_state(params)
    x_hat[1] = DRIVING
    _, x_hat = controller.step(tick([0.0, 0, 0]), x_hat, params)  # e = 0.1, no integral yet
    assert x_hat[2] == 0.0 and x_hat[3] == pytest.approx(0.1)
    u, x_hat = controller.step(tick([0.02, 0, 0], k=1), x_hat, params)  # e = 0.08
    integral = 0.5 * DT * (0.1 + 0.08)
    assert x_hat[2] == pytest.approx(integral)
    assert u[0] == pytest.approx(0.5 * 0.08 + 0.2 * integral)


def test_pi_integral_does_not_wind_up_at_the_speed_limit():
    controller = WaypointController()
    params = controller.validate_params({"waypoints": [[3.0, 0.0]], "mode": "pi"})
    x_hat = controller.initial_state(params)
    x_hat[1] = DRIVING
    for k in range(20):
        u, x_hat = controller.step(tick([0.01 * k, 0, 0], k=k), x_hat, params)
    assert u[0] == pytest.approx(VMAX)
    assert x_hat[2] == 0.0


@pytest.mark.parametrize("mode", ["p", "pi"])
def test_visits_every_waypoint_in_order_and_holds_at_the_last(mode):
    waypoints = [[0.3, 0.0], [0.3, 0.3], [-0.2, 0.1]]
    cm = model(waypoints=waypoints, mode=mode, waypoint_tolerance_m=0.005)
    poses, phases = run(cm)
    assert phases[-1] == HOLDING
    assert np.hypot(*(poses[-1][:2] - waypoints[-1])) <= 0.005
    indices = np.array(cm.history["x_hat"].arrays().values[:, 0])
    assert list(np.unique(indices)) == [0, 1, 2]
    assert np.all(np.diff(indices) >= 0)
    # Holding: further ticks command zero wheel speed.
    u = cm.step(np.zeros(2), poses[-1])
    assert u == pytest.approx([0, 0])


def test_replacing_the_waypoint_list_restarts_at_its_first_entry():
    cm = model(waypoints=[[0.2, 0.0], [0.4, 0.0]])
    run(cm)
    assert cm.x_hat[0] == 1 and cm.x_hat[1] == HOLDING
    cm.set_params(waypoints=[[0.0, 0.2], [0.0, 0.4]])
    cm.step(np.zeros(2), [0.4, 0.0, 0.0])
    assert cm.x_hat[0] == 0 and cm.x_hat[1] == PIVOTING


def test_finite_pointing_tolerance_bows_the_path_but_reaches_the_target():
    # Thesis §5.6: with a pointing tolerance the legs are not straight lines.
    cm = model(waypoints=[[1.0, 0.3]], pointing_tolerance_rad=0.3)
    poses, phases = run(cm, x0=(0.0, 0.0, 0.25))
    assert phases[-1] == HOLDING
    line = np.array([1.0, 0.3]) / math.hypot(1.0, 0.3)
    cross_track = np.abs(poses[:, 0] * line[1] - poses[:, 1] * line[0])
    assert cross_track.max() > 0.005


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"waypoints": []}, "at least one"),
        ({"waypoints": [[0, 0, 0]]}, r"waypoints\[0\]"),
        ({"waypoints": [[0, "a"]]}, r"waypoints\[0\]"),
        ({"waypoints": "0,0"}, "list of"),
        ({"mode": "pid"}, "mode"),
        ({"kp": 0}, "kp"),
        ({"ki": -1}, "ki"),
        ({"pointing_tolerance_rad": 4.0}, "pointing_tolerance_rad"),
        ({"gain": 1.0}, "unknown"),
    ],
)
def test_bad_params_are_named(params, match):
    with pytest.raises(ControllerError, match=match):
        WaypointController().validate_params(params)


def test_validation_is_idempotent():
    controller = WaypointController()
    once = controller.validate_params({"waypoints": [[1, 2]], "mode": "pi"})
    assert controller.validate_params(once) == once

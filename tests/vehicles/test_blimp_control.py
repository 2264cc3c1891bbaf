"""Blimpduino trim, LQR, gain scheduling and the flight-mode machine (thesis §4.4)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.control import ControlModel
from hilswarm.agents.controllers.blimp_flight import (
    BlimpFlightController,
    Mode,
    ModeInputs,
    StateIndex,
    next_mode,
    servo_blend,
)
from hilswarm.agents.controllers.blimp_trim import (
    MODE_THRUST_ANGLE,
    FlightMode,
    ScheduleGrid,
    gain_schedule,
    lqr,
    riccati_residual,
)
from hilswarm.agents.errors import ControllerError
from hilswarm.agents.registry import resolve_controller
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS

#: A coarse grid keeps these tests fast (the schedule is cached per grid).
COARSE = ScheduleGrid(airspeeds=(0.0, 0.1, 0.3), headings=4)
COARSE_PARAMS = {"schedule_airspeeds": COARSE.airspeeds, "schedule_headings": COARSE.headings}
P = DEFAULT_BLIMP_PARAMS


@pytest.fixture(scope="module")
def schedule():
    return gain_schedule(DEFAULT_BLIMP_PARAMS, COARSE)


def all_gains(schedule):
    for mode, table in schedule.gains.items():
        for i, row in enumerate(table):
            for j, entry in enumerate(row):
                if entry is not None:
                    yield mode, i, j, entry


def test_every_trim_the_modes_use_is_an_equilibrium(schedule) -> None:
    for trim in schedule.trim_points():
        assert np.all(np.isfinite(trim.A)) and np.all(np.isfinite(trim.B))
        if trim.thrust_angle == 0.0 or trim.airspeed == 0.0:
            assert trim.feasible, trim
            assert trim.state[7] == pytest.approx(trim.heading, abs=1e-9)
            assert trim.inputs[0] == pytest.approx(trim.inputs[1], abs=1e-12)  # symmetric
            assert trim.inputs[2] == pytest.approx(trim.thrust_angle, abs=1e-9)


@pytest.mark.parametrize("speed", [0.1, 0.3])
def test_forward_trim_thrust_balances_drag(schedule, speed: float) -> None:
    trim = schedule.trims[COARSE.airspeeds.index(speed)][1][1]  # μ = 0
    assert trim.thrust_angle == 0.0
    drag = P.damping_linear[0] * speed + P.damping_quadratic[0] * speed**2
    assert 2 * trim.inputs[0] == pytest.approx(drag, rel=1e-6)
    assert trim.state[0] == pytest.approx(speed, abs=1e-9)


def test_lqr_gains_solve_the_riccati_equation(schedule) -> None:
    count = 0
    for _, _, _, gain in all_gains(schedule):
        residual = riccati_residual(gain.a_sub, gain.b_sub, gain.q, gain.r, gain.p)
        assert np.max(np.abs(residual)) < 1e-8 * np.max(np.abs(gain.q))
        np.testing.assert_allclose(gain.p, gain.p.T, atol=1e-9 * np.max(np.abs(gain.p)))
        assert np.all(np.linalg.eigvalsh(gain.p) > 0)
        np.testing.assert_allclose(
            gain.k_sub, np.linalg.solve(gain.r, gain.b_sub.T @ gain.p), rtol=1e-10
        )
        count += 1
    # vertical + hover at V = 0 (4 headings each), forward at the two V > 0 (4 headings each)
    assert count == 4 + 4 + 2 * 4


def test_closed_loop_is_stable_at_every_trim_point(schedule) -> None:
    for mode, i, j, gain in all_gains(schedule):
        poles = np.linalg.eigvals(gain.a_sub - gain.b_sub @ gain.k_sub)
        assert np.all(poles.real < -0.05), (mode, i, j, poles)
        # the same gain acting on the full reduced state through the projection
        trim = schedule.trims[i][j][schedule._angle_index(MODE_THRUST_ANGLE[mode])]
        full = trim.A - trim.B[:, :2] @ gain.gain
        sub = gain.projection @ full @ gain.projection.T
        np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(sub)), np.sort_complex(poles))


def test_zero_airspeed_is_not_stabilisable_in_all_eight_states(schedule) -> None:
    # Why each mode uses a sub-state: at V = 0 there is no side force to fix the cross-track.
    trim = schedule.trims[0][0][1]
    with pytest.raises(ControllerError, match="Riccati"):
        lqr(trim.A, trim.B[:, :2], np.eye(8), np.eye(2))


def test_schedule_interpolates_between_grid_points(schedule) -> None:
    headings = COARSE.heading_values
    table = schedule.gains[FlightMode.FORWARD]
    k00, k01 = table[1][0].gain, table[1][1].gain
    # On a grid point: exactly that gain.
    np.testing.assert_allclose(schedule.gain(FlightMode.FORWARD, 0.1, headings[1]), k01)
    # Half way in heading: the average; periodic across ±π.
    middle = (headings[0] + headings[1]) / 2
    np.testing.assert_allclose(
        schedule.gain(FlightMode.FORWARD, 0.1, middle), (k00 + k01) / 2, atol=1e-12
    )
    np.testing.assert_allclose(
        schedule.gain(FlightMode.FORWARD, 0.1, math.pi),
        schedule.gain(FlightMode.FORWARD, 0.1, -math.pi),
    )
    # Airspeed: linear between 0.1 and 0.3, clamped outside.
    k_high = table[2][1].gain
    np.testing.assert_allclose(
        schedule.gain(FlightMode.FORWARD, 0.2, headings[1]), (k01 + k_high) / 2, atol=1e-12
    )
    np.testing.assert_allclose(schedule.gain(FlightMode.FORWARD, 0.0, headings[1]), k01)
    np.testing.assert_allclose(schedule.gain(FlightMode.FORWARD, 5.0, headings[1]), k_high)
    trim = schedule.trim_input(FlightMode.FORWARD, 0.2, headings[1])
    expected = (schedule.trims[1][1][1].inputs + schedule.trims[2][1][1].inputs) / 2
    np.testing.assert_allclose(trim, expected, atol=1e-12)


def test_interpolated_gains_stay_stabilising_between_grid_points(schedule) -> None:
    # A gain blended between headings still stabilises the linearisation at that heading.
    from hilswarm.agents.controllers.blimp_trim import find_trim, mode_projection
    from hilswarm.agents.sim.blimp import BlimpPlant

    heading = 0.4 * COARSE.heading_values[1] + 0.6 * COARSE.heading_values[2]
    trim = find_trim(BlimpPlant(), 0.2, heading, 0.0)
    gain = schedule.gain(FlightMode.FORWARD, 0.2, heading)
    projection = mode_projection(FlightMode.FORWARD, heading)
    closed = projection @ (trim.A - trim.B[:, :2] @ gain) @ projection.T
    assert np.all(np.linalg.eigvals(closed).real < 0)


def test_schedule_is_cached(schedule) -> None:
    assert gain_schedule(DEFAULT_BLIMP_PARAMS, COARSE) is schedule
    assert schedule.build_seconds > 0


def test_bad_grids_are_refused() -> None:
    with pytest.raises(ControllerError, match="airspeeds"):
        ScheduleGrid(airspeeds=(0.1, 0.2))
    with pytest.raises(ControllerError, match="headings"):
        ScheduleGrid(headings=2)
    with pytest.raises(ControllerError, match="thrust_angles"):
        ScheduleGrid(thrust_angles=(0.0,))


# --- the mode machine ---------------------------------------------------------------------

PARAMS = BlimpFlightController().validate_params(COARSE_PARAMS)


def seen(**changes) -> ModeInputs:
    values = {
        "altitude_error": 0.0,
        "vertical_speed": 0.0,
        "heading_error": 0.0,
        "yaw_rate": 0.0,
        "far": False,
    }
    values.update(changes)
    return ModeInputs(**values)


def test_mode_precedence_vertical_then_turn_then_forward() -> None:
    everything = seen(altitude_error=0.5, heading_error=1.0, far=True)
    assert next_mode(Mode.HOLD, everything, PARAMS) is Mode.VERTICAL
    assert next_mode(Mode.HOLD, seen(heading_error=1.0, far=True), PARAMS) is Mode.TURN
    assert next_mode(Mode.HOLD, seen(heading_error=0.1, far=True), PARAMS) is Mode.FORWARD
    assert next_mode(Mode.FORWARD, seen(), PARAMS) is Mode.HOLD


def test_mode_switches_have_hysteresis() -> None:
    between_z = (PARAMS["z_enter"] + PARAMS["z_exit"]) / 2
    assert next_mode(Mode.HOLD, seen(altitude_error=between_z), PARAMS) is Mode.HOLD
    assert next_mode(Mode.VERTICAL, seen(altitude_error=between_z), PARAMS) is Mode.VERTICAL
    # Leaving VERTICAL also needs the vertical speed to have settled.
    small = PARAMS["z_exit"] / 2
    moving = seen(altitude_error=small, vertical_speed=0.1)
    assert next_mode(Mode.VERTICAL, moving, PARAMS) is Mode.VERTICAL
    assert next_mode(Mode.VERTICAL, seen(altitude_error=small), PARAMS) is Mode.HOLD
    between_psi = (PARAMS["heading_enter"] + PARAMS["heading_exit"]) / 2
    assert next_mode(Mode.FORWARD, seen(heading_error=between_psi, far=True), PARAMS) is (
        Mode.FORWARD
    )
    assert next_mode(Mode.TURN, seen(heading_error=between_psi, far=True), PARAMS) is Mode.TURN
    spinning = seen(heading_error=0.0, yaw_rate=0.2, far=True)
    assert next_mode(Mode.TURN, spinning, PARAMS) is Mode.TURN


def test_servo_blend_is_smooth_and_bounded() -> None:
    angles = np.linspace(-1.0, 1.0, 201)
    values = np.array([servo_blend(a, 0.3) for a in angles])
    assert values.min() == 0.0 and values.max() == 1.0
    assert servo_blend(0.0, 0.3) == 1.0 and servo_blend(0.3, 0.3) == 0.0
    assert np.max(np.abs(np.diff(values))) < 0.1


# --- the controller -----------------------------------------------------------------------


def test_controller_is_registered() -> None:
    assert resolve_controller("blimp_flight") is BlimpFlightController


@pytest.mark.parametrize(
    ("changes", "culprit"),
    [
        ({"waypoint": [0.0, 0.0]}, "waypoint"),
        ({"heading": "north"}, "heading"),
        ({"z_enter": 0.01, "z_exit": 0.02}, "z_exit"),
        ({"cruise_speed": 1.0}, "cruise_speed"),
        ({"estimator_alpha": 1.5}, "estimator_alpha"),
        ({"weights_forward": [1.0, 1.0]}, "weights_forward"),
        ({"schedule_headings": 2}, "schedule grid"),
        ({"gain": 3.0}, "unknown"),
    ],
)
def test_bad_parameters_name_the_culprit(changes, culprit: str) -> None:
    with pytest.raises(ControllerError, match=culprit):
        BlimpFlightController().validate_params({**COARSE_PARAMS, **changes})


def run(model: ControlModel, y, u=(0.0, 0.0, 0.0), ticks: int = 1) -> np.ndarray:
    out = np.asarray(u, dtype=float)
    for _ in range(ticks):
        out = model.step(out, y)
    return out


def test_commands_respect_the_hardware_limits_and_rate_limits() -> None:
    model = ControlModel(
        BlimpFlightController(), dt=0.05, n_inputs=3, n_outputs=4, params=COARSE_PARAMS
    )
    previous = np.zeros(3)
    for k in range(200):
        # A far waypoint, a big altitude error: maximal demands.
        u = model.step(previous, [3.0, -4.0, 0.5 + 0.01 * k, 2.0])
        assert np.all(np.abs(u[:2]) <= P.thrust_limit_n + 1e-12)
        assert P.thrust_angle_min_rad <= u[2] <= P.thrust_angle_max_rad
        assert np.all(np.abs(u[:2] - previous[:2]) <= 0.25 * 0.05 + 1e-12)
        assert abs(u[2] - previous[2]) <= 3.0 * 0.05 + 1e-12
        previous = u
    assert Mode(int(model.x_hat[StateIndex.MODE])) is Mode.VERTICAL


def test_waypoint_can_be_replaced_at_run_time() -> None:
    model = ControlModel(
        BlimpFlightController(),
        dt=0.05,
        n_inputs=3,
        n_outputs=4,
        params={**COARSE_PARAMS, "waypoint": [0.0, 0.0, -1.0]},
    )
    run(model, [0.0, 0.0, -1.0, 0.0], ticks=5)
    assert Mode(int(model.x_hat[StateIndex.MODE])) is Mode.HOLD
    model.set_params(waypoint=[0.0, 0.0, -2.0])  # climb 1 m
    u = run(model, [0.0, 0.0, -1.0, 0.0], ticks=20)
    assert Mode(int(model.x_hat[StateIndex.MODE])) is Mode.VERTICAL
    assert u[2] == pytest.approx(-math.pi / 2)  # thrust pointing up ...
    assert u[0] > 0 and u[1] > 0  # ... and pushing up
    model.set_params(waypoint=[2.0, 0.0, -1.0])  # straight ahead at this altitude
    run(model, [0.0, 0.0, -1.0, 0.0], ticks=3)
    assert Mode(int(model.x_hat[StateIndex.MODE])) is Mode.FORWARD
    with pytest.raises(ControllerError, match="waypoint"):
        model.set_params(waypoint=[1.0])

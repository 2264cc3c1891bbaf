"""Closed-form checks of the exact differential-drive kinematics (eqs. 5.1-5.8, corrected)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.differential_drive import (
    FRISBEE_GEOMETRY,
    SERIES_THRESHOLD,
    BatteryModel,
    DifferentialDrive,
    DriveGeometry,
    FrisbeePinPlant,
    HBridgePins,
    arc_functions,
    arc_step,
    body_rates,
    scale_wheel_speeds,
    wheel_speeds,
    wrap_angle,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

B = FRISBEE_GEOMETRY.track_width_m
VMAX = FRISBEE_GEOMETRY.max_wheel_speed_m_s


def ode_solution(pose, v_left, v_right, dt, track=B):
    speed, rate = body_rates(v_left, v_right, track)

    def rhs(t, s):
        return [speed * math.cos(s[2]), speed * math.sin(s[2]), rate]

    sol = solve_ivp(rhs, (0.0, dt), list(pose), method="DOP853", rtol=1e-12, atol=1e-14)
    return sol.y[:, -1]


def test_straight_line_is_exact():
    x, y, psi = arc_step(1.0, -2.0, 0.3, 0.1, 0.1, dt=2.0, track_width_m=B)
    assert x == pytest.approx(1.0 + 0.2 * math.cos(0.3), abs=1e-15)
    assert y == pytest.approx(-2.0 + 0.2 * math.sin(0.3), abs=1e-15)
    assert psi == 0.3


def test_pure_rotation_stays_in_place():
    x, y, psi = arc_step(0.5, 0.5, 0.0, -0.1, 0.1, dt=1.0, track_width_m=B)
    assert (x, y) == (0.5, 0.5)
    assert psi == pytest.approx(0.2 / B)


def test_left_turn_from_zero_heading_moves_to_positive_y():
    # The printed eq. 5.4 has the opposite sign here; this is the physical answer.
    _, y, psi = arc_step(0.0, 0.0, 0.0, 0.05, 0.1, dt=1.0, track_width_m=B)
    assert psi > 0
    assert y > 0


def test_quarter_circle_closed_form():
    # Outer wheel speed chosen so the radius is 1 m: V/ψ̇ = 1, quarter turn lands at (1, 1).
    rate = 0.1
    v_left, v_right = wheel_speeds(1.0 * rate, rate, B)
    x, y, psi = arc_step(0.0, 0.0, 0.0, v_left, v_right, dt=(math.pi / 2) / rate, track_width_m=B)
    assert (x, y, psi) == pytest.approx((1.0, 1.0, math.pi / 2), abs=1e-12)


def test_full_circle_returns_to_start():
    v_left, v_right = 0.03, 0.12
    _, rate = body_rates(v_left, v_right, B)
    period = 2 * math.pi / rate
    x, y, psi = arc_step(0.2, -0.4, 1.1, v_left, v_right, dt=period, track_width_m=B)
    assert (x, y) == pytest.approx((0.2, -0.4), abs=1e-12)
    assert wrap_angle(psi) == pytest.approx(wrap_angle(1.1), abs=1e-12)


def test_many_small_steps_equal_one_big_step():
    state = (0.0, 0.0, 0.4)
    for _ in range(1000):
        state = arc_step(*state, 0.07, 0.11, dt=0.01, track_width_m=B)
    big = arc_step(0.0, 0.0, 0.4, 0.07, 0.11, dt=10.0, track_width_m=B)
    assert state == pytest.approx(big, abs=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_arc_matches_ode_integration(seed):
    rng = np.random.default_rng(seed)
    pose = rng.uniform([-1, -1, -math.pi], [1, 1, math.pi])
    v_left, v_right = rng.uniform(-VMAX, VMAX, size=2)
    dt = rng.uniform(0.01, 5.0)
    exact = arc_step(*pose, v_left, v_right, dt=dt, track_width_m=B)
    assert np.allclose(exact, ode_solution(pose, v_left, v_right, dt), atol=1e-10, rtol=0)


@pytest.mark.parametrize("delta", [0.0, 1e-300, 1e-15, 1e-9, 1e-6, 1e-4])
def test_no_division_by_zero_near_equal_wheel_speeds(delta):
    exact = arc_step(0.0, 0.0, 0.7, 0.1, 0.1 + delta, dt=1.0, track_width_m=B)
    assert all(math.isfinite(v) for v in exact)
    assert np.allclose(exact, ode_solution((0.0, 0.0, 0.7), 0.1, 0.1 + delta, 1.0), atol=1e-12)


def test_series_and_closed_form_agree_at_the_threshold():
    for theta in (SERIES_THRESHOLD * (1 - 1e-9), SERIES_THRESHOLD * (1 + 1e-9)):
        s, c = arc_functions(theta)
        assert s == pytest.approx(math.sin(theta) / theta, rel=1e-14)
        assert c == pytest.approx((1 - math.cos(theta)) / theta, rel=1e-9)
    assert arc_functions(0.0) == (1.0, 0.0)


@settings(max_examples=200, deadline=None)
@given(
    v_left=st.floats(-VMAX, VMAX),
    v_right=st.floats(-VMAX, VMAX),
    psi=st.floats(-math.pi, math.pi),
    dt=st.floats(0.0, 3.0),
)
def test_arc_properties(v_left, v_right, psi, dt):
    x, y, psi_end = arc_step(0.0, 0.0, psi, v_left, v_right, dt=dt, track_width_m=B)
    speed, rate = body_rates(v_left, v_right, B)
    # Heading changes linearly; the chord is never longer than the path length.
    assert psi_end == pytest.approx(psi + rate * dt, abs=1e-12)
    assert math.hypot(x, y) <= abs(speed) * dt + 1e-12
    # The chord of an arc makes half the turned angle with the start heading.
    if abs(speed) * dt > 1e-6 and abs(rate * dt) < math.pi:
        chord_heading = math.atan2(y, x) if speed > 0 else math.atan2(-y, -x)
        assert wrap_angle(chord_heading - psi - rate * dt / 2) == pytest.approx(0.0, abs=1e-6)


def test_plant_clips_wheel_speeds_and_checks_shapes():
    plant = DifferentialDrive()
    fast = plant.step([0, 0, 0], [10.0, 10.0], 1.0)
    assert fast[0] == pytest.approx(VMAX)
    assert plant.dynamics(0.0, [0, 0, 0], [0.1, 0.1]) == pytest.approx([0.1, 0.0, 0.0])
    assert plant.output(0.0, [0, 0, 3 * math.pi])[2] == pytest.approx(-math.pi)
    with pytest.raises(PlantError, match="state"):
        plant.step([0, 0], [0, 0], 0.1)
    with pytest.raises(PlantError, match="input"):
        plant.step([0, 0, 0], [0], 0.1)
    with pytest.raises(PlantError, match="dt"):
        plant.step([0, 0, 0], [0, 0], -1.0)
    with pytest.raises(PlantError, match="track_width_m"):
        DriveGeometry(track_width_m=0.0, wheel_diameter_m=0.07, max_wheel_speed_m_s=0.2)


def test_scale_keeps_curvature():
    v_left, v_right = scale_wheel_speeds(0.1, 0.4, 0.2)
    assert (v_left, v_right) == pytest.approx((0.05, 0.2))


class LinearCal:
    """Signed duty -> speed, 255 -> VMAX (a stand-in calibration with the same to_u API)."""

    def to_u(self, name, pwm):
        return pwm / 255 * VMAX


def test_pin_plant_reads_h_bridge_pins():
    left, right = HBridgePins(7, 8, 5), HBridgePins(4, 12, 6)
    plant = FrisbeePinPlant(
        LinearCal(), left=left, right=right, battery=BatteryModel(pin=14, drain_v_per_s=0.5)
    )
    # Both forward at full duty: straight ahead for 1 s.
    analog = plant.advance({7: 1, 8: 0, 5: 255, 4: 1, 12: 0, 6: 255}, 1.0)
    assert plant.pose() == pytest.approx([VMAX, 0, 0, 0, 0, 0])
    assert analog == {14: pytest.approx((12.6 - 0.5) / 3.0)}
    # Left backward, right forward: pivot in place (counter-clockwise).
    plant.advance({7: 0, 8: 1, 5: 100, 4: 1, 12: 0, 6: 100}, 0.5)
    assert plant.pose()[:2] == pytest.approx([VMAX, 0])
    assert plant.pose()[5] > 0
    # Direction pins both low (coast) or both high (brake): no motion whatever the duty.
    before = plant.pose()
    plant.advance({7: 0, 8: 0, 5: 255, 4: 1, 12: 1, 6: 255}, 1.0)
    assert plant.pose() == pytest.approx(before)
    assert plant.time_s == pytest.approx(2.5)


def test_advance_is_a_continuous_plant_with_an_exact_default():
    from hilswarm.agents.sim.plant import ContinuousPlant

    plant = DifferentialDrive()
    assert isinstance(plant, ContinuousPlant)
    assert (plant.n_states, plant.n_inputs, plant.n_outputs) == (3, 2, 3)
    exact = plant.advance(0.0, [0, 0, 0.3], [0.05, 0.15], 2.0)
    rk4 = plant.advance(0.0, [0, 0, 0.3], [0.05, 0.15], 2.0, method="rk4", substeps=200)
    assert exact == pytest.approx(plant.step([0, 0, 0.3], [0.05, 0.15], 2.0), abs=0)
    assert rk4 == pytest.approx(exact, abs=1e-12)

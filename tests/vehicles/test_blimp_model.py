"""The Blimpduino's 6-DOF model: added mass, frames, forces, energy, linearisation (thesis §4.3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.controllers.blimp_trim import central_jacobians, find_trim
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.added_mass import (
    LAMB_TABLE,
    added_mass,
    k_factors,
    k_factors_from_table,
    spheroid_volume,
)
from hilswarm.agents.sim.blimp import (
    REDUCED_INDEX,
    BlimpPinout,
    BlimpPinPlant,
    BlimpPlant,
    full_state_from_reduced,
    rotation_body_to_world,
)
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS, BatteryParams
from hilswarm.agents.vehicles.blimpduino import reference_calibration
from hypothesis import given, settings
from hypothesis import strategies as st

P = DEFAULT_BLIMP_PARAMS
LIMIT = P.thrust_limit_n

# --- Lamb's k-factors ---------------------------------------------------------------------


@pytest.mark.parametrize("factors", [k_factors, k_factors_from_table])
def test_sphere_has_half_added_mass_and_no_added_inertia(factors) -> None:
    k = factors(1.0, 1.0)
    assert k.k1 == pytest.approx(0.5, abs=1e-12)
    assert k.k2 == pytest.approx(0.5, abs=1e-12)
    assert k.k_rot == pytest.approx(0.0, abs=1e-12)


def test_nearly_spherical_closed_form_tends_to_sphere() -> None:
    k = k_factors(1.0 + 1e-7, 1.0)
    assert (k.k1, k.k2, k.k_rot) == pytest.approx((0.5, 0.5, 0.0), abs=1e-6)
    k = k_factors(1.001, 1.0)
    assert (k.k1, k.k2, k.k_rot) == pytest.approx((0.5, 0.5, 0.0), abs=1e-3)


@pytest.mark.parametrize("factors", [k_factors, k_factors_from_table])
def test_slender_body_limit(factors) -> None:
    k = factors(1e4, 1.0)
    assert k.k1 < 1e-3
    assert k.k2 > 0.999
    assert k.k_rot > 0.99


def test_table_rows_match_closed_form() -> None:
    # Lamb's printed table (3 decimals, hand-computed) agrees with the closed form to 2.5e-3.
    for ratio, k1, k2, k_rot in LAMB_TABLE[:-1]:
        closed = k_factors(ratio, 1.0)
        assert closed.k1 == pytest.approx(k1, abs=2.5e-3), ratio
        assert closed.k2 == pytest.approx(k2, abs=2.5e-3), ratio
        assert closed.k_rot == pytest.approx(k_rot, abs=2.5e-3), ratio


@settings(max_examples=60, deadline=None)
@given(st.floats(min_value=1.0, max_value=100.0))
def test_interpolated_table_matches_closed_form(ratio: float) -> None:
    # Between the rows, the interpolation of a 13-row table adds its own error: largest for k'
    # between L/D = 1 and 1.5, where k' grows like e^4 (a dense scan gives 0.009 at most).
    table, closed = k_factors_from_table(ratio, 1.0), k_factors(ratio, 1.0)
    assert table.k1 == pytest.approx(closed.k1, abs=3e-3)
    assert table.k2 == pytest.approx(closed.k2, abs=4e-3)
    assert table.k_rot == pytest.approx(closed.k_rot, abs=1e-2)


def test_k_factors_are_monotone_in_slenderness() -> None:
    ratios = np.linspace(1.0, 12.0, 60)
    ks = np.array([[*vars_of(k_factors(r, 1.0))] for r in ratios])
    assert np.all(np.diff(ks[:, 0]) < 0)  # k1 falls
    assert np.all(np.diff(ks[:, 1]) > 0)  # k2 rises
    assert np.all(np.diff(ks[:, 2]) > 0)  # k' rises


def vars_of(k) -> tuple[float, float, float]:
    return k.k1, k.k2, k.k_rot


@pytest.mark.parametrize(
    ("length", "diameter"), [(0.5, 1.0), (0.0, 1.0), (1.0, -1.0), (math.inf, 1.0)]
)
def test_bad_spheroids_are_refused(length: float, diameter: float) -> None:
    with pytest.raises(PlantError, match=r"length_m|diameter_m"):
        k_factors(length, diameter)


def test_added_mass_terms_follow_eqs_4_4_to_4_9() -> None:
    a = added_mass(2.0, 1.0, 1.2, use_table=False)
    k = k_factors(2.0, 1.0)
    fluid = 1.2 * spheroid_volume(2.0, 1.0)
    assert spheroid_volume(2.0, 1.0) == pytest.approx(4 / 3 * math.pi * 1.0 * 0.25)
    assert a.m_x == pytest.approx(k.k1 * fluid)
    assert a.m_y == a.m_z == pytest.approx(k.k2 * fluid)
    assert a.i_x == 0.0
    assert a.i_y == a.i_z == pytest.approx(k.k_rot * fluid * (1.0 + 0.25) / 5)


# --- parameters ---------------------------------------------------------------------------


def test_default_blimp_is_neutrally_buoyant_and_pendulum_stable() -> None:
    assert P.mass_kg == pytest.approx(P.air_density_kg_m3 * P.volume_m3)
    assert P.buoyancy_n == pytest.approx(P.mass_kg * P.gravity_m_s2)
    assert P.cg_below_cb_m > 0
    assert P.envelope_length_m == pytest.approx(52 * 0.0254)  # thesis: 52-inch balloon
    assert P.thruster_arm_m == pytest.approx(2.5 * 0.0254)  # motors 5 in apart
    assert P.thrust_limit_n == 0.0637
    assert (P.thrust_angle_min_rad, P.thrust_angle_max_rad) == (-math.pi, 0.0)


def test_bad_parameters_name_the_field() -> None:
    with pytest.raises(PlantError, match="thrust_limit_n"):
        P.with_changes(thrust_limit_n=-1.0)
    with pytest.raises(PlantError, match="damping_linear"):
        P.with_changes(damping_linear=(0.1, 0.1))
    with pytest.raises(PlantError, match="initial_charge"):
        BatteryParams(initial_charge=1.5)


# --- frames and forces --------------------------------------------------------------------


def rates(plant: BlimpPlant, state: np.ndarray, u) -> np.ndarray:
    return plant.dynamics(0.0, state, np.asarray(u, dtype=float))


@settings(max_examples=30, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-1.4, 1.4), st.floats(-math.pi, math.pi))
def test_rotation_is_proper_and_right_handed(roll: float, pitch: float, yaw: float) -> None:
    r = rotation_body_to_world(roll, pitch, yaw)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(np.cross(r[:, 0], r[:, 1]), r[:, 2], atol=1e-12)


def test_body_frame_is_forward_right_down() -> None:
    plant = BlimpPlant()
    # Facing +y (ψ = 90°): forward thrust accelerates the blimp and it moves along world +y.
    state = plant.initial_state([0.0, 0.0, -1.0, math.pi / 2])
    state[6] = 0.5  # u [m/s]
    dx = rates(plant, state, [LIMIT, LIMIT, 0.0])
    assert dx[6] > 0
    assert dx[1] == pytest.approx(0.5)
    assert dx[0] == pytest.approx(0.0, abs=1e-12)
    # Positive (left > right) differential thrust yaws the nose to the right: r > 0, ψ grows.
    still = plant.initial_state([0.0, 0.0, -1.0, 0.0])
    assert rates(plant, still, [LIMIT, -LIMIT, 0.0])[11] > 0
    # μ = -90°: positive thrust points up (-z): the blimp accelerates upwards, w' < 0.
    assert rates(plant, still, [LIMIT, LIMIT, -math.pi / 2])[8] < 0
    # A positive body w (down) moves the blimp to larger world z (lower altitude).
    sinking = still.copy()
    sinking[8] = 0.3
    assert rates(plant, sinking, [0, 0, 0])[2] == pytest.approx(0.3)


def test_tilted_differential_thrust_rolls_towards_the_weaker_side() -> None:
    plant = BlimpPlant()
    still = plant.initial_state([0.0, 0.0, -1.0, 0.0])
    # Thrust up with left > right lifts the left side: roll to the right (p > 0).
    assert rates(plant, still, [LIMIT, 0.0, -math.pi / 2])[9] > 0
    # At μ = 0 differential thrust makes no roll moment (thesis eq. 4.11).
    assert rates(plant, still, [LIMIT, 0.0, 0.0])[9] == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("angle", [0.2, -0.2, 0.6])
def test_buoyancy_couple_restores_roll_and_pitch(angle: float) -> None:
    plant = BlimpPlant()
    state = plant.initial_state([0.0, 0.0, -1.0, 0.0])
    rolled, pitched = state.copy(), state.copy()
    rolled[3], pitched[4] = angle, angle
    p_dot = rates(plant, rolled, [0, 0, 0])[9]
    q_dot = rates(plant, pitched, [0, 0, 0])[10]
    assert np.sign(p_dot) == -np.sign(angle)
    assert np.sign(q_dot) == -np.sign(angle)
    moment = P.cg_below_cb_m * P.buoyancy_n * math.sin(angle)  # eq. 4.14
    assert p_dot * plant.mass_diagonal[3] == pytest.approx(-moment)
    assert q_dot * plant.mass_diagonal[4] == pytest.approx(-moment)


def test_inputs_are_saturated_to_the_hardware_limits() -> None:
    plant = BlimpPlant()
    np.testing.assert_allclose(plant.saturate([1.0, -1.0, 1.0]), [LIMIT, -LIMIT, 0.0])
    np.testing.assert_allclose(plant.saturate([0.01, 0.02, -4.0]), [0.01, 0.02, -math.pi])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-2.0, 2.0), min_size=6, max_size=6))
def test_coriolis_forces_do_no_work(velocities: list[float]) -> None:
    plant = BlimpPlant()
    state = np.zeros(12)
    state[6:12] = velocities
    coriolis = plant.generalized_forces(state, np.zeros(3))["coriolis"]
    scale = 1.0 + float(np.sum(np.abs(coriolis)))
    assert float(np.dot(state[6:12], coriolis)) == pytest.approx(0.0, abs=1e-12 * scale)


def test_energy_is_conserved_without_damping_and_thrust() -> None:
    plant = BlimpPlant(P.with_changes(damping_linear=(0.0,) * 6, damping_quadratic=(0.0,) * 6))
    rng = np.random.default_rng(7)
    state = np.concatenate([[0, 0, -1], rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.3, 0.3, 6)])
    start = plant.energy(state)
    for _ in range(1000):
        state = plant.advance(0.0, state, [0, 0, 0], 0.01, method="rk4")
    assert plant.energy(state) == pytest.approx(start, rel=1e-6)


def test_damping_only_removes_energy() -> None:
    plant = BlimpPlant()
    rng = np.random.default_rng(3)
    state = np.concatenate([[0, 0, -1], rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.5, 0.5, 6)])
    energies = []
    for _ in range(300):
        energies.append(plant.energy(state))
        state = plant.advance(0.0, state, [0, 0, 0], 0.02, method="rk4")
    assert np.all(np.diff(energies) <= 1e-12)
    assert energies[-1] < 0.5 * energies[0]


def test_terminal_speeds_are_plausible() -> None:
    # Full forward thrust: drag balances 2 T_max at ~1.3 m/s (the chosen drag coefficients).
    plant = BlimpPlant()
    state = plant.initial_state([0, 0, -1, 0])
    for _ in range(800):
        state = plant.advance(0.0, state, [LIMIT, LIMIT, 0.0], 0.05, method="rk4")
    d_lin, d_quad = P.damping_linear[0], P.damping_quadratic[0]
    expected = (-d_lin + math.sqrt(d_lin**2 + 4 * d_quad * 2 * LIMIT)) / (2 * d_quad)
    assert state[6] == pytest.approx(expected, rel=1e-3)
    assert 0.8 < expected < 2.0


def test_reduced_model_is_the_full_model_restricted_to_level_flight() -> None:
    plant = BlimpPlant()
    rng = np.random.default_rng(11)
    for _ in range(5):
        s = rng.uniform(-0.5, 0.5, 8)
        u = [rng.uniform(-LIMIT, LIMIT), rng.uniform(-LIMIT, LIMIT), rng.uniform(-math.pi, 0)]
        full = plant.dynamics(0.0, full_state_from_reduced(s), u)
        reduced = plant.reduced_dynamics(s, u)
        index = list(REDUCED_INDEX)
        # velocity rows: u', v', w', r'; navigation rows: x', y', z', ψ'
        np.testing.assert_allclose(reduced, full[[6, 7, 8, 11, 0, 1, 2, 5]], atol=1e-12)
        assert len(index) == 8


@pytest.mark.parametrize(
    ("speed", "heading", "angle"), [(0.2, 0.3, 0.0), (0.0, -2.0, 0.0), (0.0, 1.0, -math.pi / 2)]
)
def test_linearisation_matches_the_nonlinear_model(speed, heading, angle) -> None:
    plant = BlimpPlant()
    trim = find_trim(plant, speed, heading, angle)
    assert trim.feasible
    f0 = plant.reduced_dynamics(trim.state, trim.inputs)
    np.testing.assert_allclose(f0[:4], 0.0, atol=1e-9)  # an equilibrium of the velocities
    rng = np.random.default_rng(5)
    direction_s = rng.standard_normal(8)
    direction_u = rng.standard_normal(3) * np.array([LIMIT, LIMIT, 0.5])
    errors = []
    for eps in (1e-2, 1e-3):
        ds, du = eps * direction_s, eps * direction_u
        exact = plant.reduced_dynamics(trim.state + ds, trim.inputs + du) - f0
        linear = trim.A @ ds + trim.B @ du
        errors.append(np.linalg.norm(exact - linear))
        assert np.linalg.norm(exact - linear) <= 0.05 * np.linalg.norm(exact) + 1e-12
    # The remainder is second order: shrinking the perturbation 10x shrinks it ~100x.
    assert errors[1] < errors[0] / 30


def test_central_jacobians_are_exact_for_quadratics() -> None:
    def f(s: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.array([s[0] ** 2 + 3 * s[1] * u[0], u[0] ** 2 - s[1]])

    a, b = central_jacobians(f, [1.5, -2.0], [0.5])
    np.testing.assert_allclose(a, [[3.0, 1.5], [0.0, -1.0]], atol=1e-8)
    np.testing.assert_allclose(b, [[-6.0], [1.0]], atol=1e-8)


# --- the pin-level plant ------------------------------------------------------------------


def outputs(left: int, right: int, pulse: int, *, standby: int = 1) -> dict[int, int]:
    pins = BlimpPinout()
    return {
        pins.left_fwd: int(left > 0),
        pins.left_back: int(left < 0),
        pins.left_pwm: abs(left),
        pins.right_fwd: int(right > 0),
        pins.right_back: int(right < 0),
        pins.right_pwm: abs(right),
        pins.servo: pulse,
        pins.standby: standby,
    }


def test_pin_plant_reads_duties_and_servo_pulse() -> None:
    calibration = reference_calibration()
    plant = BlimpPinPlant(calibration, initial_state=[0, 0, -1, 0])
    volts = plant.advance(outputs(255, -128, P.servo_max_us), 0.05)
    assert plant.inputs[0] == pytest.approx(LIMIT)
    assert plant.inputs[1] == pytest.approx(calibration.to_u("thrust_right", -128))
    assert plant.inputs[2] == pytest.approx(0.0)
    assert set(volts) == {14}
    plant.advance(outputs(0, 0, (P.servo_min_us + P.servo_max_us) // 2), 0.05)
    assert plant.inputs[2] == pytest.approx(-math.pi / 2)
    # Standby LOW: the H-bridge is disabled, no thrust whatever the other pins say.
    plant.advance(outputs(255, 255, P.servo_max_us, standby=0), 0.05)
    np.testing.assert_allclose(plant.inputs[:2], 0.0)


def test_pin_plant_flies_and_reports_pose() -> None:
    plant = BlimpPinPlant(reference_calibration(), initial_state=[1.0, 2.0, -1.0, 0.5])
    for _ in range(40):
        plant.advance(outputs(200, 200, P.servo_max_us), 0.05)
    pose = plant.pose()
    assert pose.shape == (6,)
    moved = pose[:2] - [1.0, 2.0]
    assert np.linalg.norm(moved) > 0.1
    assert math.atan2(moved[1], moved[0]) == pytest.approx(0.5, abs=1e-6)


def test_battery_discharges_and_sags_under_load() -> None:
    params = P.with_changes(battery=BatteryParams(capacity_ah=0.001))
    plant = BlimpPinPlant(reference_calibration(), params=params)
    idle = plant.advance(outputs(0, 0, 1500), 0.05)[14]
    loaded = plant.advance(outputs(255, 255, 1500), 0.05)[14]
    assert loaded < idle  # internal resistance drop
    for _ in range(100):
        plant.advance(outputs(255, 255, 1500), 0.5)
    assert plant.battery.charge < 0.9
    assert plant.analog_inputs()[14] < loaded
    assert plant.analog_inputs()[14] == pytest.approx(plant.battery.volts / 3.0)

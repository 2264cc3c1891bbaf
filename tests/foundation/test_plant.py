"""Plants and fixed-step integrators: orders of accuracy, closed forms, errors; SimulatedMocap."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hilswarm.agents.errors import PlantError
from hilswarm.agents.registry import resolve_plant
from hilswarm.agents.sim.integrator import Integrator
from hilswarm.agents.sim.mocap import SimulatedMocap
from hilswarm.agents.sim.plant import (
    LinearPlant,
    PoseSource,
    euler_step,
    integrate,
    rk4_step,
)
from hilswarm.agents.sim.spring_mass_damper import SpringMassDamper
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm


def _error_at_one(method: str, n_steps: int, a: float = -1.3) -> float:
    x1 = integrate(lambda t, x: a * x, 0.0, [1.0], 1.0, method=method, substeps=n_steps)
    return abs(float(x1[0]) - math.exp(a))


@pytest.mark.parametrize(("method", "order"), [("euler", 1), ("rk4", 4)])
def test_order_of_accuracy_on_exponential(method: str, order: int) -> None:
    errors = [_error_at_one(method, n) for n in (8, 16, 32, 64)]
    observed = [math.log2(e1 / e2) for e1, e2 in itertools.pairwise(errors)]
    assert all(abs(p - order) < 0.15 for p in observed), observed


def test_single_steps_closed_form() -> None:
    a, h = 0.7, 0.1
    assert euler_step(lambda t, x: a * x, 0.0, np.array([2.0]), h)[0] == pytest.approx(
        2.0 * (1 + a * h)
    )
    # RK4 on x' = a x is the 4th-order Taylor polynomial of exp(a h)
    taylor = sum((a * h) ** n / math.factorial(n) for n in range(5))
    assert rk4_step(lambda t, x: a * x, 0.0, np.array([2.0]), h)[0] == pytest.approx(
        2.0 * taylor, rel=1e-14
    )
    # time-dependent rate: x' = t  ->  x(1) = 1/2 exactly for RK4 (Simpson)
    assert integrate(lambda t, x: np.array([t]), 0.0, [0.0], 1.0, method="rk4")[0] == (
        pytest.approx(0.5, rel=1e-14)
    )


def test_integrate_errors() -> None:
    with pytest.raises(PlantError, match="one of"):
        integrate(lambda t, x: x, 0.0, [1.0], 0.1, method="ode45")
    with pytest.raises(PlantError, match="substeps"):
        integrate(lambda t, x: x, 0.0, [1.0], 0.1, substeps=0)
    with pytest.raises(PlantError, match="dt"):
        integrate(lambda t, x: x, 0.0, [1.0], -0.1)


def test_spring_mass_damper_matrices_eq_3_3() -> None:
    plant = SpringMassDamper()
    np.testing.assert_array_equal(
        plant.A, [[0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1], [0, 0, -1, 0]]
    )
    np.testing.assert_array_equal(plant.B, [[0, 0], [1, 0], [0, 0], [0, 1]])
    eigenvalues = np.sort_complex(np.linalg.eigvals(plant.A))
    np.testing.assert_allclose(eigenvalues, [-1j, -1j, 1j, 1j], atol=1e-12)
    assert plant.state_names == ("x", "xdot", "y", "ydot")
    assert plant.input_names == ("F1", "F2")
    assert (plant.n_states, plant.n_inputs, plant.n_outputs) == (4, 2, 4)
    assert resolve_plant("spring_mass_damper") is SpringMassDamper
    assert resolve_plant("integrator") is Integrator


def test_spring_mass_damper_general_parameters_eq_3_2() -> None:
    plant = SpringMassDamper(m=2.0, k1=3.0, k2=5.0, c1=0.4, c2=0.6)
    z = np.array([0.1, -0.2, 0.3, 0.4])
    u = np.array([1.0, -2.0])
    dz = plant.dynamics(0.0, z, u)
    assert dz[0] == z[1] and dz[2] == z[3]
    assert dz[1] == pytest.approx((1.0 - 3.0 * 0.1 - 0.4 * -0.2) / 2.0)
    assert dz[3] == pytest.approx((-2.0 - 5.0 * 0.3 - 0.6 * 0.4) / 2.0)
    np.testing.assert_array_equal(plant.output(0.0, z, u), z)


def test_free_oscillation_closed_form_and_energy() -> None:
    """Undamped, unforced: x(t) = x0 cos(w t), energy constant (RK4, fine steps)."""
    m, k = 2.0, 8.0
    omega = math.sqrt(k / m)
    plant = SpringMassDamper(m=m, k1=k, k2=k)
    z = np.array([4.0, 0.0, -4.0, 0.0])
    energy0 = plant.energy(z)
    assert energy0 == pytest.approx(0.5 * k * 32.0)
    dt = 0.01
    for i in range(1, 301):
        z = plant.advance((i - 1) * dt, z, [0.0, 0.0], dt, method="rk4")
    t = 300 * dt
    np.testing.assert_allclose(
        z,
        [
            4 * math.cos(omega * t),
            -4 * omega * math.sin(omega * t),
            -4 * math.cos(omega * t),
            4 * omega * math.sin(omega * t),
        ],
        atol=1e-8,
    )
    assert plant.energy(z) == pytest.approx(energy0, rel=1e-8)


def test_euler_pumps_energy_into_the_oscillator_exactly() -> None:
    """Euler on x'' = -w^2 x multiplies the energy by (1 + (w h)^2) every step."""
    plant = SpringMassDamper()  # m = k = 1, w = 1
    h = 0.1
    z = np.array([4.0, 0.0, -4.0, 0.0])
    energies = [plant.energy(z)]
    for i in range(50):
        z = plant.advance(i * h, z, [0.0, 0.0], h)
        energies.append(plant.energy(z))
    ratios = np.array(energies[1:]) / np.array(energies[:-1])
    np.testing.assert_allclose(ratios, 1 + h**2, rtol=1e-12)


def test_damping_dissipates_energy() -> None:
    plant = SpringMassDamper(c1=0.5, c2=0.2)
    z = np.array([1.0, 0.0, 0.0, 2.0])
    energy = plant.energy(z)
    for i in range(200):
        z = plant.advance(i * 0.01, z, [0.0, 0.0], 0.01, method="rk4")
        new_energy = plant.energy(z)
        assert new_energy < energy
        energy = new_energy


def test_forced_static_equilibrium() -> None:
    """A constant force F holds the mass at x = F / k once the damping has settled it."""
    plant = SpringMassDamper(m=1.0, k1=2.0, k2=4.0, c1=3.0, c2=5.0)
    z = np.zeros(4)
    z = plant.advance(0.0, z, [1.0, 2.0], 40.0, method="rk4", substeps=4000)
    np.testing.assert_allclose(z, [0.5, 0.0, 0.5, 0.0], atol=1e-9)


@pytest.mark.parametrize(
    "kwargs", [{"m": 0}, {"m": -1}, {"k1": -1}, {"c2": float("nan")}, {"c1": "1"}, {"k2": True}]
)
def test_spring_mass_damper_bad_parameters(kwargs: dict[str, object]) -> None:
    with pytest.raises(PlantError, match="SpringMassDamper"):
        SpringMassDamper(**kwargs)  # type: ignore[arg-type]


@settings(max_examples=200, deadline=None)
@given(st.integers(min_value=0, max_value=2**31), st.sampled_from([1, 2, 3]))
def test_linear_plant_rk4_converges_to_zoh_discretisation(seed: int, m: int) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(3, 3)) - 2 * np.eye(3)
    b = rng.normal(size=(3, m))
    plant = LinearPlant(a.tolist(), b.tolist())
    x0, u = rng.normal(size=3), rng.normal(size=m)
    dt = 0.05
    augmented = np.block([[a, b], [np.zeros((m, 3 + m))]])
    big = expm(augmented * dt)
    exact = big[:3, :3] @ x0 + big[:3, 3:] @ u
    substeps = 2
    approx = plant.advance(0.0, x0, u, dt, method="rk4", substeps=substeps)
    # RK4 on x' = A x + B u (u held) is the degree-4 Taylor polynomial T of exp(M h) per
    # substep, M = [[A, B], [0, 0]] acting on z = [x; u]. With s = |M|_2 h, |T^n - E^n| <=
    # n e^((n-1) s) |T - E| and |T - E| <= e^s - (1 + s + s^2/2 + s^3/6 + s^4/24): the
    # method's own error bound, not a tuned tolerance (a wrong coefficient errs ~s^4/24).
    s = np.linalg.norm(augmented, 2) * dt / substeps
    remainder = math.exp(s) - sum(s**k / math.factorial(k) for k in range(5))
    bound = substeps * math.exp((substeps - 1) * s) * remainder
    bound *= float(np.linalg.norm(np.concatenate([x0, u])))
    assert np.linalg.norm(approx - exact) <= bound + 1e-12


def test_linear_plant_shapes_and_defaults() -> None:
    plant = LinearPlant([[0, 1], [0, 0]], [0, 1])  # flat B: one input column
    assert (plant.n_states, plant.n_inputs, plant.n_outputs) == (2, 1, 2)
    np.testing.assert_array_equal(
        plant.output(0.0, np.array([1.0, 2.0]), np.array([3.0])), [1.0, 2.0]
    )
    with_c = LinearPlant([[0, 1], [0, 0]], [[0], [1]], C=[1, 0], D=[[0.5]])
    assert with_c.n_outputs == 1
    assert with_c.output(0.0, np.array([2.0, 5.0]), np.array([4.0]))[0] == 4.0
    with pytest.raises(PlantError, match="A must be square"):
        LinearPlant([[0, 1]], [[1]])
    with pytest.raises(PlantError, match="B must have 2 rows"):
        LinearPlant(np.eye(2), np.ones((3, 1)))
    with pytest.raises(PlantError, match="C must have 2 columns"):
        LinearPlant(np.eye(2), np.ones((2, 1)), C=np.ones((1, 3)))
    with pytest.raises(PlantError, match=r"D must have shape \(2, 1\)"):
        LinearPlant(np.eye(2), np.ones((2, 1)), D=np.ones((1, 1)))
    with pytest.raises(PlantError, match="non-finite"):
        LinearPlant([[float("nan")]], [[1.0]])
    with pytest.raises(PlantError, match="input must have 1 entries, got 2"):
        plant.advance(0.0, [0, 0], [1, 2], 0.1)
    with pytest.raises(PlantError, match="state must have 2 entries, got 3"):
        plant.advance(0.0, [0, 0, 0], [1], 0.1)


def test_integrator_plant_is_exact_for_constant_input() -> None:
    plant = Integrator(n_dims=2)
    x = plant.advance(0.0, [1.0, -1.0], [0.5, 2.0], 0.4)
    np.testing.assert_allclose(x, [1.2, -0.2], rtol=1e-15)
    np.testing.assert_array_equal(plant.output(0.0, x, np.zeros(2)), x)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(PlantError, match="n_dims"):
            Integrator(n_dims=bad)  # type: ignore[arg-type]


# --- simulated motion capture ---------------------------------------------------------------


class MovingBody:
    def __init__(self) -> None:
        self.state = np.array([1.0, 2.0, 0.5, 0.0, 0.0, 3.1])

    def pose(self) -> np.ndarray:
        return self.state.copy()


def test_mocap_is_a_pose_source_and_noise_free_by_default() -> None:
    mocap = SimulatedMocap(MovingBody())
    assert isinstance(mocap, PoseSource)
    np.testing.assert_array_equal(mocap.pose(), [1.0, 2.0, 0.5, 0.0, 0.0, 3.1])


def test_mocap_noise_is_seeded_and_has_the_requested_spread() -> None:
    body = MovingBody()
    first = SimulatedMocap(body, noise_std_m=0.01, noise_std_rad=0.02, seed=7)
    second = SimulatedMocap(body, noise_std_m=0.01, noise_std_rad=0.02, seed=7)
    other = SimulatedMocap(body, noise_std_m=0.01, noise_std_rad=0.02, seed=8)
    a = np.array([first.pose() for _ in range(4000)])
    b = np.array([second.pose() for _ in range(4000)])
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a[0], other.pose())
    position_error = a[:, :3] - body.state[:3]
    np.testing.assert_allclose(position_error.std(axis=0), 0.01, rtol=0.06)
    np.testing.assert_allclose(position_error.mean(axis=0), 0.0, atol=0.001)
    # yaw 3.1 rad + noise crosses pi: measured angles are wrapped into [-pi, pi)
    assert np.all(a[:, 3:] >= -math.pi) and np.all(a[:, 3:] < math.pi)
    yaw_error = (a[:, 5] - 3.1 + math.pi) % (2 * math.pi) - math.pi
    assert yaw_error.std() == pytest.approx(0.02, rel=0.06)


def test_mocap_rate_limit_repeats_frames_between_camera_samples() -> None:
    body = MovingBody()
    mocap = SimulatedMocap(body, rate_hz=10.0)
    samples = []
    for i in range(25):
        body.state[0] = float(i)  # the body moves every 0.02 s tick
        samples.append(mocap.pose(t=0.02 * i)[0])
    # new frames at t = 0, 0.1, 0.2, 0.3, 0.4 -> ticks 0, 5, 10, 15, 20
    assert samples == [float(5 * (i // 5)) for i in range(25)]
    assert mocap.pose()[0] == 24.0  # no time given: a fresh sample


def test_mocap_errors() -> None:
    with pytest.raises(PlantError, match="no pose"):
        SimulatedMocap(object())  # type: ignore[arg-type]
    with pytest.raises(PlantError, match="noise_std_m"):
        SimulatedMocap(MovingBody(), noise_std_m=-1.0)
    with pytest.raises(PlantError, match="rate_hz"):
        SimulatedMocap(MovingBody(), rate_hz=0.0)

    class Flat:
        def pose(self) -> np.ndarray:
            return np.zeros(3)

    with pytest.raises(PlantError, match="6 numbers"):
        SimulatedMocap(Flat()).pose()

"""SimulatedVehicle: plant chosen by params, one period per apply, Vehicle semantics."""

from __future__ import annotations

import numpy as np
import pytest
from hilswarm.agents.control import ControlModel, StaticGain
from hilswarm.agents.errors import VehicleError
from hilswarm.agents.registry import resolve_vehicle
from hilswarm.agents.sim.integrator import Integrator
from hilswarm.agents.sim.plant import LinearPlant
from hilswarm.agents.sim.simulated_vehicle import STATE_CHANNEL, SimulatedVehicle
from hilswarm.agents.sim.spring_mass_damper import SpringMassDamper


def _smd(**overrides: object) -> SimulatedVehicle:
    kwargs: dict[str, object] = {
        "name": "smd",
        "params": {"plant": "spring_mass_damper", "plant_params": {"m": 2.0, "c1": 0.5}},
        "initial_state": [4.0, 0.0, -4.0, 0.0],
        "dt": 0.1,
    }
    kwargs.update(overrides)
    return SimulatedVehicle(**kwargs)  # type: ignore[arg-type]


def test_registry_and_sizes_from_the_plant() -> None:
    assert resolve_vehicle("simulated") is SimulatedVehicle
    vehicle = _smd()
    assert vehicle.needs_board is False
    assert (vehicle.n_inputs, vehicle.n_outputs) == (2, 4)
    assert vehicle.input_names == ("F1", "F2")
    assert vehicle.output_names == ("x", "xdot", "y", "ydot")
    assert isinstance(vehicle.plant, SpringMassDamper) and vehicle.plant.m == 2.0
    assert vehicle.exchange() is None
    integrator = SimulatedVehicle(
        params={"plant": "integrator", "plant_params": {"n_dims": 3}}, dt=0.5
    )
    assert (integrator.n_inputs, integrator.n_outputs) == (3, 3)
    np.testing.assert_array_equal(integrator.sense(0, 0.0), [0.0, 0.0, 0.0])  # default zeros
    # sizes are per instance: two vehicles with different plants coexist
    assert vehicle.n_inputs == 2 and integrator.n_inputs == 3


def test_apply_integrates_exactly_one_period() -> None:
    vehicle = _smd()
    plant = SpringMassDamper(m=2.0, c1=0.5)
    z = np.array([4.0, 0.0, -4.0, 0.0])
    np.testing.assert_array_equal(vehicle.sense(0, 0.0), z)
    for k in range(5):
        u = np.array([0.3 * k, -1.0])
        vehicle.apply(u)
        vehicle.exchange()
        z = z + 0.1 * plant.dynamics(0.0, z, u)  # one Euler step of dt
        np.testing.assert_allclose(vehicle.sense(k + 1, 0.1 * (k + 1)), z, rtol=1e-15)
        np.testing.assert_array_equal(vehicle.u, u)
    assert vehicle.time_s == pytest.approx(0.5)


def test_rk4_and_substeps() -> None:
    params = {
        "plant": "integrator",
        "plant_params": {"n_dims": 1},
        "integrator": "rk4",
        "substeps": 4,
    }
    vehicle = SimulatedVehicle(params=params, initial_state=[1.0], dt=0.2)
    vehicle.apply([2.0])
    assert vehicle.sense(1, 0.2)[0] == pytest.approx(1.4, rel=1e-14)
    plant = SpringMassDamper()
    smd = SimulatedVehicle(
        params={"integrator": "rk4", "substeps": 3}, initial_state=[1.0, 0.0, 0.0, 0.0], dt=0.3
    )
    smd.apply([0.0, 0.0])
    expected = plant.advance(0.0, [1.0, 0.0, 0.0, 0.0], [0.0, 0.0], 0.3, method="rk4", substeps=3)
    np.testing.assert_array_equal(smd.state, expected)


def test_limits_apply_before_the_plant() -> None:
    vehicle = _smd(limits={"F1": (-1.0, 1.0)}, initial_state=[0.0, 0.0, 0.0, 0.0])
    vehicle.apply([5.0, 5.0])
    np.testing.assert_array_equal(vehicle.u, [1.0, 5.0])
    # xdot grows by dt * F1 / m = 0.1 * 1 / 2
    assert vehicle.sense(1, 0.1)[1] == pytest.approx(0.05)


def test_state_telemetry_and_plant_instance() -> None:
    plant = LinearPlant([[0.0]], [[1.0]], C=[[2.0]])
    vehicle = SimulatedVehicle(name="lin", params={"plant": plant}, initial_state=[1.0], dt=1.0)
    assert vehicle.sense(0, 0.0)[0] == 2.0  # y = C x
    vehicle.apply([3.0])
    assert vehicle.sense(1, 1.0)[0] == 8.0
    k, _t, values = vehicle.telemetry[STATE_CHANNEL].arrays()
    np.testing.assert_array_equal(k, [0, 1])
    np.testing.assert_array_equal(values, [[1.0], [4.0]])


def test_safe_mode_keeps_the_world_moving_with_safe_inputs() -> None:
    vehicle = SimulatedVehicle(params={"plant": "integrator"}, initial_state=[0.0], dt=0.5)
    vehicle.apply([2.0])
    vehicle.exchange()
    assert vehicle.state[0] == 1.0
    vehicle.enter_safe_mode("test")
    vehicle.apply([2.0])  # ignored
    vehicle.exchange()  # advances with the safe input 0
    assert vehicle.state[0] == 1.0 and vehicle.time_s == 1.0
    assert vehicle.ignored_applies == 1


def test_closed_loop_with_control_model() -> None:
    """x' = u with u = -x (static gain -1) decays geometrically under Euler: (1 - dt)^k."""
    vehicle = SimulatedVehicle(params={"plant": "integrator"}, initial_state=[1.0], dt=0.25)
    model = ControlModel(StaticGain(), dt=0.25, n_inputs=1, n_outputs=1, params={"K": -1.0})
    for k in range(10):
        y = vehicle.sense(k, 0.25 * k)
        assert y[0] == pytest.approx(0.75**k)
        vehicle.apply(model.step(vehicle.u, y))
        vehicle.exchange()


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"dt": None}, "dt"),
        ({"params": {"plant": "no_such_plant"}}, "params.plant"),
        (
            {"params": {"plant": "spring_mass_damper", "plant_params": {"mass": 1}}},
            "plant_params do not fit",
        ),
        ({"params": {"plant_params": {"m": -1.0}}}, "m must be > 0"),
        ({"params": {"integrator": "ode45"}}, "params.integrator"),
        ({"params": {"substeps": 0}}, "params.substeps"),
        ({"params": {"plant_params": [1, 2]}}, "plant_params must be a table"),
        ({"params": {"unknown": 1}}, "unknown parameter"),
        ({"initial_state": [1.0, 2.0]}, "initial_state must have 4 entries"),
        ({"params": {"plant": "hilswarm.agents.sim.plant:PoseSource"}}, "not a ContinuousPlant"),
    ],
)
def test_bad_configuration_names_the_key(overrides: dict[str, object], message: str) -> None:
    with pytest.raises(VehicleError, match=message):
        _smd(**overrides)


def test_bad_u_and_state() -> None:
    vehicle = _smd()
    with pytest.raises(VehicleError, match="shape"):
        vehicle.apply([1.0])
    with pytest.raises(VehicleError, match="not finite"):
        vehicle.apply([np.nan, 0.0])
    with pytest.raises(VehicleError, match="4 finite numbers"):
        vehicle.set_state([1.0])
    vehicle.set_state([0.0, 1.0, 0.0, 0.0])
    assert vehicle.sense(0, 0.0)[1] == 1.0
    assert isinstance(Integrator(), Integrator)


def test_plant_specific_method_is_accepted() -> None:
    """DifferentialDrive integrates exactly (method "exact"); the vehicle passes it through."""
    vehicle = SimulatedVehicle(
        params={"plant": "differential_drive", "integrator": "exact"},
        initial_state=[0.0, 0.0, 0.0],
        dt=0.5,
    )
    assert vehicle.input_names == ("v_left", "v_right")
    vehicle.apply([0.04, 0.04])
    np.testing.assert_allclose(vehicle.sense(1, 0.5), [0.02, 0.0, 0.0], atol=1e-15)

"""Controller contract and ControlModel: closed forms, shapes, params, state, history."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
import pytest
from hilswarm.agents.control import (
    ContinuousModel,
    ContinuousStateSpace,
    Controller,
    ControlModel,
    DiscreteStateSpace,
    StateFeedback,
    StaticGain,
    TickInput,
)
from hilswarm.agents.errors import ControllerError, HilswarmError
from hilswarm.agents.registry import resolve_controller
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm


class Recorder(Controller):
    """Remembers every tick it sees; x_hat counts ticks; u = y[:2] + params offset."""

    n_states: ClassVar[int] = 1
    default_params: ClassVar[Mapping[str, Any]] = {"offset": 0.0}

    def __init__(self) -> None:
        self.ticks: list[TickInput] = []

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        self.ticks.append(tick)
        return tick.y[:2] + params["offset"], x_hat + 1


def test_registry_names_point_at_the_helpers() -> None:
    assert resolve_controller("static_gain") is StaticGain
    assert resolve_controller("state_feedback") is StateFeedback
    assert resolve_controller("discrete_state_space") is DiscreteStateSpace


def test_control_model_runs_once_per_tick_with_k_t_dt() -> None:
    recorder = Recorder()
    model = ControlModel(recorder, dt=0.25, n_inputs=2, t0=10.0, x0=[5.0])
    for k in range(4):
        u = model.step([0.0, 0.0], [k, 2 * k, 9], neighbours={"b": np.array([1.0]), "c": None})
        np.testing.assert_array_equal(u, [k, 2 * k])
    model.step([0.0, 0.0], [0, 0], t=99.0)
    assert [tick.k for tick in recorder.ticks] == [0, 1, 2, 3, 4]
    assert [tick.t for tick in recorder.ticks] == [10.0, 10.25, 10.5, 10.75, 99.0]
    assert {tick.dt for tick in recorder.ticks} == {0.25}
    assert recorder.ticks[0].neighbours["c"] is None
    np.testing.assert_array_equal(recorder.ticks[0].neighbours["b"], [1.0])
    assert model.k == 5
    np.testing.assert_array_equal(model.x_hat, [10.0])  # x0 = 5, +1 per tick


def test_tick_arrays_are_read_only() -> None:
    class Mutator(Controller):
        def step(self, tick, x_hat, params):  # type: ignore[no-untyped-def]
            tick.y[0] = 1.0
            return np.zeros(1), x_hat

    model = ControlModel(Mutator(), dt=0.1, n_inputs=1)
    y = np.array([0.0])
    with pytest.raises(ValueError, match="read-only"):
        model.step([0.0], y)
    assert y[0] == 0.0


def test_history_records_u_next_and_x_hat() -> None:
    model = ControlModel(Recorder(), dt=0.1, n_inputs=2, input_names=("left", "right"))
    for k in range(3):
        model.step([0, 0], [k, -k])
    u_history = model.history["u"]
    assert u_history.fields == ("left", "right")
    k, t, values = u_history.arrays()
    np.testing.assert_array_equal(k, [0, 1, 2])
    np.testing.assert_allclose(t, [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(values, [[0, 0], [1, -1], [2, -2]])
    np.testing.assert_array_equal(model.history["x_hat"].arrays().values, [[1], [2], [3]])
    model.reset()
    assert model.k == 0 and len(u_history) == 0
    np.testing.assert_array_equal(model.x_hat, [0.0])


def test_stateless_controller_has_no_x_hat_channel() -> None:
    model = ControlModel(StaticGain(), dt=0.1, n_inputs=1, params={"K": [[2.0]]})
    model.step([0.0], [3.0])
    assert model.history.names == ("u",)


def test_params_replaceable_and_validated_by_the_controller() -> None:
    model = ControlModel(Recorder(), dt=0.1, n_inputs=2)
    np.testing.assert_array_equal(model.step([0, 0], [1, 1]), [1, 1])
    model.set_params(offset=10.0)
    assert model.params["offset"] == 10.0
    np.testing.assert_array_equal(model.step([0, 0], [1, 1]), [11, 11])
    with pytest.raises(ControllerError, match=r"Recorder: unknown parameter\(s\) \['gain'\]"):
        model.set_params(gain=2.0)
    assert model.params == {"offset": 10.0}  # unchanged after a rejected update
    with pytest.raises(TypeError):
        model.params["offset"] = 3.0  # type: ignore[index]


def test_shape_errors_name_controller_and_shapes() -> None:
    class WrongU(Controller):
        def step(self, tick, x_hat, params):  # type: ignore[no-untyped-def]
            return np.zeros(3), x_hat

    class WrongX(Controller):
        n_states: ClassVar[int] = 2

        def step(self, tick, x_hat, params):  # type: ignore[no-untyped-def]
            return np.zeros(1), np.zeros(5)

    class NotATuple(Controller):
        def step(self, tick, x_hat, params):  # type: ignore[no-untyped-def]
            return np.zeros(1)

    class NanU(Controller):
        def step(self, tick, x_hat, params):  # type: ignore[no-untyped-def]
            return np.array([np.nan]), x_hat

    with pytest.raises(ControllerError, match=r"WrongU: returned u_\{k\+1\} .*\(1,\), got \(3,\)"):
        ControlModel(WrongU(), dt=0.1, n_inputs=1).step([0], [0])
    with pytest.raises(ControllerError, match=r"WrongX: returned x_hat.*\(2,\), got \(5,\)"):
        ControlModel(WrongX(), dt=0.1, n_inputs=1).step([0], [0])
    with pytest.raises(ControllerError, match=r"NotATuple\.step must return"):
        ControlModel(NotATuple(), dt=0.1, n_inputs=1).step([0], [0])
    with pytest.raises(ControllerError, match="NanU: returned a non-finite"):
        ControlModel(NanU(), dt=0.1, n_inputs=1).step([0], [0])
    model = ControlModel(Recorder(), dt=0.1, n_inputs=2, n_outputs=3)
    with pytest.raises(ControllerError, match=r"Recorder: u_k must have shape \(2,\), got \(3,\)"):
        model.step([0, 0, 0], [0, 0, 0])
    with pytest.raises(ControllerError, match=r"Recorder: y_k must have shape \(3,\), got \(2,\)"):
        model.step([0, 0], [0, 0])
    assert model.k == 0  # nothing ran


@pytest.mark.parametrize("dt", [0, -0.1, float("nan"), float("inf"), "0.1", True])
def test_bad_dt(dt: Any) -> None:
    with pytest.raises(ControllerError, match="dt"):
        ControlModel(Recorder(), dt=dt, n_inputs=2)


def test_controller_errors_are_value_errors() -> None:
    assert issubclass(ControllerError, HilswarmError) and issubclass(ControllerError, ValueError)


def test_static_gain() -> None:
    model = ControlModel(StaticGain(), dt=0.1, n_inputs=2, params={"K": [[1, 2, 3], [0, 0, -1]]})
    np.testing.assert_allclose(model.step([0, 0], [1, 1, 1]), [6, -1])
    assert isinstance(model.params["K"], np.ndarray)
    with pytest.raises(ControllerError, match="StaticGain: parameter 'K' is required"):
        ControlModel(StaticGain(), dt=0.1, n_inputs=1)
    with pytest.raises(ControllerError, match="StaticGain: parameter 'K' must be"):
        ControlModel(StaticGain(), dt=0.1, n_inputs=1, params={"K": [[1, 2], [3]]})
    with pytest.raises(ControllerError, match="non-finite"):
        ControlModel(StaticGain(), dt=0.1, n_inputs=1, params={"K": [[float("inf")]]})
    with pytest.raises(ControllerError, match=r"StaticGain: y_k must have shape \(3,\)"):
        model.step([0, 0], [1, 1])


def test_state_feedback_with_reference_and_feed_forward() -> None:
    gain = [[3.01, 4.0, 0.0, 0.0], [0.0, 0.0, 3.01, 4.0]]
    model = ControlModel(StateFeedback(), dt=0.1, n_inputs=2, params={"K": gain})
    np.testing.assert_allclose(model.step([0, 0], [4, 0, -4, 0]), [-12.04, 12.04])
    model.set_params(reference=[1, 0, 0, 0], u_ref=[0.5, 0.0])
    np.testing.assert_allclose(model.step([0, 0], [1, 1, 0, 0]), [0.5 - 4.0, 0.0])
    with pytest.raises(ControllerError, match="'reference' must have 4 entries"):
        model.set_params(reference=[1, 2])


def test_discrete_state_space_contract() -> None:
    a = np.array([[0.9, 0.1], [0.0, 0.8]])
    b = np.array([[1.0, 0.5], [0.0, 1.0]])  # w = [u; y], m = p = 1
    c = np.array([[1.0, -1.0]])
    d = np.array([[0.0, 2.0]])
    model = ControlModel(
        DiscreteStateSpace(),
        dt=0.1,
        n_inputs=1,
        params={"A": a, "B": b, "C": c, "D": d, "x0": [1.0, 2.0]},
    )
    x = np.array([1.0, 2.0])
    rng = np.random.default_rng(3)
    for _ in range(20):
        u_k, y_k = rng.normal(size=1), rng.normal(size=1)
        w = np.concatenate([u_k, y_k])
        expected_u = c @ x + d @ w
        x = a @ x + b @ w
        np.testing.assert_allclose(model.step(u_k, y_k), expected_u, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(model.x_hat, x, rtol=1e-12, atol=1e-12)


def test_discrete_state_space_shape_checks_and_stateless_form() -> None:
    with pytest.raises(ControllerError, match=r"DiscreteStateSpace: B must have shape \(2, 3\)"):
        DiscreteStateSpace().validate_params(
            {"A": np.eye(2), "B": np.ones((2, 2)), "C": np.ones((1, 2)), "D": np.ones((1, 3))}
        )
    model = ControlModel(DiscreteStateSpace(), dt=0.1, n_inputs=1, params={"D": [[0.5, 2.0]]})
    np.testing.assert_allclose(model.step([2.0], [1.0]), [3.0])
    assert model.x_hat.shape == (0,)


def test_observer_based_form_from_the_docstring() -> None:
    """u_{k+1} = -K x_hat_{k+1} is C = -K A, D = -K B."""
    a = np.array([[1.0, 0.1], [0.0, 1.0]])
    b = np.array([[0.0, 0.1], [0.1, 0.2]])
    gain = np.array([[2.0, 3.0]])
    model = ControlModel(
        DiscreteStateSpace(),
        dt=0.1,
        n_inputs=1,
        params={"A": a, "B": b, "C": -gain @ a, "D": -gain @ b},
    )
    u_next = model.step([0.3], [0.7])
    np.testing.assert_allclose(u_next, -gain @ model.x_hat)


def test_set_params_with_new_state_size_needs_reset() -> None:
    model = ControlModel(DiscreteStateSpace(), dt=0.1, n_inputs=1, params={"D": [[0.0, 1.0]]})
    model.set_params(A=[[0.5]], B=[[0.0, 1.0]], C=[[1.0]], reset_state=True)
    model.step([0.0], [1.0])
    np.testing.assert_allclose(model.step([0.0], [1.0]), [2.0])  # C x_1 + D w = 1 + 1
    assert model.history["x_hat"].fields == ("x0",)


def test_continuous_state_space_matches_exact_discretisation() -> None:
    """RK4 with substeps converges to the zero-order-hold discretisation (expm)."""
    a = np.array([[0.0, 1.0], [-2.0, -0.5]])
    b = np.array([[0.0, 0.0], [0.0, 1.0]])  # driven by y only
    c = np.array([[1.0, 0.0]])
    d = np.zeros((1, 2))
    dt = 0.2
    big = expm(np.block([[a, b], [np.zeros((2, 4))]]) * dt)
    ad, bd = big[:2, :2], big[:2, 2:]
    for integrator, substeps, tolerance in (("rk4", 4, 1e-6), ("euler", 200, 2e-3)):
        model = ControlModel(
            ContinuousStateSpace(),
            dt=dt,
            n_inputs=1,
            params={
                "A": a,
                "B": b,
                "C": c,
                "D": d,
                "x0": [1.0, 0.0],
                "integrator": integrator,
                "substeps": substeps,
            },
        )
        x = np.array([1.0, 0.0])
        for k in range(10):
            y = np.array([np.sin(k)])
            x = ad @ x + bd @ np.concatenate([[0.0], y])
            u_next = model.step([0.0], y)
            np.testing.assert_allclose(model.x_hat, x, atol=tolerance)
            np.testing.assert_allclose(u_next, c @ model.x_hat, atol=1e-12)


def test_continuous_model_euler_is_one_step() -> None:
    class Decay(ContinuousModel):
        n_states: ClassVar[int] = 1

        def derivative(self, t, x, u, y, params):  # type: ignore[no-untyped-def]
            return -x + y

        def output(self, t, x, u, y, params):  # type: ignore[no-untyped-def]
            return 2 * x

    model = ControlModel(Decay(), dt=0.5, n_inputs=1, x0=[1.0])
    np.testing.assert_allclose(model.step([0.0], [3.0]), [2 * (1 + 0.5 * (-1 + 3))])
    with pytest.raises(ControllerError, match="integrator must be one of"):
        model.set_params(integrator="ode45")
    with pytest.raises(ControllerError, match="substeps"):
        model.set_params(substeps=0)


@settings(max_examples=40, deadline=None)
@given(
    st.integers(min_value=1, max_value=4),
    st.integers(min_value=1, max_value=5),
    st.integers(min_value=0, max_value=2**31),
)
def test_static_gain_is_linear(m: int, p: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    gain = rng.normal(size=(m, p))
    model = ControlModel(StaticGain(), dt=0.1, n_inputs=m, n_outputs=p, params={"K": gain.tolist()})
    y1, y2 = rng.normal(size=p), rng.normal(size=p)
    u1, u2 = model.step(np.zeros(m), y1), model.step(np.zeros(m), y2)
    np.testing.assert_allclose(model.step(np.zeros(m), 2 * y1 - 3 * y2), 2 * u1 - 3 * u2, atol=1e-9)

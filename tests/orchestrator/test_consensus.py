"""LinearConsensus: converges to the average over a graph, in pure Python with ControlModel."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.control import ControlModel, TickInput
from hilswarm.agents.controllers.consensus import LinearConsensus
from hilswarm.agents.errors import ControllerError
from hilswarm.agents.registry import resolve_controller
from hilswarm.orchestrator.experiment import load_experiment
from hypothesis import given, settings
from hypothesis import strategies as st

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"


def run_consensus(
    adjacency: np.ndarray,
    x0: np.ndarray,
    *,
    dt: float,
    ticks: int,
    params: dict | None = None,
) -> np.ndarray:
    """Agents' tick order: y_k = x_k; u_{k+1} from y_k and neighbours' y_k; x += dt * u."""
    n = adjacency.shape[0]
    dims = x0.shape[1]
    names = [f"a{i}" for i in range(n)]
    models = [
        ControlModel(LinearConsensus(), dt=dt, n_inputs=dims, n_outputs=dims, params=params)
        for _ in range(n)
    ]
    x = x0.astype(float).copy()
    u = np.zeros_like(x)
    for _ in range(ticks):
        y = x.copy()
        for i, model in enumerate(models):
            heard = {names[j]: y[j] for j in np.flatnonzero(adjacency[i])}
            u[i] = model.step(u[i], y[i], neighbours=heard)
        x = x + dt * u
    return x


def test_registry_name_resolves() -> None:
    assert resolve_controller("consensus") is LinearConsensus


def test_ring_example_converges_to_the_average() -> None:
    experiment = load_experiment(GRAPHS / "consensus_ring.toml")
    x0 = np.array([spec.initial_state for spec in experiment.agents])
    gain = experiment.agents[0].params["gain"]
    x = run_consensus(
        experiment.adjacency.astype(int),
        x0,
        dt=experiment.dt,
        ticks=experiment.n_ticks,
        params={"gain": gain},
    )
    average = x0.mean(axis=0)
    assert average == pytest.approx([0.5, 0.0])
    assert np.allclose(x, average, atol=1e-3)


def test_average_is_preserved_every_tick_on_undirected_graph() -> None:
    a = np.array([[0, 1, 1, 0], [1, 0, 1, 0], [1, 1, 0, 1], [0, 0, 1, 0]])
    x0 = np.array([[0.0], [4.0], [-2.0], [10.0]])
    for ticks in (1, 5, 50):
        x = run_consensus(a, x0, dt=0.1, ticks=ticks)
        assert x.mean() == pytest.approx(x0.mean(), abs=1e-12)
    assert np.allclose(run_consensus(a, x0, dt=0.1, ticks=400), x0.mean(), atol=1e-6)


def test_directed_chain_converges_to_the_leader() -> None:
    a = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    x0 = np.array([[3.0], [-1.0], [7.0]])
    x = run_consensus(a, x0, dt=0.05, ticks=600, params={"gain": 2.0})
    assert np.allclose(x, 3.0, atol=1e-6)
    assert x[0, 0] == 3.0  # the leader hears nobody and never moves


def test_single_step_value_and_missing_neighbours() -> None:
    controller = LinearConsensus()
    params = controller.validate_params({"gain": 2.0, "weights": {"b": 0.5}})
    tick = TickInput(
        k=0,
        t=0.0,
        dt=0.1,
        u=np.zeros(2),
        y=np.array([1.0, 2.0]),
        neighbours={"b": np.array([3.0, 2.0]), "c": None, "d": np.array([0.0, 0.0])},
    )
    u, x_hat = controller.step(tick, np.zeros(0), params)
    # -2 * (0.5 * ([1,2]-[3,2]) + 1 * ([1,2]-[0,0])) = -2 * ([-1,0] + [1,2]) = [0, -4]
    assert u.tolist() == [0.0, -4.0]
    assert x_hat.shape == (0,)
    alone = TickInput(k=0, t=0.0, dt=0.1, u=np.zeros(2), y=np.ones(2), neighbours={"c": None})
    assert controller.step(alone, np.zeros(0), params)[0].tolist() == [0.0, 0.0]


def test_u_max_saturates() -> None:
    controller = LinearConsensus()
    params = controller.validate_params({"gain": 10.0, "u_max": 0.5})
    tick = TickInput(
        k=0, t=0.0, dt=0.1, u=np.zeros(1), y=np.array([0.0]), neighbours={"b": np.array([9.0])}
    )
    assert controller.step(tick, np.zeros(0), params)[0].tolist() == [0.5]


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"gain": 0}, "gain"),
        ({"gain": -1.0}, "gain"),
        ({"gain": "fast"}, "gain"),
        ({"u_max": 0}, "u_max"),
        ({"weights": [1, 2]}, "weights"),
        ({"weights": {"b": -1}}, "weights.b"),
        ({"speed": 1}, "unknown parameter"),
    ],
)
def test_bad_params_are_rejected(params: dict, match: str) -> None:
    with pytest.raises(ControllerError, match=match):
        LinearConsensus().validate_params(params)


def test_neighbour_of_other_size_is_an_error() -> None:
    controller = LinearConsensus()
    params = controller.validate_params({})
    tick = TickInput(
        k=0, t=0.0, dt=0.1, u=np.zeros(2), y=np.zeros(2), neighbours={"b": np.zeros(3)}
    )
    with pytest.raises(ControllerError, match="neighbour 'b'"):
        controller.step(tick, np.zeros(0), params)


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(min_value=2, max_value=7),
    seed=st.integers(min_value=0, max_value=2**32 - 1),
)
def test_connected_undirected_graphs_reach_the_average(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    a = np.zeros((n, n), dtype=int)
    order = rng.permutation(n)
    for i in range(n - 1):  # a random spanning path keeps the graph connected
        a[order[i], order[i + 1]] = a[order[i + 1], order[i]] = 1
    extra = np.triu(rng.random((n, n)) < 0.3, 1)
    a = np.maximum(a, (extra | extra.T).astype(int))
    x0 = rng.uniform(-5.0, 5.0, size=(n, 2))
    dt = 0.5 / (a.sum(axis=1).max())  # gain * dt * d_max = 0.5 < 1
    x = run_consensus(a, x0, dt=dt, ticks=600)
    assert np.allclose(x, x0.mean(axis=0), atol=1e-6)

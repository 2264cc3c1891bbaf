"""Graph facts: closed forms of algebraic connectivity, spanning trees, degrees, properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.orchestrator.graph_facts import (
    algebraic_connectivity,
    graph_facts,
    information_graph,
    laplacian,
)
from hypothesis import given, settings
from hypothesis import strategies as st


def names(n: int) -> list[str]:
    return [f"a{i}" for i in range(n)]


def path_graph(n: int) -> np.ndarray:
    a = np.zeros((n, n), dtype=int)
    for i in range(n - 1):
        a[i, i + 1] = a[i + 1, i] = 1
    return a


def ring_graph(n: int) -> np.ndarray:
    a = path_graph(n)
    a[0, n - 1] = a[n - 1, 0] = 1
    return a


def complete_graph(n: int) -> np.ndarray:
    return np.ones((n, n), dtype=int) - np.eye(n, dtype=int)


@pytest.mark.parametrize("n", [2, 3, 5, 8, 13])
def test_path_lambda2_closed_form(n: int) -> None:
    expected = 2.0 * (1.0 - math.cos(math.pi / n))
    assert algebraic_connectivity(path_graph(n)) == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("n", [3, 4, 6, 10])
def test_ring_lambda2_closed_form(n: int) -> None:
    expected = 2.0 * (1.0 - math.cos(2.0 * math.pi / n))
    facts = graph_facts(names(n), ring_graph(n))
    assert facts.algebraic_connectivity == pytest.approx(expected, rel=1e-9)
    # Undirected: the directed Laplacian is the same matrix, so the rates agree.
    assert facts.consensus_rate == pytest.approx(expected, rel=1e-9)
    assert facts.symmetric and facts.strongly_connected and facts.has_spanning_tree
    assert set(facts.in_degree.values()) == {2} and set(facts.out_degree.values()) == {2}


@pytest.mark.parametrize("n", [2, 4, 7])
def test_complete_graph_lambda2_is_n(n: int) -> None:
    assert algebraic_connectivity(complete_graph(n)) == pytest.approx(n, rel=1e-9)


def test_star_lambda2_is_one() -> None:
    a = np.zeros((5, 5), dtype=int)
    a[0, 1:] = a[1:, 0] = 1
    assert algebraic_connectivity(a) == pytest.approx(1.0)


def test_directed_chain_leader_and_spanning_tree() -> None:
    # leader -> f1 -> f2 (f1 receives leader, f2 receives f1)
    a = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    facts = graph_facts(["leader", "f1", "f2"], a)
    assert facts.leaders == ("leader",)
    assert facts.roots == ("leader",)
    assert facts.has_spanning_tree
    assert facts.weakly_connected and not facts.strongly_connected
    assert facts.in_degree == {"leader": 0, "f1": 1, "f2": 1}
    assert facts.out_degree == {"leader": 1, "f1": 1, "f2": 0}
    assert facts.n_edges == 2 and not facts.symmetric
    # Undirected version is the path P3: lambda_2 = 1.
    assert facts.algebraic_connectivity == pytest.approx(1.0)
    # L = [[0,0,0],[-1,1,0],[0,-1,1]]: eigenvalues 0, 1, 1.
    assert facts.consensus_rate == pytest.approx(1.0)
    graph = information_graph(["leader", "f1", "f2"], a)
    assert set(graph.edges) == {("leader", "f1"), ("f1", "f2")}


def test_two_sources_have_no_spanning_tree() -> None:
    # b hears a and c; a and c hear nobody: two roots, no single spanning tree.
    a = np.array([[0, 0, 0], [1, 0, 1], [0, 0, 0]])
    facts = graph_facts(["a", "b", "c"], a)
    assert not facts.has_spanning_tree and facts.roots == ()
    assert facts.leaders == ("a", "c")
    assert facts.weakly_connected
    assert facts.consensus_rate == 0.0


def test_disconnected_graph_components_and_isolated() -> None:
    a = np.zeros((4, 4), dtype=int)
    a[0, 1] = a[1, 0] = 1
    facts = graph_facts(names(4), a)
    assert not facts.weakly_connected
    assert facts.components == (("a0", "a1"), ("a2",), ("a3",))
    assert facts.isolated == ("a2", "a3")
    assert facts.algebraic_connectivity == 0.0
    assert "component 2: a2" in facts.format()


def test_single_agent() -> None:
    facts = graph_facts(["solo"], np.zeros((1, 1), dtype=int))
    assert facts.weakly_connected and facts.has_spanning_tree and facts.roots == ("solo",)
    assert facts.algebraic_connectivity == 0.0


def test_shape_mismatch_raises() -> None:
    with pytest.raises(ValueError, match="does not match 3 agent names"):
        graph_facts(["a", "b", "c"], np.zeros((2, 2)))


def test_format_lists_every_agent() -> None:
    text = graph_facts(names(6), ring_graph(6)).format()
    assert "algebraic connectivity" in text
    for name in names(6):
        assert f"\n{name}" in text


@st.composite
def adjacency_matrices(draw: st.DrawFn) -> np.ndarray:
    n = draw(st.integers(min_value=2, max_value=8))
    bits = draw(st.lists(st.integers(0, 1), min_size=n * n, max_size=n * n))
    a = np.array(bits, dtype=int).reshape(n, n)
    np.fill_diagonal(a, 0)
    return a


@settings(max_examples=150, deadline=None)
@given(adjacency_matrices())
def test_properties(a: np.ndarray) -> None:
    n = a.shape[0]
    facts = graph_facts(names(n), a)
    # lambda_2 > 0 exactly when the undirected graph is connected.
    assert (facts.algebraic_connectivity > 1e-9) == facts.weakly_connected
    # Strongly connected implies a spanning tree with every agent a root.
    if facts.strongly_connected:
        assert facts.has_spanning_tree and set(facts.roots) == set(facts.names)
    # A spanning tree implies weak connectivity and at most one leader.
    if facts.has_spanning_tree:
        assert facts.weakly_connected and len(facts.leaders) <= 1
    # Degrees are row and column sums; the Laplacian's rows sum to zero.
    assert sum(facts.in_degree.values()) == sum(facts.out_degree.values()) == facts.n_edges
    assert np.allclose(laplacian(a).sum(axis=1), 0.0)
    # With a spanning tree, the directed Laplacian has exactly one zero eigenvalue.
    eigenvalues = np.linalg.eigvals(laplacian(a))
    zeros = int(np.sum(np.abs(eigenvalues) < 1e-7))
    if facts.has_spanning_tree:
        assert zeros == 1 and facts.consensus_rate > 0

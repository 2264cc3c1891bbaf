"""Facts about an experiment's communication graph, as ``hilswarm graph`` shows them.

The graph is the directed graph of *information flow*: an edge ``j -> i`` for every
``A[i][j] = 1`` (agent ``i`` receives agent ``j``'s output). So the in-degree of an agent is the
number of agents it hears, its out-degree the number of agents that hear it.

* Consensus over the graph reaches agreement for every initial condition iff the graph has a
  directed spanning tree (some agent's information reaches every other agent); the agents that
  can be its root are :attr:`GraphFacts.roots`.
* The algebraic connectivity ``lambda_2`` of the undirected graph (edges made two-way) is the
  second-smallest eigenvalue of its Laplacian ``L = D - A_sym``; it is > 0 iff that graph is
  connected, and sets the convergence rate of undirected consensus.
* The directed Laplacian ``L = diag(in-degrees) - A`` has one eigenvalue 0 per root component;
  the smallest real part of the others (:attr:`GraphFacts.consensus_rate` [1/s per unit gain])
  sets how fast continuous-time consensus converges.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import networkx as nx
import numpy as np
from numpy.typing import ArrayLike

#: Eigenvalues whose magnitude is below this are treated as zero.
ZERO_TOLERANCE = 1e-9
#: Largest graph whose spectral facts (algebraic connectivity, consensus rate) are computed:
#: a dense eigen-decomposition is O(n^3) time and O(n^2) memory (1,000 agents: seconds;
#: 10,000 agents: minutes and GBs). The default agent cap of an experiment is the same.
SPECTRAL_MAX_AGENTS = 256


def information_graph(names: Sequence[str], adjacency: ArrayLike) -> nx.DiGraph:
    """The directed graph with an edge ``j -> i`` for every ``A[i][j] = 1``."""
    matrix = np.asarray(adjacency)
    graph = nx.DiGraph()
    graph.add_nodes_from(names)
    for i, j in zip(*np.nonzero(matrix), strict=True):
        graph.add_edge(names[int(j)], names[int(i)])
    return graph


def laplacian(adjacency: ArrayLike) -> np.ndarray:
    """The (in-degree) Laplacian ``L = diag(row sums of A) - A`` as floats."""
    matrix = np.asarray(adjacency, dtype=np.float64)
    return np.diag(matrix.sum(axis=1)) - matrix


def algebraic_connectivity(adjacency: ArrayLike) -> float:
    """Second-smallest Laplacian eigenvalue of the undirected graph ``A`` or ``A^T`` (``>= 0``).

    Returns 0.0 for a graph with fewer than two agents.
    """
    matrix = np.asarray(adjacency, dtype=np.float64)
    if matrix.shape[0] < 2:
        return 0.0
    symmetric = ((matrix + matrix.T) > 0).astype(np.float64)
    eigenvalues = np.sort(np.linalg.eigvalsh(laplacian(symmetric)))
    value = float(eigenvalues[1])
    return 0.0 if abs(value) < ZERO_TOLERANCE else value


@dataclass(frozen=True)
class GraphFacts:
    """What the adjacency matrix says about the swarm.

    Attributes:
        names: agent names in graph order.
        n_edges: number of directed edges (ones in ``A``).
        symmetric: ``A == A^T`` (every link is two-way).
        weakly_connected: connected when edge directions are ignored.
        strongly_connected: every agent's output reaches every other agent.
        has_spanning_tree: some agent's output reaches every agent (consensus is possible).
        roots: agents whose output reaches every agent (empty without a spanning tree).
        leaders: agents that hear nobody (in-degree 0).
        isolated: agents that neither hear nor are heard by anyone.
        in_degree: per agent, how many agents it hears (row sum of ``A``).
        out_degree: per agent, how many agents hear it (column sum of ``A``).
        algebraic_connectivity: ``lambda_2`` of the undirected Laplacian (``None`` above
            :data:`SPECTRAL_MAX_AGENTS` agents: not computed).
        consensus_rate: smallest real part of the non-zero eigenvalues of the directed
            Laplacian (0.0 without a spanning tree; ``None`` when not computed).
        components: weakly connected components, each a tuple of names in graph order.
    """

    names: tuple[str, ...]
    n_edges: int
    symmetric: bool
    weakly_connected: bool
    strongly_connected: bool
    has_spanning_tree: bool
    roots: tuple[str, ...]
    leaders: tuple[str, ...]
    isolated: tuple[str, ...]
    in_degree: dict[str, int]
    out_degree: dict[str, int]
    algebraic_connectivity: float | None
    consensus_rate: float | None
    components: tuple[tuple[str, ...], ...]

    @property
    def max_in_degree(self) -> int:
        """Largest number of agents any agent hears."""
        return max(self.in_degree.values(), default=0)

    def format(self) -> str:
        """Multi-line text for ``hilswarm graph``."""
        yes = {True: "yes", False: "no"}
        width = max([len("agent"), *(len(name) for name in self.names)])
        lines = [
            f"agents: {len(self.names)}    edges (who hears whom): {self.n_edges}",
            f"symmetric (two-way links): {yes[self.symmetric]}",
            f"weakly connected: {yes[self.weakly_connected]}"
            + ("" if self.weakly_connected else f" ({len(self.components)} components)"),
            f"strongly connected: {yes[self.strongly_connected]}",
            f"spanning tree (consensus possible): {yes[self.has_spanning_tree]}"
            + (f"  roots: {', '.join(self.roots)}" if self.roots else ""),
            f"leaders (hear nobody): {', '.join(self.leaders) or '-'}",
            f"isolated: {', '.join(self.isolated) or '-'}",
            "algebraic connectivity (undirected lambda_2): "
            f"{_spectral(self.algebraic_connectivity)}",
            f"consensus rate (directed Laplacian, min Re lambda != 0): "
            f"{_spectral(self.consensus_rate)}",
            "",
            f"{'agent':<{width}}  in  out",
        ]
        lines.extend(
            f"{name:<{width}}  {self.in_degree[name]:>2}  {self.out_degree[name]:>3}"
            for name in self.names
        )
        if not self.weakly_connected:
            lines.append("")
            lines.extend(
                f"component {n + 1}: {', '.join(component)}"
                for n, component in enumerate(self.components)
            )
        return "\n".join(lines)


def graph_facts(names: Sequence[str], adjacency: ArrayLike) -> GraphFacts:
    """Compute the :class:`GraphFacts` of ``A`` (``A[i][j] = 1``: ``i`` receives ``j``).

    Raises:
        ValueError: ``A`` is not square or does not match ``names``.
    """
    names = tuple(names)
    matrix = np.asarray(adjacency)
    if matrix.ndim != 2 or matrix.shape != (len(names), len(names)):
        raise ValueError(
            f"adjacency of shape {matrix.shape} does not match {len(names)} agent names"
        )
    graph = information_graph(names, matrix)
    order = {name: i for i, name in enumerate(names)}
    rows, columns = matrix.sum(axis=1).tolist(), matrix.sum(axis=0).tolist()
    in_degree = {name: int(rows[i]) for i, name in enumerate(names)}
    out_degree = {name: int(columns[i]) for i, name in enumerate(names)}
    components = tuple(
        tuple(sorted(component, key=order.__getitem__))
        for component in sorted(
            nx.weakly_connected_components(graph), key=lambda c: min(order[n] for n in c)
        )
    )
    roots = _roots(graph, order)
    spectral = len(names) <= SPECTRAL_MAX_AGENTS
    return GraphFacts(
        names=names,
        n_edges=int(np.count_nonzero(matrix)),
        symmetric=bool(np.array_equal(matrix, matrix.T)),
        weakly_connected=len(names) > 0 and nx.is_weakly_connected(graph),
        strongly_connected=len(names) > 0 and nx.is_strongly_connected(graph),
        has_spanning_tree=bool(roots),
        roots=roots,
        leaders=tuple(name for name in names if in_degree[name] == 0),
        isolated=tuple(name for name in names if in_degree[name] == 0 and out_degree[name] == 0),
        in_degree=in_degree,
        out_degree=out_degree,
        algebraic_connectivity=algebraic_connectivity(matrix) if spectral else None,
        consensus_rate=(_consensus_rate(matrix) if roots else 0.0) if spectral else None,
        components=components,
    )


def _roots(graph: nx.DiGraph, order: dict[str, int]) -> tuple[str, ...]:
    """Agents from which every agent is reachable: the single source component, if any."""
    if graph.number_of_nodes() == 0:
        return ()
    condensed = nx.condensation(graph)
    sources = [node for node in condensed.nodes if condensed.in_degree(node) == 0]
    if len(sources) != 1:
        return ()
    members = condensed.nodes[sources[0]]["members"]
    return tuple(sorted(members, key=order.__getitem__))


def _consensus_rate(matrix: np.ndarray) -> float:
    """Smallest real part among the directed Laplacian's eigenvalues except one zero."""
    if matrix.shape[0] < 2:
        return 0.0
    eigenvalues = np.linalg.eigvals(laplacian(matrix))
    real_parts = np.sort(eigenvalues.real)
    # With a spanning tree exactly one eigenvalue is 0 and the others have Re > 0.
    value = float(real_parts[1])
    return 0.0 if abs(value) < ZERO_TOLERANCE else value


def _spectral(value: float | None) -> str:
    if value is None:
        return f"not computed (more than {SPECTRAL_MAX_AGENTS} agents)"
    return f"{value:.6g}"

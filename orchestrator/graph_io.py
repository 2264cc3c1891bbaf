"""Read the communication graph of an experiment: inline matrix or a file beside it.

Convention everywhere: ``A[i][j] = 1`` means agent ``i`` *receives* agent ``j``'s output. In a
graph file read by networkx (GraphML, GML, edge list, adjacency list) an edge ``u -> v`` is the
direction information flows, so it means ``v`` receives ``u``: ``A[v][u] = 1``. An undirected
edge means both agents hear each other. A CSV file is the matrix ``A`` itself (row ``i`` lists
whom agent ``i`` hears), optionally with a header row of agent names.

Every function appends :class:`~hilswarm.orchestrator.problems.Problem` s to a list instead of
raising, so one pass reports everything wrong with a file.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np
from hilswarm.orchestrator.problems import Problem

#: file suffix -> networkx reader kind (CSV is read here, without networkx).
NETWORKX_SUFFIXES: dict[str, str] = {
    ".graphml": "graphml",
    ".gml": "gml",
    ".edgelist": "edgelist",
    ".edges": "edgelist",
    ".adjlist": "adjlist",
}
GRAPH_FILE_SUFFIXES: tuple[str, ...] = (".csv", *NETWORKX_SUFFIXES)


def validate_matrix(
    rows: Any, names: Sequence[str], *, file: Path | str, key: str, problems: list[Problem]
) -> np.ndarray | None:
    """Check an adjacency matrix given as rows; return it as an ``int8`` array or ``None``.

    Checks: a list of lists, square, one row per agent name, every entry 0 or 1 (booleans and
    whole floats such as ``1.0`` are accepted), zero diagonal (an agent does not receive its own
    output over the bus: it has it already).
    """
    n = len(names)
    if not isinstance(rows, list | tuple):
        problems.append(Problem(file, key, "must be a list of rows (a list of lists of 0/1)"))
        return None
    ok = True
    for i, row in enumerate(rows):  # every bad row is reported; the others are still checked
        if not isinstance(row, list | tuple):
            problems.append(
                Problem(file, f"{key}[{i}]", f"row is {row!r}; expected a list of 0/1 per agent")
            )
            ok = False
    rows = [row if isinstance(row, list | tuple) else [0] * n for row in rows]
    if len(rows) != n:
        problems.append(
            Problem(
                file,
                key,
                f"has {len(rows)} rows, expected {n} (one per agent: {_names(names)}); "
                "the matrix must be square",
            )
        )
        ok = False
    for i, row in enumerate(rows):
        if len(row) != n:
            problems.append(
                Problem(
                    file,
                    f"{key}[{i}]",
                    f"row has {len(row)} entries, expected {n} (one per agent); "
                    "the matrix must be square",
                )
            )
            ok = False
    size = max([n, len(rows), *(len(row) for row in rows)])
    matrix = np.zeros((size, size), dtype=np.int8)
    for i, row in enumerate(rows):
        for j, value in enumerate(row):
            entry = _zero_one(value)
            if entry is None:
                problems.append(
                    Problem(file, f"{key}[{i}][{j}]", f"entry is {value!r}; expected 0 or 1")
                )
                ok = False
            else:
                matrix[i, j] = entry
    for i in range(size):
        if matrix[i, i] != 0:
            who = f" ({names[i]})" if i < n else ""
            problems.append(
                Problem(
                    file,
                    f"{key}[{i}][{i}]",
                    f"diagonal entry is 1{who}; an agent does not receive its own output, "
                    "the diagonal must be 0",
                )
            )
            ok = False
    return matrix[:n, :n] if ok else None


def read_graph_file(
    path: Path,
    names: Sequence[str] | None,
    *,
    undirected: bool,
    file: Path | str,
    key: str,
    problems: list[Problem],
) -> tuple[list[str], np.ndarray] | None:
    """Read ``path`` (CSV or a networkx format) into ``(agent names, A)``.

    Args:
        path: the graph file (already resolved against the experiment file's folder).
        names: ``[graph] agents`` if the experiment gives it (fixes the row order), else
            ``None`` (names come from the file: CSV header or the node order of the file).
        undirected: for edge/adjacency lists, make every edge two-way.
        file: the experiment file (where ``key`` lives), for problem reports.
        key: the TOML key naming the graph file, e.g. ``"graph.file"``.
        problems: where problems are appended.
    """
    if not path.is_file():
        problems.append(Problem(file, key, f"graph file {str(path)!r} does not exist"))
        return None
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return _read_csv(path, names, problems=problems)
    kind = NETWORKX_SUFFIXES.get(suffix)
    if kind is None:
        problems.append(
            Problem(
                file,
                key,
                f"graph file {path.name!r} has unknown suffix {suffix!r}; expected one of "
                + ", ".join(GRAPH_FILE_SUFFIXES),
            )
        )
        return None
    return _read_networkx(path, kind, names, undirected=undirected, problems=problems)


def _read_csv(
    path: Path, names: Sequence[str] | None, *, problems: list[Problem]
) -> tuple[list[str], np.ndarray] | None:
    with path.open(newline="", encoding="utf-8") as handle:
        lines = [
            [cell.strip() for cell in row]
            for row in csv.reader(handle)
            if row and any(c.strip() for c in row) and not row[0].strip().startswith("#")
        ]
    if not lines:
        problems.append(Problem(path, "", "CSV graph file is empty; expected an adjacency matrix"))
        return None
    header: list[str] | None = None
    if any(_number(cell) is None for cell in lines[0]):
        header, lines = lines[0], lines[1:]
        # A header may start with an empty corner cell when each row starts with its name.
        if header and header[0] == "":
            header = header[1:]
            labels = [row[0] if row else "" for row in lines]
            lines = [row[1:] for row in lines]
            for i, (label, expected) in enumerate(zip(labels, header, strict=False)):
                if label != expected:
                    problems.append(
                        Problem(
                            path,
                            f"row {i + 2}",
                            f"row label {label!r} does not match column {i + 1} name "
                            f"{expected!r}; rows and columns must list agents in the same order",
                        )
                    )
    if header is not None:
        if names is not None and list(header) != list(names):
            problems.append(
                Problem(
                    path,
                    "header",
                    f"names {_names(header)} differ from [graph] agents {_names(names)} "
                    "(same names in the same order expected)",
                )
            )
            return None
        names = list(header)
    if names is None:
        problems.append(
            Problem(
                path,
                "",
                "CSV matrix has no header row of agent names and [graph] agents is not given; "
                "add one of them",
            )
        )
        return None
    rows = [[_number(cell) if _number(cell) is not None else cell for cell in row] for row in lines]
    matrix = validate_matrix(rows, names, file=path, key="matrix", problems=problems)
    return (list(names), matrix) if matrix is not None else None


def _read_networkx(
    path: Path,
    kind: str,
    names: Sequence[str] | None,
    *,
    undirected: bool,
    problems: list[Problem],
) -> tuple[list[str], np.ndarray] | None:
    try:
        if kind == "graphml":
            graph = nx.read_graphml(path)
        elif kind == "gml":
            graph = nx.read_gml(path)
        elif kind == "edgelist":
            graph = nx.read_edgelist(path, create_using=nx.DiGraph, nodetype=str, data=False)
        else:
            graph = nx.read_adjlist(path, create_using=nx.DiGraph, nodetype=str)
    except (nx.NetworkXError, OSError, ValueError, SyntaxError) as exc:
        problems.append(Problem(path, "", f"cannot read {kind} graph file: {exc}"))
        return None
    nodes = [str(node) for node in graph.nodes]
    if names is None:
        names = nodes
    elif set(names) != set(nodes):
        only_file = sorted(set(nodes) - set(names))
        only_list = sorted(set(names) - set(nodes))
        problems.append(
            Problem(
                path,
                "",
                f"nodes differ from [graph] agents: only in the file {only_file}, "
                f"only in [graph] agents {only_list}",
            )
        )
        return None
    index = {name: i for i, name in enumerate(names)}
    matrix = np.zeros((len(names), len(names)), dtype=np.int8)
    two_way = undirected or not graph.is_directed()
    for u, v in graph.edges():
        if u == v:
            problems.append(
                Problem(path, f"edge {u}->{v}", "self-loop; an agent does not receive itself")
            )
            continue
        source, target = index[str(u)], index[str(v)]
        matrix[target, source] = 1  # information flows u -> v: v receives u
        if two_way:
            matrix[source, target] = 1
    return list(names), matrix


def _zero_one(value: Any) -> int | None:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int | float) and value in (0, 1):
        return int(value)
    return None


def _number(cell: str) -> float | None:
    try:
        return float(cell)
    except ValueError:
        return None


def _names(names: Sequence[str]) -> str:
    return "[" + ", ".join(names) + "]"

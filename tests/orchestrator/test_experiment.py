"""Experiment files: loading, the A[i][j] convention, graph file forms, overrides, problems."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
from hilswarm.orchestrator.experiment import (
    AgentSpec,
    Experiment,
    ExperimentError,
    load_experiment,
    parse_experiment,
    parse_link_overrides,
)
from hilswarm.orchestrator.problems import Problem

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"

HEADER = """
[experiment]
name = "t1"
rate_hz = 10
duration_s = 2
"""

AGENTS_ABC = """
[defaults]
vehicle = "simulated"
controller = "consensus"
vehicle_params = { plant = "integrator" }
[agents.a]
initial_state = [1.0]
[agents.b]
initial_state = [2.0]
params = { gain = 0.5 }
[agents.c]
initial_state = [3]
"""


def write(tmp_path: Path, text: str, name: str = "exp.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text), encoding="utf-8")
    return path


def problems_of(path: Path, **kwargs) -> list[Problem]:
    with pytest.raises(ExperimentError) as info:
        load_experiment(path, **kwargs)
    return list(info.value.problems)


def test_inline_graph_and_receive_convention(tmp_path: Path) -> None:
    # b hears a and c; c hears b; a hears nobody.
    path = write(
        tmp_path,
        HEADER
        + """
        [graph]
        agents = ["a", "b", "c"]
        adjacency = [[0, 0, 0], [1, 0, 1], [0, 1, 0]]
        """
        + AGENTS_ABC,
    )
    experiment = load_experiment(path)
    assert isinstance(experiment, Experiment)
    assert experiment.name == "t1"
    assert experiment.rate_hz == 10.0 and experiment.dt == pytest.approx(0.1)
    assert experiment.duration_s == 2.0 and experiment.n_ticks == 20
    assert experiment.mode == "lockstep" and experiment.on_agent_loss == "stop"
    assert experiment.agent_names == ("a", "b", "c")
    assert experiment.neighbours("a") == ()
    assert experiment.neighbours("b") == ("a", "c")
    assert experiment.neighbours("c") == ("b",)
    assert experiment.receivers("a") == ("b",)
    assert experiment.index("c") == 2
    assert experiment.adjacency.dtype == np.int8
    assert not experiment.adjacency.flags.writeable
    assert experiment.source_text == path.read_text()
    assert experiment.graph_dict() == {
        "agents": ["a", "b", "c"],
        "adjacency": [[0, 0, 0], [1, 0, 1], [0, 1, 0]],
    }


def test_agent_spec_fields_and_defaults_merge(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        HEADER
        + """
        [graph]
        agents = ["a", "b", "c"]
        adjacency = [[0, 1, 0], [1, 0, 1], [0, 1, 0]]
        """
        + AGENTS_ABC
        + """
        [agents.a.pinout.motor]
        left_pwm = 5
        left_fwd = "D4"
        """,
    )
    experiment = load_experiment(path)
    a, b = experiment.agent("a"), experiment.agent("b")
    assert isinstance(a, AgentSpec)
    assert a == AgentSpec(
        name="a",
        vehicle="simulated",
        link=None,
        controller="consensus",
        params={},
        vehicle_params={"plant": "integrator"},
        pinout={"motor": {"left_pwm": 5, "left_fwd": "D4"}},
        initial_state=(1.0,),
        calibration=None,
    )
    assert b.params == {"gain": 0.5}
    assert experiment.agent("c").initial_state == (3.0,)
    with pytest.raises(KeyError, match="no agent 'zz'"):
        experiment.agent("zz")


def test_defaults_are_merged_recursively(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        HEADER
        + """
        [graph]
        agents = ["a"]
        adjacency = [[0]]
        [defaults]
        vehicle = "simulated"
        controller = "consensus"
        vehicle_params = { plant = "integrator", plant_params = { n_dims = 2 } }
        [agents.a]
        vehicle_params = { plant_params = { n_dims = 3 } }
        """,
    )
    spec = load_experiment(path).agent("a")
    assert spec.vehicle_params == {"plant": "integrator", "plant_params": {"n_dims": 3}}


def test_overrides_replace_mode_duration_and_links(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        HEADER
        + """
        [graph]
        agents = ["a", "b", "c"]
        adjacency = [[0, 1, 0], [1, 0, 1], [0, 1, 0]]
        """
        + AGENTS_ABC,
    )
    experiment = load_experiment(
        path,
        overrides={
            "mode": "realtime",
            "duration_s": 5.0,
            "rate_hz": 50,
            "links": {"b": "socket://127.0.0.1:5555"},
        },
    )
    assert experiment.mode == "realtime"
    assert experiment.duration_s == 5.0 and experiment.rate_hz == 50.0
    assert experiment.agent("b").link == "socket://127.0.0.1:5555"
    assert experiment.agent("a").link is None

    problems = problems_of(
        path, overrides={"mode": "fast", "links": {"nobody": "sim://"}, "colour": 1}
    )
    keys = {p.key for p in problems}
    assert {"override mode", "--link nobody", "override colour"} <= keys


def test_parse_link_overrides() -> None:
    assert parse_link_overrides(["leader=/dev/ttyUSB0", "f1 = sim://"]) == {
        "leader": "/dev/ttyUSB0",
        "f1": "sim://",
    }
    with pytest.raises(ExperimentError, match="expected NAME=URL"):
        parse_link_overrides(["leader"])


def test_csv_graph_file_with_header(tmp_path: Path) -> None:
    (tmp_path / "g.csv").write_text("a,b,c\n0,1,0\n1,0,1\n0,1,0\n")
    path = write(tmp_path, HEADER + '[graph]\nfile = "g.csv"\n' + AGENTS_ABC)
    experiment = load_experiment(path)
    assert experiment.agent_names == ("a", "b", "c")
    assert experiment.neighbours("b") == ("a", "c")
    assert experiment.graph_file == (tmp_path / "g.csv").resolve()


def test_csv_graph_file_with_row_labels_and_agents_list(tmp_path: Path) -> None:
    (tmp_path / "g.csv").write_text(",a,b,c\na,0,0,0\nb,1,0,0\nc,0,1,0\n")
    path = write(tmp_path, HEADER + '[graph]\nfile = "g.csv"\n' + AGENTS_ABC)
    experiment = load_experiment(path)
    assert experiment.neighbours("c") == ("b",)
    # Without a header, [graph] agents names the rows.
    (tmp_path / "h.csv").write_text("0,0,0\n1,0,0\n0,1,0\n")
    path = write(
        tmp_path, HEADER + '[graph]\nagents = ["a", "b", "c"]\nfile = "h.csv"\n' + AGENTS_ABC
    )
    assert load_experiment(path).neighbours("b") == ("a",)


def test_edgelist_file_edges_are_information_flow(tmp_path: Path) -> None:
    # "a b" means information flows a -> b: b receives a.
    (tmp_path / "g.edgelist").write_text("a b\nb c\n")
    path = write(tmp_path, HEADER + '[graph]\nfile = "g.edgelist"\n' + AGENTS_ABC)
    experiment = load_experiment(path)
    assert experiment.neighbours("b") == ("a",)
    assert experiment.neighbours("c") == ("b",)
    assert experiment.neighbours("a") == ()
    path = write(
        tmp_path,
        HEADER + '[graph]\nfile = "g.edgelist"\nundirected = true\n' + AGENTS_ABC,
        name="u.toml",
    )
    assert load_experiment(path).neighbours("b") == ("a", "c")


def test_graphml_file_undirected(tmp_path: Path) -> None:
    import networkx as nx

    graph = nx.Graph()
    graph.add_edges_from([("a", "b"), ("b", "c")])
    nx.write_graphml(graph, tmp_path / "g.graphml")
    path = write(
        tmp_path,
        HEADER + '[graph]\nagents = ["c", "b", "a"]\nfile = "g.graphml"\n' + AGENTS_ABC,
    )
    experiment = load_experiment(path)
    assert experiment.agent_names == ("c", "b", "a")  # [graph] agents fixes the order
    assert experiment.neighbours("b") == ("c", "a")
    assert experiment.adjacency.tolist() == [[0, 1, 0], [1, 0, 1], [0, 1, 0]]


def test_example_files_load() -> None:
    ring = load_experiment(GRAPHS / "consensus_ring.toml")
    ring_file = load_experiment(GRAPHS / "consensus_ring_file.toml")
    assert np.array_equal(ring.adjacency, ring_file.adjacency)
    assert ring.agent_names == ring_file.agent_names == tuple(f"a{i}" for i in range(6))
    assert ring.neighbours("a0") == ("a1", "a3", "a5")
    lead = load_experiment(GRAPHS / "lead_follow.toml")
    assert lead.neighbours("f1") == ("leader",) and lead.neighbours("f2") == ("f1",)
    assert lead.agent("f2").link == "sim://"
    smd = load_experiment(GRAPHS / "spring_mass_damper.toml")
    assert smd.agent("smd").initial_state == (4.0, 0.0, -4.0, 0.0)
    assert smd.rate_hz == 10.0


def test_every_problem_is_reported_at_once(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        """
        [experiment]
        name = "de mo"
        rate_hz = -1
        mode = "fast"
        colour = 3
        [graph]
        agents = ["a", "b", "x"]
        adjacency = [[1, 1, 0], [2, 0, 1]]
        [agents.a]
        vehicle = "simulated"
        [agents.b]
        controller = 3
        initial_state = ["x"]
        [agents.zz]
        vehicle = "s"
        controller = "c"
        """,
    )
    problems = problems_of(path)
    keys = [p.key for p in problems]
    for key in (
        "experiment.colour",
        "experiment.name",
        "experiment.rate_hz",
        "experiment.duration_s",
        "experiment.mode",
        "agents.a.controller",
        "agents.b.vehicle",
        "agents.b.controller",
        "agents.b.initial_state[0]",
        "graph.adjacency",
        "graph.adjacency[1][0]",
        "graph.adjacency[0][0]",
        "graph.agents[2]",
        "agents.zz",
    ):
        assert key in keys, f"{key} not in {keys}"
    assert all(p.file == path for p in problems)
    message = str(ExperimentError(problems))
    assert f"{path}:experiment.rate_hz: -1 Hz is out of range" in message
    assert message.startswith(f"{len(problems)} problems in experiment")


def test_missing_and_unreadable_files(tmp_path: Path) -> None:
    experiment, problems = parse_experiment(tmp_path / "nope.toml")
    assert experiment is None
    assert problems[0].message == "experiment file does not exist"
    bad = write(tmp_path, "[experiment\nname=1")
    (problem,) = problems_of(bad)
    assert problem.key == "" and "not valid TOML" in problem.message
    assert str(problem).startswith(f"{bad}: not valid TOML")


def test_experiment_error_is_a_value_error() -> None:
    from hilswarm.agents.errors import HilswarmError

    error = ExperimentError([Problem("f.toml", "k", "why")])
    assert isinstance(error, HilswarmError) and isinstance(error, ValueError)
    assert "f.toml:k: why" in str(error)
    with pytest.raises(ValueError, match="at least one problem"):
        ExperimentError([])


def test_on_agent_safe_policy(tmp_path: Path) -> None:
    graph = """
        [graph]
        agents = ["a", "b", "c"]
        adjacency = [[0, 1, 0], [1, 0, 1], [0, 1, 0]]
        """
    path = write(tmp_path, HEADER + graph + AGENTS_ABC)
    assert load_experiment(path).on_agent_safe == "continue"  # the default
    assert load_experiment(path, overrides={"on_agent_safe": "stop"}).on_agent_safe == "stop"

    stop = write(tmp_path, HEADER + 'on_agent_safe = "stop"\n' + graph + AGENTS_ABC, "stop.toml")
    assert load_experiment(stop).on_agent_safe == "stop"

    bad = write(tmp_path, HEADER + 'on_agent_safe = "maybe"\n' + graph + AGENTS_ABC, "bad.toml")
    [problem] = problems_of(bad)
    assert problem.key == "experiment.on_agent_safe"
    assert "'maybe'" in problem.message and "'continue', 'stop'" in problem.message

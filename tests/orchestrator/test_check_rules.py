"""The rules `check` and `run` share: tick count, agent count, graph files inside the
experiment's folder, and vehicle/controller names checked without running unknown code."""

from __future__ import annotations

import itertools
import sys
import textwrap
from pathlib import Path

import pytest
from hilswarm.orchestrator.checks import check_file
from hilswarm.orchestrator.cli import main
from hilswarm.orchestrator.experiment import DEFAULT_MAX_AGENTS, MAX_TICKS, parse_experiment

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"


def swarm(folder: Path, n: int, *, extra: str = "", graph: str | None = None) -> Path:
    """An experiment of ``n`` simulated integrators in a ring, written to ``folder``."""
    names = [f"a{i}" for i in range(n)]
    lines = [
        "[experiment]",
        'name = "swarm"',
        "rate_hz = 10",
        "duration_s = 1",
        extra,
        "[graph]",
    ]
    if graph is None:
        folder.joinpath("ring.edgelist").write_text(
            "".join(
                f"{a} {b}\n{b} {a}\n" for a, b in zip(names, names[1:] + names[:1], strict=True)
            )
        )
        graph = 'file = "ring.edgelist"'
    lines += [
        graph,
        "[defaults]",
        'vehicle = "simulated"',
        'controller = "consensus"',
        'vehicle_params = { plant = "integrator" }',
    ]
    for i, name in enumerate(names):
        lines += [f"[agents.{name}]", f"initial_state = [{float(i)}]"]
    path = folder / "swarm.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# -- duration x rate -------------------------------------------------------------------------


def test_too_many_ticks_are_refused_with_the_memory_they_need(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = swarm(tmp_path, 2)
    path.write_text(path.read_text().replace("duration_s = 1", "duration_s = 1e9"))
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{path}:experiment.duration_s: 1e+09 s at 10 Hz is 1e+10 ticks" in err
    assert "160 GB of memory" in err and "Traceback" not in err
    # run refuses it before allocating anything, also without the deep checks
    out = tmp_path / "run.mcap"
    assert main(["run", str(path), "--no-check", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "160 GB of memory" in err and "Traceback" not in err
    assert not out.exists()
    # an override is bounded the same way
    _, problems = parse_experiment(GRAPHS / "lead_follow.toml", overrides={"rate_hz": 1000.0})
    assert not problems
    _, problems = parse_experiment(
        GRAPHS / "lead_follow.toml", overrides={"duration_s": MAX_TICKS / 20 + 1.0}
    )
    assert [p.key for p in problems] == ["experiment.duration_s"]


# -- agent count --------------------------------------------------------------------------------


def test_more_agents_than_the_cap_need_max_agents(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    n = DEFAULT_MAX_AGENTS + 1
    path = swarm(tmp_path, n)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{path}:agents: {n} agents is more than {DEFAULT_MAX_AGENTS}" in err
    assert f"--max-agents {n}" in err
    assert main(["check", str(path), "--max-agents", str(n)]) == 0
    capsys.readouterr()


def test_run_without_checks_never_starts_more_agents_than_the_cap(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = swarm(tmp_path, 10_000)
    out = tmp_path / "run.mcap"
    # refused while loading, before a bus, a recorder or any agent process exists
    assert main(["run", str(path), "--no-check", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "10000 agents is more than 256" in err
    assert not out.exists()


def test_a_graph_file_over_the_cap_is_refused(tmp_path: Path) -> None:
    path = swarm(tmp_path, 4)
    names = [f"n{i}" for i in range(300)]
    tmp_path.joinpath("big.edgelist").write_text(
        "".join(f"{a} {b}\n" for a, b in itertools.pairwise(names))
    )
    path.write_text(path.read_text().replace("ring.edgelist", "big.edgelist"))
    _, problems = parse_experiment(path)
    assert any(p.key == "graph.file" and "300 agents is more than" in p.message for p in problems)


# -- graph files ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["../outside.csv", "../../etc/passwd", "/etc/passwd"])
def test_graph_files_must_lie_inside_the_experiments_folder(tmp_path: Path, name: str) -> None:
    folder = tmp_path / "exp"
    folder.mkdir()
    tmp_path.joinpath("outside.csv").write_text("a0,a1\n0,1\n1,0\n")
    path = swarm(folder, 2, graph=f'file = "{name}"')
    _, problems = parse_experiment(path)
    [problem] = [p for p in problems if p.key == "graph.file"]
    assert "outside the experiment's folder" in problem.message
    assert all(p.file == path for p in problems)  # the outside file was never read


def test_graph_files_in_a_subfolder_are_fine(tmp_path: Path) -> None:
    path = swarm(tmp_path, 3)
    tmp_path.joinpath("graphs").mkdir()
    tmp_path.joinpath("ring.edgelist").rename(tmp_path / "graphs" / "ring.edgelist")
    path.write_text(path.read_text().replace("ring.edgelist", "graphs/ring.edgelist"))
    assert check_file(path).ok


# -- module:Class names ------------------------------------------------------------------------

USER_MODULE = """
import pathlib
pathlib.Path(__file__).with_name("imported.marker").write_text("ran")

from hilswarm.agents.control import Controller

s = "not a class"

def make():
    return None

class NotAVehicle:
    pass
"""


@pytest.fixture
def user_folder(tmp_path: Path) -> Path:
    """A folder with an experiment beside a user module that leaves a marker when it runs."""
    tmp_path.joinpath("robots_chk.py").write_text(textwrap.dedent(USER_MODULE))
    yield tmp_path
    sys.modules.pop("robots_chk", None)
    if str(tmp_path) in sys.path:
        sys.path.remove(str(tmp_path))


@pytest.mark.parametrize(
    ("vehicle", "reason"),
    [
        ("robots_chk:s", "is not a class: module 'robots_chk' binds 's' as assigned a constant"),
        ("robots_chk:make", "binds 'make' as a function"),
        ("robots_chk:Missing", "defines no 'Missing'"),
        ("no_such_module_xyz:Bot", "cannot find module 'no_such_module_xyz'"),
        ("builtins:dict", "'builtins:dict' is class dict, not a vehicle class"),
        ("this:s", "module 'this' is part of Python's standard library"),
    ],
)
def test_names_that_are_not_classes_are_refused_without_running_the_module(
    user_folder: Path, vehicle: str, reason: str, capsys: pytest.CaptureFixture[str]
) -> None:
    this_was_loaded = "this" in sys.modules
    path = swarm(user_folder, 2)
    path.write_text(path.read_text().replace('vehicle = "simulated"', f'vehicle = "{vehicle}"'))
    assert main(["check", str(path)]) == 2
    out, err = capsys.readouterr()
    assert f"{path}:agents.a0.vehicle: " in err and reason in err, err
    assert "Traceback" not in out + err
    assert not user_folder.joinpath("imported.marker").exists()  # never executed
    if not this_was_loaded:
        assert "this" not in sys.modules  # `this` prints the Zen of Python when it runs
    assert "Beautiful is better than ugly" not in out


def test_a_class_that_is_not_a_vehicle_is_refused_after_import(user_folder: Path) -> None:
    path = swarm(user_folder, 2)
    text = path.read_text().replace('vehicle = "simulated"', 'vehicle = "robots_chk:NotAVehicle"')
    text = text.replace('controller = "consensus"', 'controller = "robots_chk:Controller"')
    path.write_text(text)
    problems = {p.key: p.message for p in check_file(path).problems}
    # a class statement: the module is imported (it runs in the agents anyway) and the class
    # must subclass Vehicle
    assert "class NotAVehicle, not a vehicle class" in problems["agents.a0.vehicle"]
    assert "hilswarm.agents.vehicle.Vehicle" in problems["agents.a0.vehicle"]
    # an import of hilswarm's abstract Controller is followed statically, then built
    assert "agents.a0.controller" in problems
    assert user_folder.joinpath("imported.marker").exists()

"""``hilswarm check``: every error class, reported as file:key: reason with exit status 2."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.mocap.qtm_sim import QtmSimulator, SimSettings
from hilswarm.orchestrator.checks import check_file
from hilswarm.orchestrator.cli import main

DATA = Path(__file__).resolve().parent / "data"
GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
SIM_MOCAP = '[mocap]\nsystem = "sim"\n'


@contextlib.contextmanager
def real_mocap(*bodies: str) -> Iterator[str]:
    """A "real" Qualisys system that sees ``bodies`` (the protocol-level simulator on a free
    loopback port, addressed as a user with a Qualisys system would); yields its [mocap] table."""
    with QtmSimulator(SimSettings(bodies=bodies)) as sim:
        for body in bodies:
            sim.set_truth(body, np.zeros(6))
        yield f'[mocap]\nsystem = "qualisys"\nhost = "127.0.0.1"\nport = {sim.port}\n'


#: broken file -> (file the problem is in, key, part of the reason)
CASES: dict[str, tuple[str, str, str]] = {
    # structure: file, [experiment]
    "not_toml.toml": ("not_toml.toml", "", "not valid TOML"),
    "missing_experiment.toml": ("missing_experiment.toml", "experiment", "missing [experiment]"),
    "bad_name.toml": ("bad_name.toml", "experiment.name", "'my run' is not a valid name"),
    "bad_rate.toml": ("bad_rate.toml", "experiment.rate_hz", "0 Hz is out of range"),
    "bad_duration.toml": (
        "bad_duration.toml",
        "experiment.duration_s",
        "-5 s is out of range; expected duration_s > 0",
    ),
    "bad_mode.toml": ("bad_mode.toml", "experiment.mode", "'fast' is not one of"),
    "bad_agent_loss.toml": (
        "bad_agent_loss.toml",
        "experiment.on_agent_loss",
        "'retry' is not one of",
    ),
    "bad_lockstep_window.toml": (
        "bad_lockstep_window.toml",
        "experiment.lockstep_window",
        "0 is out of range; expected lockstep_window >= 1",
    ),
    "unknown_key.toml": ("unknown_key.toml", "experiment.rate", "unknown key"),
    "watchdog_short.toml": (
        "watchdog_short.toml",
        "experiment.watchdog_s",
        "not longer than the control period",
    ),
    # the graph
    "nonsquare.toml": ("nonsquare.toml", "graph.adjacency[1]", "must be square"),
    "not_zero_one.toml": ("not_zero_one.toml", "graph.adjacency[0][1]", "expected 0 or 1"),
    "diagonal.toml": ("diagonal.toml", "graph.adjacency[1][1]", "the diagonal must be 0"),
    "graph_name_without_table.toml": (
        "graph_name_without_table.toml",
        "graph.agents[3]",
        "has no [agents.d] table",
    ),
    "table_not_in_graph.toml": ("table_not_in_graph.toml", "agents.c", "is not in the graph"),
    "duplicate_agent.toml": ("duplicate_agent.toml", "graph.agents[1]", "listed twice"),
    "bad_agent_name.toml": ("bad_agent_name.toml", "agents.c c", "not a valid agent name"),
    "graph_both_forms.toml": ("graph_both_forms.toml", "graph", "exactly one of"),
    "missing_graph_file.toml": ("missing_graph_file.toml", "graph.file", "does not exist"),
    "bad_csv_graph.toml": ("bad_matrix.csv", "matrix[1][0]", "expected 0 or 1"),
    # registry
    "unknown_vehicle.toml": ("unknown_vehicle.toml", "agents.a.vehicle", "unknown vehicle"),
    "unknown_controller.toml": (
        "unknown_controller.toml",
        "agents.a.controller",
        "unknown controller 'mpc'",
    ),
    # links
    "bad_link.toml": ("bad_link.toml", "agents.leader.link", "unknown scheme 'ftp'"),
    "missing_link.toml": ("missing_link.toml", "agents.leader.link", "needs a board"),
    "shared_serial.toml": ("shared_serial.toml", "agents.f1.link", "already the link of agent"),
    # pins (vehicles built without a board)
    "pin_conflict.toml": ("pin_conflict.toml", "agents.leader.pinout", "already bound"),
    "pin_no_pwm.toml": ("pin_no_pwm.toml", "agents.f1.pinout", "has no PWM"),
    "unknown_pinout_device.toml": (
        "unknown_pinout_device.toml",
        "agents.leader.pinout",
        "unknown device 'wheels'",
    ),
    # vehicle parameters and state
    "bad_vehicle_params.toml": (
        "bad_vehicle_params.toml",
        "agents.c.vehicle_params",
        "unknown parameter(s) ['colour']",
    ),
    "initial_state_length.toml": (
        "initial_state_length.toml",
        "agents.a.initial_state",
        "must have 2 entries",
    ),
    "missing_calibration.toml": (
        "missing_calibration.toml",
        "agents.leader.calibration",
        "does not exist",
    ),
    "bad_calibration.toml": (
        "bad_calibration.toml",
        "agents.leader.calibration",
        "strictly increasing",
    ),
    # controllers
    "bad_params.toml": ("bad_params.toml", "agents.b.params", "'gain' must be a number > 0"),
    "controller_mismatch.toml": (
        "controller_mismatch.toml",
        "agents.a.controller",
        "does not fit vehicle",
    ),
    "leader_not_heard.toml": (
        "leader_not_heard.toml",
        "agents.f1.params.leader",
        "does not hear its leader 'leader'",
    ),
    "leader_unknown.toml": ("leader_unknown.toml", "agents.f1.params.leader", "'boss'"),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_every_error_class_exits_2_with_file_key_reason(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    file_name, key, reason = CASES[name]
    path = DATA / name
    status = main(["check", str(path)])
    out, err = capsys.readouterr()
    assert status == 2, out + err
    assert "Traceback" not in out + err
    where = str(path.parent / file_name) if file_name != name else str(path)
    if file_name.endswith(".csv"):
        where = str((DATA / file_name).resolve())
    prefix = f"{where}:{key}: " if key else f"{where}: "
    lines = [line for line in err.splitlines() if line.startswith(prefix)]
    assert lines, f"no line starting with {prefix!r} in:\n{err}"
    assert any(reason in line for line in lines), f"{reason!r} not in {lines}"
    assert "problem" in err.splitlines()[-1]


@pytest.mark.parametrize("name", sorted(CASES))
def test_check_file_reports_the_same_problem(name: str) -> None:
    _, key, reason = CASES[name]
    report = check_file(DATA / name)
    assert not report.ok
    assert any(p.key == key and reason in p.message for p in report.problems), report.problems


def test_several_problems_are_reported_together(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (DATA / "bad_params.toml").read_text()
    text = text.replace('name = "t"', 'name = "t"\nmode = "fast"')
    text = text.replace("[agents.a]\n", '[agents.a]\nvehicle = "hovercraft"\n')
    path = tmp_path / "many.toml"
    path.write_text(text)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    # A structure problem does not hide the deep checks of the agents: one pass shows all.
    assert f"{path}:experiment.mode:" in err
    assert f"{path}:agents.a.vehicle:" in err
    assert f"{path}:agents.b.params:" in err
    assert "3 problems" in err


def test_a_broken_graph_hides_nothing_else(tmp_path: Path) -> None:
    text = (DATA / "bad_params.toml").read_text()
    start = text.index("adjacency = ")
    end = text.index("]]", start) + 2
    text = text[:start] + "adjacency = [[0, 1, 1], 7, [1, 1, 1]]" + text[end:]
    text = text.replace("[agents.a]\n", '[agents.a]\nvehicle = "hovercraft"\n')
    text = text.replace("rate_hz = 10.0", "rate_hz = 10.0\ncolour = 1")
    path = tmp_path / "graph.toml"
    path.write_text(text)
    keys = {p.key for p in check_file(path).problems}
    assert {
        "graph.adjacency[1]",  # the row that is not a list
        "graph.adjacency[2][2]",  # a later row is still checked
        "experiment.colour",
        "agents.a.vehicle",  # deep checks of the agents still run
        "agents.b.params",
    } <= keys, keys


def test_link_override_of_unknown_agent(capsys: pytest.CaptureFixture[str]) -> None:
    path = GRAPHS / "lead_follow.toml"
    assert main(["check", str(path), "--link", "nobody=/dev/ttyUSB0"]) == 2
    err = capsys.readouterr().err
    assert f"{path}:--link nobody: no agent named 'nobody'" in err
    assert main(["check", str(path), "--link", "leader"]) == 2
    assert "expected NAME=URL" in capsys.readouterr().err


def test_link_override_is_checked_deeply(capsys: pytest.CaptureFixture[str]) -> None:
    path = GRAPHS / "lead_follow.toml"
    assert main(["check", str(path), "--link", "leader=gopher://x"]) == 2
    assert f"{path}:agents.leader.link: link URL 'gopher://x'" in capsys.readouterr().err
    assert main(["check", str(path), "--link", "leader=sim://duemilanove"]) == 0
    # A real board gives no pose and lead_follow.toml has no [mocap]: the leader cannot run.
    assert main(["check", str(path), "--link", "leader=socket://127.0.0.1:5760"]) == 2
    err = capsys.readouterr().err
    assert f"{path}:agents.leader.link: agent 'leader': vehicle 'frisbee' needs a pose" in err
    assert "[mocap]" in err
    # The demo's mocap system is the simulator, whose cameras see only simulated robots: a
    # real board there cannot run either, and check says what to change.
    mocap = GRAPHS / "lead_follow_mocap.toml"
    assert main(["check", str(mocap), "--link", "leader=socket://127.0.0.1:5760"]) == 2
    err = capsys.readouterr().err
    assert f"{mocap}:mocap.system: " in err
    assert "agent 'leader' (link 'socket://127.0.0.1:5760') has a real board" in err
    assert "set [mocap] system to your real motion capture system" in err
    assert "needs a pose" not in err  # the pose would come from [mocap], were it real


@pytest.mark.parametrize(
    ("url", "reason"),
    [
        ("/dev/ttyUSB9", "serial device '/dev/ttyUSB9' does not exist"),
        ("simavr://mega", "unknown board profile 'mega'"),
        ("sim://mega", "unknown board profile 'mega'"),
        ("socket://127.0.0.1", "expected socket://HOST:PORT"),
        ("sim://uno?colour=red", "unknown option 'colour'"),
    ],
)
def test_check_and_run_reject_the_same_links(
    url: str, reason: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = GRAPHS / "lead_follow.toml"
    assert main(["check", str(path), "--link", f"leader={url}"]) == 2
    err = capsys.readouterr().err
    assert f"{path}:agents.leader.link: " in err and reason in err, err
    assert "Traceback" not in err
    # run refuses it the same way before starting anything, with or without the deep checks
    out = tmp_path / "run.mcap"
    for extra in ([], ["--no-check"]):
        assert main(["run", str(path), "--out", str(out), *extra, "--link", f"leader={url}"]) == 2
        err = capsys.readouterr().err
        assert f"{path}:agents.leader.link: " in err and reason in err, err
        assert not out.exists()


def test_network_serial_urls_are_only_syntax_checked(tmp_path: Path) -> None:
    text = (DATA / "shared_serial.toml").read_text()
    text = text.replace('link = "socket://127.0.0.1:5760"', 'link = "rfc2217://127.0.0.1:1"', 1)
    path = tmp_path / "net.toml"
    with real_mocap("leader", "f1") as table:  # real boards need a real mocap system
        path.write_text(text.replace(SIM_MOCAP, table))
        report = check_file(path)  # nobody listens on either board's port: not connected
    assert report.ok, report.problems


def test_vehicle_that_needs_a_pose_on_a_real_link_needs_mocap(tmp_path: Path) -> None:
    path = GRAPHS / "lead_follow.toml"
    report = check_file(path, overrides={"links": {"leader": "socket://127.0.0.1:5760"}})
    [problem] = report.problems
    assert problem.key == "agents.leader.link"
    assert "agent 'leader'" in problem.message and "[mocap]" in problem.message
    # simulated boards simulate the motion capture too
    assert check_file(path, overrides={"links": {"leader": "simavr://uno"}}).ok
    # with a [mocap] table the pose comes from it: no "needs a pose" problem (the simulated
    # system's own rule for real boards: test_sim_mocap_with_a_real_board_is_a_problem)
    text = path.read_text().replace('mode = "lockstep"', 'mode = "realtime"')
    text += '\n[mocap]\nsystem = "sim"\n'
    with_mocap = tmp_path / "lead_follow.toml"
    with_mocap.write_text(text)
    report = check_file(with_mocap, overrides={"links": {"leader": "socket://127.0.0.1:5760"}})
    assert [p.key for p in report.problems] == ["mocap.system"], report.problems
    with real_mocap("leader", "f1", "f2") as table:
        with_mocap.write_text(text.replace(SIM_MOCAP, table))
        report = check_file(with_mocap, overrides={"links": {"leader": "socket://127.0.0.1:5760"}})
    assert report.ok, report.problems
    blimp = (DATA / "shared_serial.toml").read_text().replace('"frisbee"', '"blimpduino"')
    blimp = blimp.replace('[mocap]\nsystem = "sim"\n', "")
    blimp_path = tmp_path / "blimp.toml"
    blimp_path.write_text(blimp)
    keys = {p.key for p in check_file(blimp_path).problems if "needs a pose" in p.message}
    assert keys == {"agents.leader.link", "agents.f1.link"}


def test_sim_mocap_with_a_real_board_is_a_problem(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The simulated cameras see only simulated plants: with ``[mocap] system = "sim"`` an
    agent on a real board could never be seen. check and run say so and what to change."""
    demo = GRAPHS / "lead_follow_mocap.toml"
    real = {"leader": "socket://127.0.0.1:9"}
    [problem] = check_file(demo, overrides={"links": real}).problems
    assert problem.key == "mocap.system"
    assert "agent 'leader' (link 'socket://127.0.0.1:9') has a real board" in problem.message
    assert "set [mocap] system to your real motion capture system" in problem.message
    assert "or give that agent a simulated link" in problem.message
    # several real boards: one problem naming them all
    two = {"leader": "socket://127.0.0.1:9", "f2": "rfc2217://127.0.0.1:10"}
    [problem] = check_file(demo, overrides={"links": two}).problems
    assert problem.key == "mocap.system"
    assert "agents 'leader' (link 'socket://127.0.0.1:9'), 'f2' (link" in problem.message
    assert "have real boards" in problem.message
    # every simulated link feeds the simulator its plant's true pose
    for url in ("sim://duemilanove", "simavr://uno", "xbee://0013A20040000001?sim=sim://uno"):
        report = check_file(demo, overrides={"links": {"leader": url}})
        assert report.ok, (url, report.problems)
    # run refuses it before starting anything, with the same file:key: reason
    out = tmp_path / "run.mcap"
    assert main(["run", str(demo), "--out", str(out), "--link", "leader=socket://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert f"{demo}:mocap.system: " in err and "set [mocap] system to your real" in err, err
    assert not out.exists()
    # the change it asks for: a real system that sees the robots' bodies
    head, _, rest = demo.read_text().partition("\n[mocap]\n")
    _, _, graph = rest.partition("\n[graph]\n")
    path = tmp_path / "real.toml"
    with real_mocap("frisbee1", "frisbee2", "frisbee3") as table:
        path.write_text(f"{head}\n{table}\n[graph]\n{graph}")
        report = check_file(path, overrides={"links": real})
    assert report.ok, report.problems


@pytest.mark.parametrize(
    "name",
    [
        "spring_mass_damper.toml",
        "lead_follow.toml",
        "consensus_ring.toml",
        "consensus_ring_file.toml",
        "lead_follow_mocap.toml",
    ],
)
def test_example_files_are_valid(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    path = GRAPHS / name
    assert main(["check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("ok: ")
    assert "warning" not in err


def test_warnings_do_not_fail_unless_strict(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (GRAPHS / "consensus_ring.toml").read_text()
    text = text.replace("params = { gain = 1.0 }", "params = { gain = 10.0 }")
    path = tmp_path / "fast_gain.toml"
    path.write_text(text)
    assert main(["check", str(path)]) == 0
    err = capsys.readouterr().err
    assert f"warning: {path}:agents.a0.params.gain:" in err
    assert "gain * dt * in-degree" in err
    assert main(["check", str(path), "--strict"]) == 2


def test_disconnected_graph_is_a_warning(tmp_path: Path) -> None:
    text = (GRAPHS / "consensus_ring.toml").read_text()
    start = text.index("adjacency = [[")
    end = text.index("]]", start) + 2
    text = (
        text[:start]
        + "adjacency = [[0,1,0,0,0,0],[1,0,0,0,0,0],[0,0,0,1,0,0],"
        + "[0,0,1,0,0,0],[0,0,0,0,0,1],[0,0,0,0,1,0]]"
        + text[end:]
    )
    path = tmp_path / "split.toml"
    path.write_text(text)
    report = check_file(path)
    assert report.ok
    keys = [w.key for w in report.warnings]
    assert "graph" in keys
    assert "agents.a0.controller" in keys  # consensus without a spanning tree


def test_graph_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["graph", str(GRAPHS / "lead_follow.toml"), "--matrix"]) == 0
    out = capsys.readouterr().out
    assert "leaders (hear nobody): leader" in out
    assert "spanning tree (consensus possible): yes  roots: leader" in out
    assert main(["graph", str(GRAPHS / "consensus_ring.toml"), "--json"]) == 0
    import json

    data = json.loads(capsys.readouterr().out)
    assert data["in_degree"]["a0"] == 3 and data["strongly_connected"]
    assert main(["graph", str(DATA / "diagonal.toml")]) == 2
    assert "graph.adjacency[1][1]" in capsys.readouterr().err


def test_remote_agents_links_are_not_checked_for_local_devices(tmp_path: Path) -> None:
    text = (DATA / "shared_serial.toml").read_text()
    text = text.replace('link = "socket://127.0.0.1:5760"', 'link = "/dev/ttyUSB9"', 1)
    path = tmp_path / "remote.toml"
    with real_mocap("leader", "f1") as table:  # real boards need a real mocap system
        path.write_text(text.replace(SIM_MOCAP, table))
        assert "does not exist" in " ".join(p.message for p in check_file(path).problems)
        # the leader's board is plugged into another machine (hilswarm run --remote leader)
        report = check_file(path, remote=["leader"])
    assert report.ok, report.problems


def test_hilswarm_agent_checks_only_its_own_device(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (DATA / "shared_serial.toml").read_text()
    text = text.replace('link = "socket://127.0.0.1:5760"', 'link = "/dev/ttyUSB9"', 1)
    path = tmp_path / "remote.toml"
    path.write_text(text)  # the leader's board is on another machine
    argv = ["agent", "--connect", "tcp/127.0.0.1:9", "--experiment", str(path), "--name", "f1"]
    assert main([*argv, "--link", "f1=/dev/ttyUSB8"]) == 2  # f1's own device is checked here
    err = capsys.readouterr().err
    assert "agents.f1.link: serial device '/dev/ttyUSB8' does not exist" in err
    assert "agents.leader.link" not in err


def test_an_unused_link_is_a_warning_of_check_and_of_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A link given to a vehicle that needs no board is not used: ``check`` warns and its
    summary says so, and ``run`` prints the same warning (it used to run without a word)."""
    path = GRAPHS / "consensus_ring.toml"
    link = ["--link", "a0=socket://127.0.0.1:1"]
    assert main(["check", str(path), *link]) == 0
    captured = capsys.readouterr()
    warning = "agents.a0.link: vehicle 'simulated' needs no board; link 'socket://127.0.0.1:1'"
    assert warning in captured.err
    assert "a0: simulated via (no board; link socket://127.0.0.1:1 not used)" in captured.out
    out = tmp_path / "run.mcap"
    done = subprocess.run(
        [sys.executable, "-m", "hilswarm.orchestrator.cli", "run", str(path), *link,
         "--duration", "0.25", "--out", str(out)],
        capture_output=True, text=True, timeout=120, cwd=tmp_path, stdin=subprocess.DEVNULL,
        env={**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"warning: {path}:{warning}" in done.stderr, done.stderr


def test_the_gateway_port_is_checked_where_the_gateway_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A coordinator on a device that is not there: ``check`` and ``run`` refuse it as they
    refuse an agent's missing serial device (``run`` used to start and then fail); with
    ``--remote-gateway`` the coordinator is on another machine and its device is not looked for."""
    text = (GRAPHS / "xbee_swarm.toml").read_text()
    assert '\nport = "sim"' in text
    path = tmp_path / "xbee_usb9.toml"
    path.write_text(text.replace('\nport = "sim"', '\nport = "/dev/ttyUSB9"', 1))
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    want = f"{path}:gateway.port: the coordinator: serial device '/dev/ttyUSB9' does not exist"
    assert want in err, err
    out = tmp_path / "run.mcap"
    assert main(["run", str(path), "--out", str(out)]) == 2
    assert want in capsys.readouterr().err
    assert not out.exists()
    report = check_file(path, remote_gateway=True)
    assert not [p for p in report.problems if p.key == "gateway.port"], report.problems


def test_a_second_link_for_one_agent_and_a_link_for_another_agent_are_refused(
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = GRAPHS / "lead_follow.toml"
    assert main(["check", str(path), "--link", "leader=sim://", "--link", "leader=sim://uno"]) == 2
    assert "agent 'leader' has a --link already (sim://)" in capsys.readouterr().err
    # `hilswarm agent` runs one agent: a link for another one would be silently unused
    assert main(["agent", "--experiment", str(path), "--name", "f2", "--link", "f1=sim://"]) == 2
    err = capsys.readouterr().err
    assert "--link for f1: this process runs only agent 'f2'" in err and "Traceback" not in err

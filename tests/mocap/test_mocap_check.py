"""``[mocap]`` in experiment files, ``hilswarm check`` and ``hilswarm mocap`` against a server.

The "real" system here is the protocol-level simulator on a free port, addressed as
``system = "qualisys"`` (what a user with a Qualisys system writes).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.mocap.qtm_sim import QtmSimulator, SimSettings
from hilswarm.orchestrator.cli import main
from hilswarm.orchestrator.experiment import parse_experiment

REPO = Path(__file__).resolve().parents[2]
DEMO = (REPO / "graphs" / "lead_follow_mocap.toml").read_text()


@pytest.fixture
def qualisys() -> Iterator[QtmSimulator]:
    """A 'Qualisys' system that sees frisbee1 and frisbee3 (frisbee2 is listed, not tracked)."""
    with QtmSimulator(SimSettings(bodies=("frisbee1", "frisbee2", "frisbee3"))) as sim:
        sim.set_truth("frisbee1", np.array([0.5, 0.25, 0.0, 0.0, 0.0, 0.5]))
        sim.set_truth("frisbee3", np.zeros(6))
        yield sim


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "experiment.toml"
    path.write_text(text)
    return path


def real_system(port: int) -> str:
    """The demo on a 'real' Qualisys system at ``port`` (no simulated cameras)."""
    head, _, rest = DEMO.partition("\n[mocap]\n")
    _, _, graph = rest.partition("\n[graph]\n")
    return (
        f'{head}\n[mocap]\nsystem = "qualisys"\nhost = "127.0.0.1"\nport = {port}\n'
        f"rate_hz = 100.0\n\n[graph]\n{graph}"
    )


def test_check_names_a_body_the_system_does_not_see(
    qualisys: QtmSimulator, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, real_system(qualisys.port))
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "agents.f1.mocap_body: body 'frisbee2' is not visible to qualisys" in err
    assert "it sees: frisbee1, frisbee3" in err
    assert "agents.leader" not in err and "agents.f2" not in err


def test_hilswarm_mocap_lists_bodies_rate_and_world_pose(
    qualisys: QtmSimulator, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["mocap", "--system", "qualisys", "--host", "127.0.0.1", "--port", str(qualisys.port)]
    assert main([*argv, "--seconds", "0.5"]) == 0
    out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if line.strip().startswith("frisbee1"))
    assert line.split()[3:7] == ["0.500", "0.250", "0.000", "28.6"]  # m, m, m, deg
    assert "not tracked" in next(line for line in out.splitlines() if "frisbee2" in line)
    # With the experiment: the agent's body missing is named, exit 1.
    path = write(tmp_path, real_system(qualisys.port))
    assert main(["mocap", str(path), "--seconds", "0.5"]) == 1
    captured = capsys.readouterr()
    assert "MISSING" in captured.out and "not visible: frisbee2" in captured.err


def test_hilswarm_mocap_refused_server_and_bad_input(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["mocap"]) == 2
    assert "give an experiment file" in capsys.readouterr().err
    assert main(["mocap", "--system", "qualisys", "--host", "127.0.0.1", "--port", "1"]) == 1
    assert "cannot connect" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("change", "key", "reason"),
    [
        (('mode = "realtime"', 'mode = "lockstep"'), "experiment.mode", "wall clock"),
        (('system = "sim"', 'system = "kinect"'), "mocap.system", "is not one of"),
        (("hold_frames = 50", "hold_frames = 0"), "mocap.hold_frames", "frames >= 1"),
        (("rate_hz = 100.0", "rate_hz = 0"), "mocap.rate_hz", "out of range"),
        (("dropout_frames = 3", "dropout_frames = 3\nflicker = 1"), "mocap.sim.flicker", "unknown"),
        (('mocap_body = "frisbee2"', 'mocap_body = "frisbee1"'), "agents.f1.mocap_body", "already"),
        (('mocap_body = "frisbee2"', 'mocap_body = "a/b"'), "agents.f1.mocap_body", "letters"),
    ],
)
def test_mocap_section_problems_are_reported(
    tmp_path: Path, change: tuple[str, str], key: str, reason: str
) -> None:
    assert change[0] in DEMO
    _, problems = parse_experiment(write(tmp_path, DEMO.replace(change[0], change[1], 1)))
    assert any(p.key == key and reason in p.message for p in problems), problems


def test_mocap_body_without_a_mocap_section_is_a_problem(tmp_path: Path) -> None:
    head, _, rest = DEMO.partition("\n[mocap]\n")
    _, _, graph = rest.partition("\n[graph]\n")
    _, problems = parse_experiment(write(tmp_path, f"{head}\n[graph]\n{graph}"))
    assert any(p.key == "agents.leader.mocap_body" for p in problems), problems


def test_ticks_faster_than_the_frames_warn(tmp_path: Path) -> None:
    from hilswarm.orchestrator.checks import check_file

    assert "rate_hz = 20.0" in DEMO and "rate_hz = 100.0" in DEMO  # control, camera frames
    report = check_file(write(tmp_path, DEMO.replace("rate_hz = 20.0", "rate_hz = 150.0", 1)))
    assert report.ok  # it can run: a warning
    (warning,) = [w for w in report.warnings if w.key == "experiment.rate_hz"]
    assert "faster than the mocap frames" in warning.message
    assert "about 67% of the ticks get a new pose" in warning.message
    assert "use rate_hz <= 100 Hz" in warning.message
    same = check_file(write(tmp_path, DEMO.replace("rate_hz = 20.0", "rate_hz = 100.0", 1)))
    assert not [w for w in same.warnings if w.key == "experiment.rate_hz"]


@pytest.mark.parametrize("line", ["tick_frames_only = true", "tick_spread_frames = 3"])
def test_schedule_settings_without_the_managers_schedule_warn(tmp_path: Path, line: str) -> None:
    """``tick_frames_only`` and ``tick_spread_frames`` need the manager's schedule in advance,
    which tick messages (``realtime_clock = "manager"``, an XBee gateway) replace."""
    from hilswarm.orchestrator.checks import check_file

    key = "mocap." + line.split(maxsplit=1)[0]
    old = "hold_frames = 50 "
    assert old in DEMO
    text = DEMO.replace(old, f"{line}\n" + old, 1)
    report = check_file(write(tmp_path, text))  # self-clocked: the schedule is known
    assert report.ok and not [w for w in report.warnings if w.key == key]
    ticked = text.replace('mode = "realtime"', 'mode = "realtime"\nrealtime_clock = "manager"', 1)
    report = check_file(write(tmp_path, ticked))
    assert report.ok
    (warning,) = [w for w in report.warnings if w.key == key]
    assert 'has no effect here: realtime_clock = "manager" drives the ticks' in warning.message
    xbee = (REPO / "graphs" / "xbee_swarm_broadcast.toml").read_text()
    for old, new in (
        ('mode = "lockstep"', 'mode = "realtime"'),
        ('mode = "broadcast"', 'mode = "broadcast"\nanswer = "at_once"'),
        ("[graph]", f'[mocap]\nsystem = "sim"\n{line}\n\n[graph]'),
    ):
        xbee = xbee.replace(old, new, 1)
    report = check_file(write(tmp_path, xbee))
    (warning,) = [w for w in report.warnings if w.key == key]
    assert "an XBee [gateway] drives the ticks with tick messages" in warning.message
    report = check_file(write(tmp_path, text), remote=["f1"])  # f1 joins from elsewhere
    (warning,) = [w for w in report.warnings if w.key == key]
    assert "the manager, for the agent on another machine (--remote f1), drives the ticks" in (
        warning.message
    )


def test_a_spread_leaving_the_last_agents_little_time_warns(tmp_path: Path) -> None:
    """100 Hz frames, 20 Hz control: 4 frames leave the last agents 10 ms of 50 (20 %): no
    warning; with 23 Hz control 4 frames leave 3.5 ms (8 %): a warning naming 3."""
    from hilswarm.orchestrator.checks import check_file

    old = "hold_frames = 50 "
    text = DEMO.replace(old, "tick_spread_frames = 4\n" + old, 1)
    report = check_file(write(tmp_path, text))
    assert report.ok and not [w for w in report.warnings if w.key == "mocap.tick_spread_frames"]
    report = check_file(write(tmp_path, text.replace("rate_hz = 20.0", "rate_hz = 23.0", 1)))
    assert report.ok
    (warning,) = [w for w in report.warnings if w.key == "mocap.tick_spread_frames"]
    assert "leave the last agents 3.48 ms (8% of the 43.5 ms control period)" in warning.message
    assert "3 frames leave 20% or more" in warning.message


def test_many_agents_per_core_sensing_at_one_frame_get_the_spread_suggested(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ticks locked to the frames, no spread, at least SPREAD_ADVICE_AGENTS_PER_CORE agents per
    core: ``check`` warns and names the spread that fits (100 Hz frames, 20 Hz control: up to
    4 frames, at most one per agent: 3). Not with fewer agents per core, a spread already set,
    or tick messages (which a spread does not change)."""
    from hilswarm.orchestrator import checks

    monkeypatch.setattr(checks, "SPREAD_ADVICE_AGENTS_PER_CORE", 1)  # the demo has 3 agents
    monkeypatch.setattr(checks, "available_cores", lambda: 3)
    report = checks.check_file(write(tmp_path, DEMO))
    assert report.ok
    (warning,) = [w for w in report.warnings if w.key == "mocap.tick_spread_frames"]
    assert "3 agents on 3 cores all sense at one frame" in warning.message
    assert "tick_spread_frames = 3 lets them take turns" in warning.message
    old = "hold_frames = 50 "
    others = [
        DEMO.replace(old, "tick_spread_frames = 2\n" + old, 1),
        DEMO.replace('mode = "realtime"', 'mode = "realtime"\nrealtime_clock = "manager"', 1),
    ]
    for text in others:
        report = checks.check_file(write(tmp_path, text))
        assert not [w for w in report.warnings if "all sense at one frame" in w.message]
    monkeypatch.setattr(checks, "available_cores", lambda: 4)  # under one agent per core
    report = checks.check_file(write(tmp_path, DEMO))
    assert not [w for w in report.warnings if w.key == "mocap.tick_spread_frames"]

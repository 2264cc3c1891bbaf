"""``hilswarm run`` tells the truth and loses nothing: exit status, --out protection, runs that
fail before their first tick, an agent safe from its first tick, a full disk (tmpfs in a mount
namespace of the test's own), and ``hilswarm recover`` on a full disk."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.link.wire_server import SocketWireServer
from hilswarm.agents.mcap_io import McapJsonWriter, iter_messages
from swarm_harness import finish_in_group, write_toy_experiment

HERE = Path(__file__).resolve().parent
GRAPHS = HERE.parents[1] / "graphs"
CLI = (sys.executable, "-m", "hilswarm.orchestrator.cli")
RUN_TIMEOUT_S = 240
ENV = {**os.environ, "PYTHONPATH": f"{HERE}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def finish(command: list[str], cwd: Path) -> tuple[int, str]:
    """Run ``command`` in its own process group (killed after RUN_TIMEOUT_S); status, output."""
    return finish_in_group(command, cwd=cwd, timeout_s=RUN_TIMEOUT_S, env=ENV)


def hilswarm(*args: str, cwd: Path) -> tuple[int, str]:
    """The CLI, in its own process group: exit status and output."""
    return finish([*CLI, *args], cwd)


def files(folder: Path) -> list[str]:
    return sorted(path.name for path in folder.iterdir() if path.suffix == ".mcap" or
                  ".mcap." in path.name)  # fmt: skip


OLD = b"\x89MCAP0\r\n an older recording"


def test_out_is_never_replaced_without_force(tmp_path: Path) -> None:
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=0.2)
    keep = tmp_path / "keep.mcap"
    keep.write_bytes(OLD)
    code, output = hilswarm("run", str(experiment), "--out", str(keep), "--no-check",
                            cwd=tmp_path)  # fmt: skip
    assert code == 2, output
    assert "--force" in output and "Traceback" not in output, output
    assert keep.read_bytes() == OLD and files(tmp_path) == ["keep.mcap"]
    # with --force it is replaced by the new recording (and the run is clean)
    code, output = hilswarm("run", str(experiment), "--out", str(keep), "--no-check", "--force",
                            cwd=tmp_path)  # fmt: skip
    assert code == 0, output
    assert "outcome: clean (exit status 0)" in output, output
    assert files(tmp_path) == ["keep.mcap"]
    assert [m["k"] for topic, _, m in iter_messages(keep) if topic == "/a/y"] == list(range(10))


def test_a_run_that_fails_before_its_first_tick_touches_no_recording(tmp_path: Path) -> None:
    keep = tmp_path / "keep.mcap"
    keep.write_bytes(OLD)
    # a serial device that does not exist: refused as bad input before anything starts
    code, output = hilswarm(
        "run", str(GRAPHS / "lead_follow.toml"), "--duration", "1", "--no-check", "--force",
        "--link", "leader=/dev/ttyUSB9", "--out", str(keep),
        "--start-timeout", "60", cwd=tmp_path,
    )  # fmt: skip
    assert code == 2, output
    assert "Traceback" not in output, output
    assert keep.read_bytes() == OLD and files(tmp_path) == ["keep.mcap"], output
    # the bus port is taken: the run cannot open its bus
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, output = hilswarm(
            "run", str(GRAPHS / "lead_follow.toml"), "--duration", "1", "--no-check",
            "--force", "--out", str(keep), "--port", str(port), cwd=tmp_path,
        )  # fmt: skip
    assert code == 1, output
    assert "Traceback" not in output, output
    assert keep.read_bytes() == OLD and files(tmp_path) == ["keep.mcap"], output


@pytest.fixture
def board_server() -> Iterator[SocketWireServer]:
    server = SocketWireServer(SimBoard("uno", dt=0.05)).start()
    yield server
    server.stop()


def test_an_agent_safe_from_its_first_tick_fails_the_run(
    tmp_path: Path, board_server: SocketWireServer
) -> None:
    """A Frisbee bot on a real-board link has no pose source: safe at tick 0 -> exit 1."""
    out = tmp_path / "run.mcap"
    code, output = hilswarm(
        "run", str(GRAPHS / "lead_follow.toml"), "--duration", "1", "--no-check",
        "--link", f"leader={board_server.url}", "--out", str(out),
        cwd=tmp_path,
    )  # fmt: skip
    assert code == 1, output
    assert "agent leader safe from tick 0" in output, output
    assert "safe from its first tick" in output, output
    states = [m["state"] for topic, _, m in iter_messages(out) if topic == "/leader/status"]
    assert "safe" in states


def _tmpfs_works() -> str:
    """Why a tmpfs cannot be mounted in a private mount namespace here ("" if it can)."""
    if shutil.which("unshare") is None:
        return "no unshare command"
    probe = subprocess.run(
        ["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt && df /mnt"],
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    return "" if probe.returncode == 0 else f"cannot mount a tmpfs: {probe.stderr.strip()}"


def in_small_tmpfs(size: str, folder: Path, script: str, keep: Path) -> tuple[int, str]:
    """Run ``script`` (sh) with a tmpfs of ``size`` mounted on ``folder`` in a mount namespace
    of its own; the ``*.mcap`` files left in it are copied to ``keep`` afterwards."""
    reason = _tmpfs_works()
    if reason:
        pytest.skip(f"disk-full test needs a small tmpfs: {reason}")
    folder.mkdir(exist_ok=True)
    keep.mkdir(exist_ok=True)
    wrapped = (
        f"mount -t tmpfs -o size={size} tmpfs {folder} || exit 99\n"
        f"{script}\ncode=$?\nls -a {folder} > {keep}/listing\n"
        f"cp {folder}/*.mcap {keep}/ 2>/dev/null\nexit $code\n"
    )
    code, output = finish(["unshare", "-m", "sh", "-c", wrapped], keep)
    assert code != 99, output
    return code, output


def test_a_full_disk_stops_the_run_safely_by_default(tmp_path: Path) -> None:
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=600.0)
    disk, keep = tmp_path / "disk", tmp_path / "keep"
    command = " ".join([*CLI, "run", str(experiment), "--no-check", "--out",
                        f"{disk}/run.mcap"])  # fmt: skip
    code, output = in_small_tmpfs("256k", disk, command, keep)
    assert code == 3, output
    assert "the disk is full" in output and "on_recording_failure = stop" in output, output
    assert "recording: stopped at tick" in output and "Traceback" not in output, output
    # what reached the disk is readable (every chunk written before the disk filled)
    ks = [m["k"] for topic, _, m in iter_messages(keep / "run.mcap") if topic == "/a/y"]
    assert ks == list(range(len(ks))) and len(ks) > 10


def test_a_full_disk_with_policy_continue_runs_to_the_end_unrecorded(tmp_path: Path) -> None:
    """``on_recording_failure = "continue"``: the disk fills early, the run goes on to its last
    tick unrecorded, exits 3, and the summary says from which tick on nothing was recorded."""
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=300.0)  # 15000 ticks
    text = experiment.read_text(encoding="utf-8")
    experiment.write_text(
        text.replace(
            'mode = "lockstep"\n', 'mode = "lockstep"\non_recording_failure = "continue"\n'
        ),
        encoding="utf-8",
    )
    last = 15000 - 1
    disk, keep = tmp_path / "disk", tmp_path / "keep"
    command = " ".join([*CLI, "run", str(experiment), "--no-check", "--out",
                        f"{disk}/run.mcap"])  # fmt: skip
    # 1 MiB: ~1500 ticks, over half a second of this lockstep run, so the disk fills after the
    # recorder's first acknowledgements (ACK_PERIOD_S apart); 256k filled at ~390 ticks, at
    # about the first one's time, and a run whose disk fills before any acknowledgement rightly
    # reports every tick as possibly unrecorded
    code, output = in_small_tmpfs("1m", disk, command, keep)
    assert code == 3, output
    assert "Traceback" not in output, output
    assert "outcome: degraded (exit status 3)" in output, output
    # the disk filled while the run ticked, and the run went on to its last tick
    failed = re.search(r"at tick (\d+); recording stopped: the disk is full", output)
    assert failed is not None, output
    assert int(failed.group(1)) < last, output
    assert "on_recording_failure = continue" in output, output
    assert "on_recording_failure = stop" not in output, output
    assert "15000/15000 ticks" in output and "stopped: completed" in output, output
    # each write error of the full disk is shown once, not once per record
    assert output.count("No space left on device") < 10, output[-3000:]
    # the summary says what was not recorded: from which tick, at most how many records
    stopped = re.search(
        rf"recording: stopped at tick (\d+); ticks \1\.\.{last} are not recorded, or only in part",
        output,
    )
    assert stopped is not None, output
    first_lost = int(stopped.group(1))
    lost = rf"recording: at most \d+ records lost \(ticks {first_lost}\.\.{last}, "
    assert re.search(lost, output), output
    # what reached the disk is readable, and holds every tick before the first one reported
    # not recorded (records not acknowledged by the recorder may be there too)
    ks = [m["k"] for topic, _, m in iter_messages(keep / "run.mcap") if topic == "/a/y"]
    assert ks == list(range(len(ks))) and len(ks) >= first_lost > 10, (len(ks), first_lost)


def test_recover_on_a_full_disk_says_so_and_leaves_no_file(tmp_path: Path) -> None:
    source = tmp_path / "run.mcap"
    with McapJsonWriter(source, chunk_size=4096) as writer:
        writer.add_topic("/a/y", fields=["x", "y"])
        for k in range(20000):
            writer.write_floats("/a/y", k=k, t=k * 0.01, values=[k * 0.1, k / 7],
                                log_time_ns=k)  # fmt: skip
    disk, keep = tmp_path / "disk", tmp_path / "keep"
    command = " ".join([*CLI, "recover", str(source), "-o", f"{disk}/fixed.mcap"])
    code, output = in_small_tmpfs("16k", disk, command, keep)
    assert code == 1, output
    assert "no space" in output.lower() or "disk is full" in output, output
    assert "Traceback" not in output, output
    listing = (keep / "listing").read_text().split()
    assert "fixed.mcap" not in listing, listing  # no empty or partial file left


def test_a_run_that_never_began_stops_its_agents_at_once_without_warnings(tmp_path: Path) -> None:
    """The remote agent never comes: the start-up times out. Nobody told the local agents to
    stop on the bus, so they get SIGTERM, their own stop request, at once (no grace period,
    no "did not exit" warning per agent), and the exit status says what failed."""
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=0.2)
    code, output = hilswarm(
        "-v", "run", str(experiment), "--no-check", "--remote", "d", "--start-timeout", "2",
        "--out", str(tmp_path / "run.mcap"), cwd=tmp_path,
    )  # fmt: skip
    assert code == 1, output
    assert "timed out after 2.0 s waiting for agents: d" in output, output
    assert "did not exit" not in output and "Traceback" not in output, output
    for name in ("a", "b", "c"):
        assert f"agent {name}: not told to stop on the bus; sending SIGTERM" in output, output
    assert files(tmp_path) == [], output

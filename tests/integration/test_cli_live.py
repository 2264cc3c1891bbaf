"""The CLI against real processes: Ctrl-C while ``hilswarm run`` is still importing, a bus
that cannot be joined, and the reason an e-stop is recorded with."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.orchestrator.run_registry import list_runs
from swarm_harness import REPO, RunProcess, read_recording, wait_for, write_toy_experiment

pytestmark = pytest.mark.integration

CLI = (sys.executable, "-m", "hilswarm.orchestrator.cli")


def mapped(pid: int, marker: str) -> bool:
    """True once process ``pid`` has a shared library whose path contains ``marker`` mapped
    (it is importing that package's extension modules)."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False
    return any(marker in line and ".so" in line for line in maps.splitlines())


@pytest.mark.parametrize("marker", ["zenoh", "/scipy/"])
def test_ctrl_c_while_run_imports_is_one_line_and_130(
    marker: str, tmp_path: Path, runs: list[RunProcess]
) -> None:
    """SIGINT once the command's modules are being imported (Zenoh early, scipy later: both
    within the first second): status 130, one short line, no traceback, nothing started."""
    run = RunProcess(tmp_path, REPO / "graphs" / "consensus_ring.toml", "--mode", "realtime")
    runs.append(run)
    pid = run.process.pid
    wait_for(
        lambda: mapped(pid, marker) or run.process.poll() is not None,
        30.0,
        f"hilswarm run to import {marker}",
    )
    assert run.process.poll() is None, run.output()
    os.kill(pid, signal.SIGINT)
    assert run.wait(60) == 130, run.output()
    stderr = run.stderr_path.read_text()
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    assert stderr.strip() == "hilswarm: interrupted", stderr
    assert not run.out.exists()


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]  # nothing listens on it once closed


def hilswarm(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CLI, *args], capture_output=True, text=True, timeout=60, env=env, check=False
    )


def test_a_bus_that_cannot_be_joined_and_an_estop_reason(
    tmp_path: Path, runs: list[RunProcess]
) -> None:
    experiment = write_toy_experiment(tmp_path / "toy.toml", mode="realtime", duration_s=60.0)
    run = RunProcess(tmp_path, experiment, "--no-check")
    runs.append(run)
    run.entry()
    wait_for(
        lambda: any(e.state == "running" for e in list_runs(run.registry)),
        60.0,
        "the run to tick",
    )

    # A well-formed endpoint where nothing listens: one line, run-time failure (exit 1).
    where = f"tcp/127.0.0.1:{free_port()}"
    joined = hilswarm(run.env, "set", "toy", "a", "gain=1", "--connect", where, "--timeout", "2")
    assert joined.returncode == 1, joined.stderr
    assert f"hilswarm set: cannot join the bus at {where}" in joined.stderr, joined.stderr
    assert "Traceback" not in joined.stderr

    # `stop --estop` without --reason: the reason says "e-stop" once.
    stopped = hilswarm(run.env, "stop", "toy", "--estop")
    assert stopped.returncode == 0, stopped.stdout + stopped.stderr
    assert run.wait(60) == 3, run.output()  # an e-stop degrades the run
    output = run.output()
    assert "e-stop: e-stop" not in output, output
    for name in ("a", "b", "c", "d"):  # each vehicle logs it, each agent records it
        assert f"vehicle '{name}' enters safe mode: e-stop\n" in output, output
    recording = read_recording(run.out)
    for name in ("a", "b", "c", "d"):
        details = [m.get("detail", "") for m in recording.get(f"/{name}/status", [])]
        assert "e-stop" in details, details
        assert not any("e-stop: e-stop" in d for d in details), details
    # every agent went safe because of the e-stop, which the outcome names: the summary lists
    # none of them as a fault (it listed those whose status happened to arrive first)
    assert "degraded: e-stop at tick" in output, output
    safe_lines = [line for line in output.splitlines() if "safe from tick" in line]
    assert not safe_lines, safe_lines

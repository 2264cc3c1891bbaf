"""The agent fork server: real forked processes, their titles, sessions and exit codes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from hilswarm.agents import spawner
from hilswarm.agents.spawner import UNKNOWN_EXIT, ForkServer, SpawnError
from hilswarm.orchestrator.launcher import AgentLauncher

pytestmark = pytest.mark.integration

CHILD = """
import pathlib, sys, time

def main(argv):
    out = pathlib.Path(argv[0])
    out.write_text(" ".join(argv[1:]))
    if argv[1] == "exit":
        return int(argv[2])
    if argv[1] == "raise":
        raise RuntimeError("boom")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        time.sleep(0.05)
    return 0
"""


def wait_until(condition, timeout_s: float, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.02)


@pytest.fixture
def server(tmp_path: Path) -> Iterator[ForkServer]:
    (tmp_path / "toychild.py").write_text(CHILD, encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    fork_server = ForkServer(env=env, preload=["toychild"])
    yield fork_server
    fork_server.close()


def test_child_runs_main_with_its_title_in_its_own_session(
    server: ForkServer, tmp_path: Path
) -> None:
    out = tmp_path / "argv.txt"
    child = server.spawn("toychild", [str(out), "wait", "x"], title="toy --name a --experiment e")
    try:
        wait_until(out.exists, 20, "the child's output")
        assert out.read_text() == "wait x"
        assert os.getsid(child.pid) == child.pid  # its own session and process group
        title = Path(f"/proc/{child.pid}/cmdline").read_bytes()
        assert b"toy --name a --experiment e" in title
        assert child.poll() is None
        with pytest.raises(subprocess.TimeoutExpired):
            child.wait(0.05)
    finally:
        child.kill()
    assert child.wait(10) == -signal.SIGKILL


def test_exit_codes_are_reported_like_popen(server: ForkServer, tmp_path: Path) -> None:
    exited = server.spawn("toychild", [str(tmp_path / "a"), "exit", "3"], title="a")
    crashed = server.spawn("toychild", [str(tmp_path / "b"), "raise"], title="b")
    assert exited.wait(20) == 3
    assert crashed.wait(20) == 1
    assert exited.poll() == 3


def test_children_outlive_a_killed_server_and_are_still_watched(
    server: ForkServer, tmp_path: Path
) -> None:
    out = tmp_path / "argv.txt"
    child = server.spawn("toychild", [str(out), "wait"], title="c")
    wait_until(out.exists, 20, "the child's output")
    server._process.kill()
    wait_until(lambda: server.gone, 10, "the server to be seen gone")
    assert child.poll() is None  # still running: the launcher stops it by its group
    with pytest.raises(SpawnError):
        server.spawn("toychild", [str(out), "wait"], title="d")
    os.killpg(child.pid, signal.SIGKILL)
    wait_until(lambda: child.poll() is not None, 10, "the orphan's end")
    assert child.returncode == UNKNOWN_EXIT


def test_a_prepared_launcher_starts_its_server_at_once_and_closes_it_unused() -> None:
    """``hilswarm run`` prepares the fork server before it opens the bus; a run that then
    fails before any agent starts must not leave the server behind."""
    launcher = AgentLauncher(["tcp/127.0.0.1:7447"])
    launcher.prepare()
    server = launcher._fork_server
    assert server is not None
    assert server._process.poll() is None  # importing the agent code, already running
    launcher.prepare()
    assert launcher._fork_server is server  # one server per launcher
    launcher.stop(told=False)
    assert launcher._fork_server is None
    assert server._process.wait(10) == -signal.SIGTERM  # never asked to fork: ended at once

    exec_launcher = AgentLauncher(["tcp/127.0.0.1:7447"], start_method="exec")
    exec_launcher.prepare()
    assert exec_launcher._fork_server is None


def test_a_fork_request_puts_its_folders_first_on_the_child_import_path(
    server: ForkServer, tmp_path: Path
) -> None:
    """The experiment's folder travels with each request (the server starts before it is
    known): the child imports a user module from it, and its PYTHONPATH starts with it."""
    user = tmp_path / "userdir"
    user.mkdir()
    (user / "usermod.py").write_text(
        "import os, pathlib, sys\n"
        "def main(argv):\n"
        "    pathlib.Path(argv[0]).write_text(os.environ['PYTHONPATH'].split(os.pathsep)[0])\n"
        "    return 5\n",
        encoding="utf-8",
    )
    out = tmp_path / "pythonpath.txt"
    child = server.spawn("usermod", [str(out)], title="u", path=[str(user)])
    assert child.wait(20) == 5
    assert out.read_text() == str(user)


def test_an_unused_server_is_ended_at_once(tmp_path: Path) -> None:
    """``hilswarm run --help`` or a run refused before its agents start: the server, still
    importing, is terminated instead of being waited for."""
    fork_server = ForkServer()
    began = time.monotonic()
    fork_server.close()
    assert fork_server._process.returncode == -signal.SIGTERM
    assert time.monotonic() - began < 5
    fork_server.close()  # idempotent


def slow_server(tmp_path: Path, import_s: float, *, fail: bool = False) -> ForkServer:
    """A server whose preload import takes ``import_s`` seconds (then raises, with ``fail``):
    a slow machine's import of the agent code, or a module that cannot import."""
    (tmp_path / "toychild.py").write_text(CHILD, encoding="utf-8")
    body = f"import time\ntime.sleep({import_s!r})\n"
    if fail:
        body += "raise ImportError('the agent code cannot import')\n"
    (tmp_path / "slowimport.py").write_text(body, encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    return ForkServer(env=env, preload=["slowimport", "toychild"])


def test_a_slow_import_does_not_count_against_the_answer_s_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The first fork waits for the server's imports (bounded by ``READY_TIMEOUT_S``), not
    within the bound on one answer: a server importing for longer than that bound still
    starts its first child, and later ones."""
    monkeypatch.setattr(spawner, "SPAWN_TIMEOUT_S", 0.5)
    fork_server = slow_server(tmp_path, 2.0)
    try:
        first = fork_server.spawn("toychild", [str(tmp_path / "a"), "exit", "3"], title="a")
        second = fork_server.spawn("toychild", [str(tmp_path / "b"), "exit", "4"], title="b")
        assert (first.wait(20), second.wait(20)) == (3, 4)
    finally:
        fork_server.close()


def test_a_server_that_never_finishes_importing_is_reported_within_its_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(spawner, "READY_TIMEOUT_S", 0.5)
    fork_server = slow_server(tmp_path, 60.0)
    began = time.monotonic()
    try:
        with pytest.raises(SpawnError, match="did not finish importing the agent code within"):
            fork_server.spawn("toychild", [str(tmp_path / "a"), "exit", "0"], title="a")
        assert time.monotonic() - began < 10
    finally:
        fork_server.close(timeout_s=2.0)
    assert fork_server._process.returncode is not None  # ended, not left behind


def test_a_server_whose_import_fails_is_reported_at_once(tmp_path: Path) -> None:
    """No wait for the whole import bound: the server's exit ends the wait."""
    fork_server = slow_server(tmp_path, 0.0, fail=True)
    began = time.monotonic()
    try:
        with pytest.raises(SpawnError, match="exited"):
            fork_server.spawn("toychild", [str(tmp_path / "a"), "exit", "0"], title="a")
        assert time.monotonic() - began < 30
    finally:
        fork_server.close()

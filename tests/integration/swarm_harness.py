"""Helpers of the swarm runtime's integration tests: a `hilswarm run` process, a spy session.

Every process started here runs in its own process group and is killed (with its agents) by
:meth:`RunProcess.cleanup`, which the tests call from a ``finally``/fixture. Every wait is
bounded.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh
from hilswarm.agents import bus
from hilswarm.agents.mcap_io import iter_messages

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent


def free_port() -> int:
    """A free TCP port on loopback."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_for(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll ``condition`` (every 20 ms) for at most ``timeout_s``; fail the test on timeout."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.02)


def child_pids(pid: int) -> list[int]:
    """Direct children of ``pid`` (from /proc)."""
    children: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            children += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return children


def children_running(pid: int, module: bytes) -> list[int]:
    """Children of ``pid`` whose command line contains ``module`` (bytes)."""
    found = []
    for child in child_pids(pid):
        try:
            command = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if module in command:
            found.append(child)
    return found


def agent_pids(pid: int) -> list[int]:
    """Agent processes below ``pid``: its children, or the children of its agent fork server."""
    servers = children_running(pid, b"hilswarm.agents.spawner")
    agents = [c for c in children_running(pid, b"hilswarm.agents.agent") if c not in servers]
    for server in servers:
        agents += children_running(server, b"hilswarm.agents.agent")
    return agents


def agent_name_of(pid: int) -> str:
    """The agent name of agent process ``pid``, from its command line or process title."""
    words = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").split()
    if b"--name" in words:  # a forked agent's title
        return words[words.index(b"--name") + 1].decode()
    config = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    return json.loads(config[config.index(b"--config") + 1])["name"]


def pid_alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


class RunProcess:
    """``hilswarm run`` in its own process group, with output captured to files."""

    def __init__(self, tmp_path: Path, experiment: Path, *args: str, port: int) -> None:
        self.port = port
        self.out = tmp_path / "run.mcap"
        self.stdout_path = tmp_path / "run.stdout"
        self.stderr_path = tmp_path / "run.stderr"
        env = {**os.environ, "PYTHONPATH": f"{HERE}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
        command = [
            sys.executable,
            "-m",
            "hilswarm.orchestrator.cli",
            "run",
            str(experiment),
            "--out",
            str(self.out),
            "--port",
            str(port),
            *args,
        ]
        self._stdout = self.stdout_path.open("wb")
        self._stderr = self.stderr_path.open("wb")
        self.process = subprocess.Popen(
            command,
            cwd=tmp_path,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=self._stdout,
            stderr=self._stderr,
            start_new_session=True,
        )
        self.agent_pids: list[int] = []

    @property
    def endpoint(self) -> str:
        return bus.loopback_endpoint(self.port)

    def remember_agents(self, n: int, timeout_s: float = 60.0) -> list[int]:
        """Wait until ``n`` agent processes exist; remember their pids for cleanup."""
        wait_for(
            lambda: len(agent_pids(self.process.pid)) >= n or self.process.poll() is not None,
            timeout_s,
            f"{n} agent processes",
        )
        self.agent_pids = agent_pids(self.process.pid)
        return self.agent_pids

    def wait(self, timeout_s: float) -> int:
        """Exit status of the run (fails the test on timeout)."""
        try:
            return self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"hilswarm run did not exit within {timeout_s} s\n{self.output()}"
            ) from None

    def output(self) -> str:
        self._stdout.flush()
        self._stderr.flush()
        return (
            "--- stdout\n"
            + self.stdout_path.read_text(errors="replace")
            + "--- stderr\n"
            + self.stderr_path.read_text(errors="replace")
        )

    def cleanup(self) -> None:
        """Kill the run and every agent process group (continuing stopped ones first)."""
        pids = set(self.agent_pids)
        if self.process.poll() is None:
            pids |= set(child_pids(self.process.pid))
        for pid in pids:
            for signum in (signal.SIGCONT, signal.SIGKILL):
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(pid, signum)
        for signum in (signal.SIGCONT, signal.SIGKILL):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.process.pid, signum)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.process.wait(timeout=10)
        self._stdout.close()
        self._stderr.close()


class Spy:
    """A Zenoh client session that subscribes to everything of an experiment."""

    def __init__(self, endpoint: str, experiment: str) -> None:
        self.keys = bus.BusKeys(experiment)
        self.session = bus.open_session(bus.client_config([endpoint]))
        self.counts: dict[str, int] = defaultdict(int)
        self.last: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self.subscriber = self.session.declare_subscriber(
            f"{self.keys.prefix}/**", zenoh.handlers.Callback(self._on_sample, indirect=False)
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with self._lock:
            self.counts[key] += 1
            self.last[key] = sample.payload.to_bytes()

    def count(self, key: str) -> int:
        with self._lock:
            return self.counts.get(key, 0)

    def last_tick(self) -> int:
        """Index of the last tick message seen (-1 before any)."""
        with self._lock:
            payload = self.last.get(self.keys.tick)
        return -1 if payload is None else bus.decode_tick(payload).k

    def manager_state(self) -> str:
        """The state the instance manager last announced on its status key ("" before any)."""
        with self._lock:
            payload = self.last.get(self.keys.manager_status)
        return "" if payload is None else str(bus.decode_json(payload).get("state", ""))

    def control(self, command: bus.ControlCommand, reason: str = "test") -> None:
        """Publish a control command."""
        self.session.put(
            self.keys.control,
            bus.encode_control(command, reason=reason),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.REAL_TIME,
        )

    def close(self) -> None:
        self.session.close()


def connect_spy(run: RunProcess, experiment: str, timeout_s: float = 30.0) -> Spy:
    """Open a spy once the run's bus is up (retrying while the router is not listening)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return Spy(run.endpoint, experiment)
        except bus.BusConnectionError:
            if time.monotonic() > deadline or run.process.poll() is not None:
                raise AssertionError(f"no bus at {run.endpoint}\n{run.output()}") from None
            time.sleep(0.1)


def read_recording(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Messages of an MCAP file by topic, in file order."""
    topics: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for topic, _log_time, message in iter_messages(path):
        topics[topic].append(message)
    return topics


def write_toy_experiment(
    path: Path,
    *,
    name: str = "toy",
    mode: str = "lockstep",
    rate_hz: float = 50.0,
    duration_s: float = 2.0,
    on_agent_loss: str = "stop",
) -> Path:
    """A ring a -> b -> c -> a (A[i][j] = 1: i hears j) of toy integrators, plus d hearing a.

    Agent ``d`` hears ``a``; nobody hears ``d``. Initial states 0, 1, 5, 10.
    """
    path.write_text(
        f"""
[experiment]
name = "{name}"
rate_hz = {rate_hz}
duration_s = {duration_s}
mode = "{mode}"
on_agent_loss = "{on_agent_loss}"

[graph]
agents = ["a", "b", "c", "d"]
adjacency = [[0, 1, 0, 0],
             [0, 0, 1, 0],
             [1, 0, 0, 0],
             [1, 0, 0, 0]]

[defaults]
vehicle = "swarm_toys:ToyIntegrator"
controller = "swarm_toys:ToyConsensus"
params = {{ gain = 2.0 }}

[agents.a]
initial_state = [0.0]
[agents.b]
initial_state = [1.0]
[agents.c]
initial_state = [5.0]
[agents.d]
initial_state = [10.0]
""",
        encoding="utf-8",
    )
    return path


#: Who hears whom in :func:`write_toy_experiment`.
TOY_NEIGHBOURS = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}

"""Helpers of the swarm runtime's integration tests: a `hilswarm run` process, a spy session.

Every process started here runs in its own process group and is killed (with its agents) by
:meth:`RunProcess.cleanup`, which the tests call from a ``finally``/fixture. Every wait is
bounded. Each run gets a run registry of its own (``XDG_RUNTIME_DIR`` in the test's folder):
its router binds a free port and reports it there, with the run id and the credentials the
spy uses (viewer to listen, operator to command).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
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
from hilswarm.agents.credentials import Credentials
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.agents.tick_engine import is_warmup
from hilswarm.orchestrator.bus_access import OPERATOR, VIEWER
from hilswarm.orchestrator.run_registry import RunEntry, list_runs

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent


def wait_for(
    condition: Callable[[], bool], timeout_s: float, what: str | Callable[[], str]
) -> None:
    """Poll ``condition`` (every 20 ms) for at most ``timeout_s``; fail the test on timeout,
    saying ``what`` was awaited (a callable: worded at the timeout, with what was seen)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            said = what() if callable(what) else what
            raise AssertionError(f"timed out after {timeout_s} s waiting for {said}")
        time.sleep(0.02)


def finish_in_group(
    command: list[str], *, cwd: Path, timeout_s: float, env: dict[str, str] | None = None
) -> tuple[int, str]:
    """Run ``command`` in a process group of its own, killed (group and all) after
    ``timeout_s``, which fails the test; returns its exit status and output (stderr merged)."""
    process = subprocess.Popen(
        command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True, start_new_session=True,
    )  # fmt: skip
    try:
        output, _ = process.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        output, _ = process.communicate(timeout=10)
        raise AssertionError(
            f"{' '.join(command)} did not finish in {timeout_s} s:\n{output}"
        ) from None
    return process.returncode, output


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


def thread_policies(pid: int) -> set[int]:
    """The CPU scheduling policies (``os.SCHED_*``) of process ``pid``'s threads."""
    policies: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
            policies.add(os.sched_getscheduler(int(task.name)))
    return policies


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


def runtime_dir(folder: Path) -> Path:
    """A private ``XDG_RUNTIME_DIR`` (mode 0700) in ``folder``: a run registry of its own."""
    path = folder / "xdg"
    path.mkdir(mode=0o700, exist_ok=True)
    return path


def run_env(folder: Path) -> dict[str, str]:
    """Environment of a ``hilswarm`` process started by a test (registry in ``folder``)."""
    return {
        **os.environ,
        "PYTHONPATH": f"{HERE}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
        "XDG_RUNTIME_DIR": str(runtime_dir(folder)),
    }


class RunProcess:
    """``hilswarm run`` in its own process group, with output captured to files.

    Args:
        tmp_path: the test's folder (recording, output, run registry).
        experiment: the experiment file.
        args: more ``hilswarm run`` arguments.
        registry: the folder whose run registry the run uses (default ``tmp_path``; runs
            that share one show up together in ``hilswarm ps``).
        netns: run inside this network namespace (``ip netns exec``; same pid).
    """

    def __init__(
        self,
        tmp_path: Path,
        experiment: Path,
        *args: str,
        registry: Path | None = None,
        netns: str | None = None,
    ) -> None:
        self.out = tmp_path / "run.mcap"
        self.stdout_path = tmp_path / "run.stdout"
        self.stderr_path = tmp_path / "run.stderr"
        self.env = run_env(registry or tmp_path)
        self.registry = Path(self.env["XDG_RUNTIME_DIR"]) / "hilswarm"
        env = self.env
        command = [
            *(("ip", "netns", "exec", netns) if netns else ()),
            sys.executable,
            "-m",
            "hilswarm.orchestrator.cli",
            "run",
            str(experiment),
            "--out",
            str(self.out),
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

    def entry(self, timeout_s: float = 60.0) -> RunEntry:
        """This run's registry entry, once its bus is up (its router's bound endpoints)."""
        found: list[RunEntry] = []

        def registered() -> bool:
            if self.process.poll() is not None:
                raise AssertionError(f"hilswarm run exited early\n{self.output()}")
            if self.registry.is_dir():
                pid = self.process.pid
                found[:] = [
                    e for e in list_runs(self.registry) if e.pid == pid and e.state != "starting"
                ]
            return bool(found)

        wait_for(registered, timeout_s, "the run's registry entry")
        return found[0]

    def credentials(self, user: str) -> Credentials:
        """``user``'s credentials for this run (from its registry folder)."""
        return Credentials.read(self.registry / self.entry().run_id / f"{user}.cred")

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
    """Zenoh client sessions on a run's bus: one that subscribes to everything of the run (as
    the run's viewer), one that sends operator commands (as its operator). On an ``--insecure``
    run both are plain sessions (that may put anywhere).

    Keys are counted without the run id (``hilswarm/<exp>/agent/a/y``), as tests name them.

    The spy may subscribe after the run's first ticks: its registry entry appears when the
    bus opens, and agents forked from the warm fork server are ready ~50 ms later (a lockstep
    run then ticks at once). So a test that needs every output from tick 0 reads the
    recording; on the bus it counts from the spy's first output (:meth:`answers`).
    """

    def __init__(self, run: RunProcess) -> None:
        entry = run.entry()
        self.keys = bus.BusKeys(entry.name, entry.run_id)
        self._legacy = bus.BusKeys(entry.name)
        if entry.secure:
            viewer, operator = run.credentials(VIEWER), run.credentials(OPERATOR)
            as_viewer = bus.client_config(viewer.endpoints, security=viewer.security())
            as_operator = bus.client_config(operator.endpoints, security=operator.security())
        else:  # hilswarm run --insecure: no credentials, no access control
            as_viewer = as_operator = bus.client_config(entry.endpoints)
        self.session = bus.open_session(as_viewer)
        self.operator = bus.open_session(as_operator)
        self.counts: dict[str, int] = defaultdict(int)
        self.warmups: dict[str, int] = defaultdict(int)  # pre-roll outputs (k < 0), per key
        self.last: dict[str, bytes] = {}
        self.first_k: dict[str, int] = {}  # tick of the first output seen, per y key
        #: Every message on the tick key: (arrival [s, CLOCK_MONOTONIC], payload).
        self.tick_messages: list[tuple[float, bytes]] = []
        self._lock = threading.Lock()
        self.subscriber = self.session.declare_subscriber(
            f"{self.keys.prefix}/**", zenoh.handlers.Callback(self._on_sample, indirect=False)
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr).replace(self.keys.prefix, self._legacy.prefix, 1)
        payload = sample.payload.to_bytes()
        output = key.endswith("/y")
        k = int.from_bytes(payload[:8], "little", signed=True) if output else 0
        with self._lock:
            if output and is_warmup(k):  # the pre-roll's, ignored like every receiver does
                self.warmups[key] += 1
                return
            if output:
                self.first_k.setdefault(key, k)
            elif key == self._legacy.tick:
                self.tick_messages.append((time.monotonic(), payload))
            self.counts[key] += 1
            self.last[key] = payload

    def count(self, key: str) -> int:
        with self._lock:
            return self.counts.get(key, 0)

    def answers(self, agent: str) -> tuple[int, int, int]:
        """``(first k, last k, count)`` of ``agent``'s outputs seen (warm-ups aside);
        ``(-1, -1, 0)`` before any. Every output since the spy's first: ``count == last -
        first + 1`` (outputs come in tick order)."""
        key = self._legacy.y(agent)
        with self._lock:
            payload = self.last.get(key)
            if payload is None:
                return -1, -1, 0
            last = int.from_bytes(payload[:8], "little", signed=True)
            return self.first_k[key], last, self.counts[key]

    def last_tick(self) -> int:
        """Index of the last tick message seen (-1 before any); in a self-clocked realtime
        run, the tick due now on the last schedule seen (same host: same monotonic clock)."""
        with self._lock:
            payload = self.last.get(self._legacy.tick)
        if payload is None:
            return -1
        if bus.is_schedule(payload):
            schedule = bus.decode_schedule(payload)
            due = math.floor((time.monotonic() - schedule.t0) / schedule.dt)
            return min(schedule.last, max(schedule.first - 1, due))
        return bus.decode_tick(payload).k

    def manager_state(self) -> str:
        """The state the instance manager last announced on its status key ("" before any)."""
        with self._lock:
            payload = self.last.get(self._legacy.manager_status)
        return "" if payload is None else str(bus.decode_json(payload).get("state", ""))

    def control(self, command: bus.ControlCommand, reason: str = "test") -> None:
        """Send a control command as the operator (the manager forwards it to the agents)."""
        self.operator.put(
            self.keys.manager_request,
            bus.encode_control(command, reason=reason),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.REAL_TIME,
        )

    def close(self) -> None:
        self.session.close()
        self.operator.close()


def connect_spy(run: RunProcess, experiment: str, timeout_s: float = 60.0) -> Spy:
    """Open a spy once the run's bus is up (its registry entry says where)."""
    spy = Spy(run)
    assert spy.keys.experiment == experiment, (spy.keys.experiment, experiment)
    return spy


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

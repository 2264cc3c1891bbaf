"""A hostile process against a running swarm: what the run's bus (authentication, access
control, one bus and one run id per run) stops.

The attacker is a plain Zenoh client on loopback, like any program of another user or a stray
one: without credentials, with a wrong password, with the credentials of another principal of
the run (an agent, the operator, the viewer) or of another run. Each run then completes all
its ticks, exits 0, and its numbers are exactly those of the toy closed loop computed here
(lockstep is deterministic), so no forged message changed anything.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.credentials import Credentials
from hilswarm.orchestrator.bus_access import OPERATOR, VIEWER, agent_user
from swarm_harness import (
    RunProcess,
    agent_name_of,
    connect_spy,
    read_recording,
    run_env,
    wait_for,
    write_toy_experiment,
)

pytestmark = pytest.mark.integration

AGENTS = ("a", "b", "c", "d")
CLI = (sys.executable, "-m", "hilswarm.orchestrator.cli")
#: A value no toy agent ever outputs: its presence in a recording means a forgery got in.
FORGED = 123456.0
#: Lockstep ticks of the attacked runs.
N_TICKS = 1000


@pytest.fixture
def runs() -> Iterator[list[RunProcess]]:
    started: list[RunProcess] = []
    yield started
    for run in started:
        run.cleanup()


@pytest.fixture
def sessions() -> Iterator[list[zenoh.Session]]:
    opened: list[zenoh.Session] = []
    yield opened
    for session in opened:
        session.close()


def toy_run(tmp_path: Path, *, initial: tuple[float, ...] = (0.0, 1.0, 5.0, 10.0)) -> Path:
    """The toy ring in lockstep; ``on_agent_safe = "stop"`` so a forged safe status would end
    it early. Each controller step sleeps 10 ms, so the run lasts >= 10 s: attacks land while
    it runs (lockstep stays exact at any speed)."""
    path = write_toy_experiment(tmp_path / "toy.toml", duration_s=N_TICKS / 50)
    text = path.read_text(encoding="utf-8")
    text = text.replace("params = { gain = 2.0 }", "params = { gain = 2.0, work_s = 0.01 }")
    text = text.replace('on_agent_loss = "stop"', 'on_agent_loss = "stop"\non_agent_safe = "stop"')
    for name, value, default in zip(AGENTS, initial, (0.0, 1.0, 5.0, 10.0), strict=True):
        text = text.replace(
            f"[agents.{name}]\ninitial_state = [{default}]",
            f"[agents.{name}]\ninitial_state = [{value}]",
        )
    path.write_text(text, encoding="utf-8")
    return path


def expected_outputs(initial: tuple[float, ...], n_ticks: int) -> np.ndarray:
    """The toy closed loop (a hears b, b hears c, c hears a, d hears a), gain 2, 50 Hz."""
    x = np.array(initial, dtype=float)
    hears = [1, 2, 0, 0]
    out = [x.copy()]
    for _ in range(1, n_ticks):
        x = x + (1 / 50) * 2.0 * (x[hears] - x)
        out.append(x.copy())
    return np.array(out)


def check_untouched(run: RunProcess, initial: tuple[float, ...]) -> dict:
    """The run completed every tick, exit 0, with exactly the closed loop's numbers."""
    assert run.wait(300) == 0, run.output()
    recording = read_recording(run.out)
    got = np.array([[m["values"][0] for m in recording[f"/{n}/y"]] for n in AGENTS]).T
    assert got.shape == (N_TICKS, 4), got.shape
    for name in AGENTS:
        assert [m["k"] for m in recording[f"/{name}/y"]] == list(range(N_TICKS)), name
    np.testing.assert_allclose(got, expected_outputs(initial, N_TICKS), rtol=0, atol=1e-9)
    return recording


def open_as(run: RunProcess, credentials: Credentials | None) -> zenoh.Session:
    """A client session on ``run``'s bus with ``credentials`` (``None``: none at all)."""
    endpoints = run.entry().endpoints
    security = credentials.security() if credentials else None
    return bus.open_session(bus.client_config(endpoints, security=security))


def forge(run: RunProcess, user: str) -> Credentials:
    """``user``'s credentials of ``run`` (what an attacker who stole them would hold)."""
    return run.credentials(user)


class Listener:
    """Counts what a session receives on a key expression."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.keys: list[str] = []
        self._lock = threading.Lock()
        self.subscriber = session.declare_subscriber(
            key, zenoh.handlers.Callback(self._on_sample, indirect=False)
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.keys.append(str(sample.key_expr))

    def seen(self) -> list[str]:
        with self._lock:
            return list(self.keys)


def attack(session: zenoh.Session, keys: bus.BusKeys, *, operator: bool) -> list[object]:
    """Every forgery of the issue, from one session (each should be dropped by the router).

    The operator may ask the manager to stop (``manager/request``) and set parameters: those
    two are not sent as the operator.

    Returns the declared entities (tokens, publishers), which must stay alive.
    """
    kept: list[object] = []

    def send(key: str, payload: bytes) -> None:
        publisher = session.declare_publisher(key, **bus.TICK_PATH_QOS)
        kept.append(publisher)
        publisher.put(payload)

    send(keys.tick, bus.encode_tick(bus.TickMessage(10**6, 2e4, (), realtime=False)))
    send(keys.tick, b"\x01")
    for command in bus.ControlCommand:
        send(keys.control, bus.encode_control(command, reason="forged"))
    if not operator:
        send(keys.manager_request, bus.encode_control(bus.ControlCommand.STOP, reason="forged"))
    send(keys.y("a"), bus.encode_vector(20, 0.4, [FORGED]))
    send(keys.y("a"), b"\x00\x01\x02")
    send(keys.status("a"), bus.encode_json({"agent": "a", "state": "safe", "detail": "forged"}))
    send(keys.agent("a", "telemetry/battery"), bus.encode_vector(3, 0.06, [FORGED]))
    kept.append(session.liveliness().declare_token(keys.alive("a")))
    kept.append(session.liveliness().declare_token(keys.alive("_manager")))
    if not operator:
        for reply in session.get(
            keys.set("b"), payload=bus.encode_json({"params": {"gain": 50.0}}), timeout=0.5
        ):
            assert reply.ok is None, "a forged set was answered"
    return kept


def test_hostile_clients_cannot_join_forge_or_snoop(
    tmp_path: Path, runs: list[RunProcess], sessions: list[zenoh.Session]
) -> None:
    initial = (0.0, 1.0, 5.0, 10.0)
    run = RunProcess(tmp_path, toy_run(tmp_path, initial=initial), "--no-check")
    runs.append(run)
    spy = connect_spy(run, "toy")
    try:
        wait_for(lambda: spy.last_tick() >= 10, 120, "tick 10")
        keys = spy.keys
        kept: list[object] = []

        # No credentials, a wrong password, an unknown user: refused when the session opens.
        with pytest.raises(bus.BusConnectionError, match=r"refused|nothing answers"):
            open_as(run, None)
        real = forge(run, agent_user("d"))
        for user, password in ((real.user, "wrong"), ("intruder", real.password)):
            stolen = Credentials(real.experiment, real.run_id, user, password, real.endpoints)
            with pytest.raises(bus.BusConnectionError):
                open_as(run, stolen)

        # Another principal's credentials: the router's access control drops every forgery.
        for user in (agent_user("d"), agent_user("b"), OPERATOR, VIEWER):
            session = open_as(run, forge(run, user))
            sessions.append(session)
            kept += attack(session, keys, operator=user == OPERATOR)

        # Snooping with an agent's credentials: only what that agent may hear arrives.
        d = open_as(run, forge(run, agent_user("d")))
        sessions.append(d)
        everything = Listener(d, f"{keys.prefix}/**")
        not_a_neighbour = Listener(d, keys.y("b"))
        inputs = Listener(d, keys.u("c"))
        allowed = Listener(d, keys.y("a"))  # d hears a
        wait_for(lambda: len(allowed.seen()) >= 5, 120, "d's session to hear a's y")
        assert spy.last_tick() < N_TICKS - 1, "the run ended before the attacks were over"
    finally:
        spy.close()
    # Everything d's session got is what agent d hears anyway (its session's own a/y
    # subscription also feeds its ** one): a's output and the manager's ticks.
    assert set(everything.seen()) <= {keys.y("a"), keys.tick, keys.control}, everything.seen()
    assert not_a_neighbour.seen() == []
    assert inputs.seen() == []

    recording = check_untouched(run, initial)
    for name in AGENTS:
        for message in recording.get(f"/{name}/status", []):
            assert "forged" not in str(message.get("detail", "")), message
            assert "gain" not in str(message.get("detail", "")), message
    assert str(FORGED) not in json.dumps(recording, default=str)  # no forged value anywhere
    events = [m.get("state") for m in recording.get("/orchestrator/status", [])]
    assert "paused" not in events and "estop" not in events, events


def test_spoofed_liveliness_does_not_hide_a_killed_agent(
    tmp_path: Path, runs: list[RunProcess], sessions: list[zenoh.Session]
) -> None:
    """Agent d's credentials declare b's token; b is then killed: the run still sees it go."""
    experiment = write_toy_experiment(tmp_path / "toy.toml", mode="lockstep", duration_s=600.0)
    run = RunProcess(tmp_path, experiment, "--no-check")
    runs.append(run)
    spy = connect_spy(run, "toy")
    try:
        pids = run.remember_agents(4)
        wait_for(lambda: spy.last_tick() >= 10, 120, "tick 10")
        spoofer = open_as(run, forge(run, agent_user("d")))
        sessions.append(spoofer)
        spoofer.liveliness().declare_token(spy.keys.alive("b"))
        victim = next(pid for pid in pids if agent_name_of(pid) == "b")
        os.kill(victim, signal.SIGKILL)
        assert run.wait(30) == 1, run.output()  # on_agent_loss = "stop"
    finally:
        spy.close()
    recording = read_recording(run.out)
    assert any(m["state"] == "lost" for m in recording["/b/status"]), recording["/b/status"]


def test_two_runs_of_one_experiment_on_one_machine(tmp_path: Path, runs: list[RunProcess]) -> None:
    """Default options, same name, same agents, at once: each run keeps to its own bus."""
    initials = ((0.0, 1.0, 5.0, 10.0), (-3.0, 7.0, 2.0, -1.0))
    started = []
    for i, initial in enumerate(initials):
        folder = tmp_path / f"run{i}"
        folder.mkdir()
        run = RunProcess(folder, toy_run(folder, initial=initial), "--no-check", registry=tmp_path)
        runs.append(run)
        started.append(run)
    entries = [run.entry() for run in started]
    assert entries[0].run_id != entries[1].run_id
    assert entries[0].endpoints != entries[1].endpoints

    env = started[0].env
    listed = subprocess.run(
        [*CLI, "ps", "--json"], capture_output=True, text=True, timeout=60, env=env, check=False
    )
    assert listed.returncode == 0, listed.stderr
    document = json.loads(listed.stdout)
    assert document["version"] == 1
    assert {r["run_id"] for r in document["runs"]} == {e.run_id for e in entries}
    for row in document["runs"]:
        assert row["name"] == "toy" and row["mode"] == "lockstep" and row["secure"] is True
        assert set(row["agents"]) == set(AGENTS)
        assert row["endpoints"] and row["pid"] > 0 and row["n_ticks"] == N_TICKS

    # By name alone the experiment is ambiguous: refused at once, listing both runs.
    began = time.monotonic()
    ambiguous = subprocess.run(
        [*CLI, "stop", "toy", "--pause"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        check=False,
    )
    assert ambiguous.returncode == 2, ambiguous.stdout + ambiguous.stderr
    assert all(e.run_id in ambiguous.stderr for e in entries), ambiguous.stderr
    unknown = subprocess.run(
        [*CLI, "stop", "wrong_name"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        check=False,
    )
    assert unknown.returncode == 2, unknown.stdout + unknown.stderr
    assert "no running experiment 'wrong_name'" in unknown.stderr
    assert "toy" in unknown.stderr
    assert time.monotonic() - began < 10.0  # no 15 s wait for a bus that is not there
    assert "Traceback" not in ambiguous.stderr + unknown.stderr

    # Run 0's credentials are refused by run 1's router.
    other = started[0].credentials(agent_user("a"))
    stolen = Credentials(
        other.experiment, other.run_id, other.user, other.password, tuple(entries[1].endpoints)
    )
    with pytest.raises(bus.BusConnectionError):
        bus.open_session(bus.client_config(entries[1].endpoints, security=stolen.security()))

    for run, initial in zip(started, initials, strict=True):
        check_untouched(run, initial)


def test_ps_without_runs_and_stale_entries(tmp_path: Path) -> None:
    """An entry whose orchestrator is gone is removed; ``ps`` then lists nothing."""
    env = run_env(tmp_path)
    stale = Path(env["XDG_RUNTIME_DIR"]) / "hilswarm" / "deadbeef"
    stale.mkdir(parents=True, mode=0o700)
    (stale.parent).chmod(0o700)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    entry = {"version": 1, "name": "old", "run_id": "deadbeef", "endpoints": [], "pid": dead.pid}
    (stale / "run.json").write_text(json.dumps({**entry, "mode": "lockstep", "pid_start": 1}))
    listed = subprocess.run(
        [*CLI, "ps", "--json"], capture_output=True, text=True, timeout=60, env=env, check=False
    )
    assert listed.returncode == 0, listed.stderr
    assert json.loads(listed.stdout) == {"version": 1, "runs": []}
    assert not stale.exists()
    text = subprocess.run(
        [*CLI, "ps"], capture_output=True, text=True, timeout=60, env=env, check=False
    )
    assert text.stdout.strip() == "no running experiments"

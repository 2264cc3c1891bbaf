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
from hilswarm.agents.mocap import frame_clock
from hilswarm.agents.mocap import message as mocap_message
from hilswarm.orchestrator.bus_access import GATEWAY, MOCAP, OPERATOR, VIEWER, agent_user
from swarm_harness import (
    REPO,
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


#: Bytes no board link ever carries (a COBS frame whose CRC is wrong): forged board traffic.
FORGED_LINK = b"\x00hilswarm-forged-link-bytes\x00"


def forgeries(
    keys: bus.BusKeys, *, user: str, target: str = "a", body: str = "a"
) -> list[tuple[str, bytes]]:
    """Every forged put of the issue, as ``(key, payload)``, that ``user`` may not make.

    ``target`` is the attacked agent and ``body`` its mocap rigid body. Besides the swarm's
    own keys (tick, control, y, status, telemetry) they cover the keys that reach hardware or
    the record: the board link over the XBee gateway (``link/tx``, ``link/rx``, the simulated
    robot's UART ``link/robot/{in,out}``), mocap poses and status, the mocap frame clock the
    manager locks its ticks to (``mocap_clock``), the simulated plant's true pose, the
    gateway's fault commands and status, the manager's status, ``u`` and ``x_hat``.
    What the principal's role allows is left out (the operator may ask the manager to stop and
    send ``gateway/sim``; the mocap process puts poses; the gateway relays link bytes).
    """
    vector = bus.encode_vector(20, 0.4, [FORGED])
    pose = mocap_message.encode_row(10**6, 0.0, 0.0, 0.0, occluded=0, values=[FORGED] * 20)
    sent = [
        (keys.tick, bus.encode_tick(bus.TickMessage(10**6, 2e4, (), realtime=False))),
        (keys.tick, b"\x01"),
        *((keys.control, bus.encode_control(c, reason="forged")) for c in bus.ControlCommand),
        (keys.manager_status, bus.encode_json({"state": "estop", "detail": "forged"})),
        (keys.y(target), vector),
        (keys.y(target), b"\x00\x01\x02"),
        (keys.u(target), vector),
        (keys.x_hat(target), vector),
        (
            keys.status(target),
            bus.encode_json({"agent": target, "state": "safe", "detail": "forged"}),
        ),
        (keys.agent(target, "telemetry/battery"), vector),
        (keys.mocap_truth(body), mocap_message.encode_truth(np.full(6, FORGED), 0.4)),
    ]
    if user != OPERATOR:
        sent += [
            (keys.manager_request, bus.encode_control(bus.ControlCommand.STOP, reason="forged")),
            (keys.gateway("sim"), json.dumps({"unplug": True, "forged": FORGED}).encode()),
        ]
    if user != MOCAP:
        sent += [
            (keys.mocap(body), pose),
            (keys.mocap_status, bus.encode_json({"state": "lost", "detail": "forged"})),
            # a frame clock half a period off the real frames would shift every tick
            (keys.mocap_clock, frame_clock.encode(10**6, FORGED)),
        ]
    if user != GATEWAY:
        sent += [
            (keys.link_tx(target), FORGED_LINK),
            (keys.link_rx(target), FORGED_LINK),
            (keys.link_robot(target, "in"), FORGED_LINK),
            (keys.link_robot(target, "out"), FORGED_LINK),
            (keys.gateway("status"), bus.encode_json({"state": "unplugged", "forged": FORGED})),
        ]
    return sent


def attack(
    session: zenoh.Session, keys: bus.BusKeys, *, user: str, target: str = "a", body: str = "a"
) -> tuple[list[object], list[tuple[str, bytes]]]:
    """Every forgery of :func:`forgeries` from one session of principal ``user`` (each should
    be dropped by the router), plus spoofed liveliness tokens and a forged ``set`` query.

    Returns the declared entities (tokens, publishers), which must stay alive, and the forged
    puts.
    """
    kept: list[object] = []
    sent = forgeries(keys, user=user, target=target, body=body)
    for key, payload in sent:
        publisher = session.declare_publisher(key, **bus.TICK_PATH_QOS)
        kept.append(publisher)
        publisher.put(payload)
    kept.append(session.liveliness().declare_token(keys.alive(target)))
    kept.append(session.liveliness().declare_token(keys.alive("_manager")))
    kept.append(session.liveliness().declare_token(keys.alive("_mocap")))
    if user != OPERATOR:
        for reply in session.get(
            keys.set(target), payload=bus.encode_json({"params": {"gain": 50.0}}), timeout=0.5
        ):
            assert reply.ok is None, "a forged set was answered"
    return kept, sent


class Witness:
    """A viewer session that hears everything of the run, both through ``**`` and through an
    explicit subscription per attacked key (publishers such as ``u`` and the link's only send
    while someone subscribes to their key): whatever the router lets through reaches it."""

    def __init__(self, session: zenoh.Session, keys: bus.BusKeys, attacked: set[str]) -> None:
        self.got: dict[str, set[bytes]] = {}
        self._lock = threading.Lock()
        callback = zenoh.handlers.Callback(self._on_sample, indirect=False)
        self.subscribers = [session.declare_subscriber(f"{keys.prefix}/**", callback)]
        for key in sorted(attacked):
            self.subscribers.append(
                session.declare_subscriber(
                    key, zenoh.handlers.Callback(self._on_sample, indirect=False)
                )
            )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.got.setdefault(str(sample.key_expr), set()).add(sample.payload.to_bytes())

    def heard(self, key: str) -> set[bytes]:
        with self._lock:
            return set(self.got.get(key, ()))

    def forged_heard(self, sent: list[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
        """The forged puts that reached the witness (none should)."""
        with self._lock:
            return [(k, p) for k, p in sent if p in self.got.get(k, ())]


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
        sent: list[tuple[str, bytes]] = []

        # No credentials, a wrong password, an unknown user: refused when the session opens,
        # so such a client puts nothing on any key (those of the board links, mocap, the
        # manager's status, u and x_hat included).
        with pytest.raises(bus.BusConnectionError, match=r"refused|nothing answers"):
            open_as(run, None)
        real = forge(run, agent_user("d"))
        for user, password in ((real.user, "wrong"), ("intruder", real.password)):
            stolen = Credentials(real.experiment, real.run_id, user, password, real.endpoints)
            with pytest.raises(bus.BusConnectionError):
                open_as(run, stolen)

        # A witness that hears whatever the router lets through, on every attacked key.
        watcher = open_as(run, forge(run, VIEWER))
        sessions.append(watcher)
        witness = Witness(watcher, keys, {k for k, _ in forgeries(keys, user=VIEWER)})

        # Another principal's credentials: the router's access control drops every forgery.
        for user in (agent_user("d"), agent_user("b"), OPERATOR, VIEWER):
            session = open_as(run, forge(run, user))
            sessions.append(session)
            entities, forged = attack(session, keys, user=user)
            kept += entities
            sent += forged

        # Snooping with an agent's credentials: only what that agent may hear arrives.
        d = open_as(run, forge(run, agent_user("d")))
        sessions.append(d)
        everything = Listener(d, f"{keys.prefix}/**")
        not_a_neighbour = Listener(d, keys.y("b"))
        inputs = Listener(d, keys.u("c"))
        allowed = Listener(d, keys.y("a"))  # d hears a
        wait_for(lambda: len(allowed.seen()) >= 5, 120, "d's session to hear a's y")
        # The query an agent sends before it closes its session (bus.flush_barrier), with its
        # credentials on its own key: the router lets it through and ends it (no one answers).
        assert bus.flush_barrier(d, keys.flush("d"), timeout_s=5.0)
        assert spy.last_tick() < N_TICKS - 1, "the run ended before the attacks were over"
    finally:
        spy.close()
    # Everything d's session got is what agent d hears anyway (its session's own a/y
    # subscription also feeds its ** one): a's output and the manager's ticks.
    assert set(everything.seen()) <= {keys.y("a"), keys.tick, keys.control}, everything.seen()
    assert not_a_neighbour.seen() == []
    assert inputs.seen() == []

    recording = check_untouched(run, initial)
    # The witness heard the genuine traffic of the attacked agent's keys, never a forgery.
    for key in (keys.tick, keys.manager_status, keys.y("a"), keys.u("a"), keys.x_hat("a")):
        assert witness.heard(key), f"the witness heard nothing on {key}"
    assert witness.forged_heard(sent) == []
    for name in AGENTS:
        for message in recording.get(f"/{name}/status", []):
            assert "forged" not in str(message.get("detail", "")), message
            assert "gain" not in str(message.get("detail", "")), message
    assert str(FORGED) not in json.dumps(recording, default=str)  # no forged value anywhere
    events = [m.get("state") for m in recording.get("/orchestrator/status", [])]
    assert "paused" not in events and "estop" not in events, events


def mocap_xbee_run(tmp_path: Path) -> Path:
    """graphs/lead_follow_mocap.toml (realtime, poses from the simulated mocap system) with
    every robot behind a simulated XBee radio: the run has every key that reaches a board or a
    pose, each with a principal of its own (agents, ``mocap``, ``gateway``).

    ``max_late_fraction = 0.5``: a loaded test machine makes a few percent of ticks late; the
    frozen swarm of a forged tick (the issue: 84 % late) would still fail the run.
    """
    text = (REPO / "graphs" / "lead_follow_mocap.toml").read_text(encoding="utf-8")
    replace = {
        'mode = "realtime"': 'mode = "realtime"\nmax_late_fraction = 0.5',
        "duration_s = 20.0": f"duration_s = {MOCAP_TICKS / 20}",
        "[graph]": '[gateway]\nport = "sim"\nseed = 1\n\n[graph]',
        'link = "sim://"\n': "",
    }
    for i, name in enumerate(("leader", "f1", "f2"), 1):
        replace[f"[agents.{name}]\n"] = (
            f'[agents.{name}]\nlink = "xbee://0013A2004000000{i}?sim=sim://duemilanove"\n'
        )
    for old, new in replace.items():
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path = tmp_path / "mocap_xbee.toml"
    path.write_text(text, encoding="utf-8")
    return path


#: Realtime ticks (20 Hz) of the attacked mocap + XBee run.
MOCAP_TICKS = 240


@pytest.mark.slow
def test_hostile_clients_cannot_reach_boards_poses_or_the_record(
    tmp_path: Path, runs: list[RunProcess], sessions: list[zenoh.Session]
) -> None:
    """The leader's board link (over the gateway), its mocap body's pose, the mocap and gateway
    status, the mocap frame clock, the manager's status, its u and x_hat: forged with every
    other principal's credentials, none reaches the agents, the gateway, the mocap process, the
    manager or the recording."""
    run = RunProcess(tmp_path, mocap_xbee_run(tmp_path), "--no-check")
    runs.append(run)
    spy = connect_spy(run, "lead_follow_mocap")
    keys = spy.keys
    try:
        with pytest.raises(bus.BusConnectionError, match=r"refused|nothing answers"):
            open_as(run, None)
        watcher = open_as(run, forge(run, VIEWER))
        sessions.append(watcher)
        attacked = {k for k, _ in forgeries(keys, user=VIEWER, target="leader", body="frisbee1")}
        witness = Witness(watcher, keys, attacked)
        wait_for(lambda: spy.last_tick() >= 20, 120, "tick 20")
        kept: list[object] = []
        sent: list[tuple[str, bytes]] = []
        # f2 hears f1, not the leader; the others' roles are elsewhere.
        for user in (agent_user("f2"), agent_user("f1"), OPERATOR, VIEWER, MOCAP, GATEWAY):
            session = open_as(run, forge(run, user))
            sessions.append(session)
            entities, forged = attack(session, keys, user=user, target="leader", body="frisbee1")
            kept += entities
            sent += forged
        assert spy.last_tick() < MOCAP_TICKS - 20, "the run ended before the attacks were over"
    finally:
        spy.close()
    assert run.wait(300) == 0, run.output()
    assert "stopped: completed" in run.output(), run.output()

    # The witness heard the genuine traffic on the leader's board link, its body's pose, the
    # mocap status, the manager's status, u and x_hat: the router forwards these keys to a
    # listener allowed to hear them, and dropped every forgery on them.
    for key in (
        keys.link_tx("leader"),
        keys.link_rx("leader"),
        keys.link_robot("leader", "in"),
        keys.link_robot("leader", "out"),
        keys.mocap("frisbee1"),
        keys.mocap_status,
        keys.mocap_clock,
        keys.manager_status,
        keys.u("leader"),
        keys.x_hat("leader"),
        keys.y("leader"),
    ):
        assert witness.heard(key), f"the witness heard nothing on {key}"
    assert witness.forged_heard(sent) == []

    # Nothing forged in the record: no forged value, no safe / lost / e-stop, and the swarm
    # kept ticking (realtime skips a tick that comes too late; a frozen swarm runs none).
    recording = read_recording(run.out)
    assert str(FORGED) not in json.dumps(recording, default=str)
    for name in ("leader", "f1", "f2"):
        ks = [m["k"] for m in recording[f"/{name}/y"]]
        assert len(ks) > MOCAP_TICKS // 2 and ks == sorted(set(ks)), (name, ks)
        for message in recording.get(f"/{name}/status", []):
            detail = str(message.get("detail", ""))
            assert "forged" not in detail, message
            assert message["state"] not in ("lost", "estop"), message
            assert message["state"] != "safe" or "completed" in detail or "stop" in detail, message
        xy = np.array([m["values"][:2] for m in recording[f"/{name}/y"]], dtype=float)
        assert np.all(np.abs(xy) < 3.0), name  # poses of the 1 m square, not forged ones
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


def test_ps_shows_the_local_agents_while_the_run_waits_for_a_remote_one(
    tmp_path: Path, runs: list[RunProcess]
) -> None:
    """``--remote d`` never joins: while the run waits, ``ps`` shows a, b and c as they
    reported (armed), d still starting; Ctrl-C then ends the wait (exit 130)."""
    run = RunProcess(
        tmp_path, toy_run(tmp_path), "--no-check", "--listen", "tls/127.0.0.1:0",
        "--remote", "d", "--start-timeout", "120",
    )  # fmt: skip
    runs.append(run)

    def states() -> dict[str, str]:
        listed = subprocess.run(
            [*CLI, "ps", "--json"], capture_output=True, text=True, timeout=60, env=run.env,
            check=False,
        )  # fmt: skip
        assert listed.returncode == 0, listed.stderr
        rows = json.loads(listed.stdout)["runs"]
        return rows[0]["agents"] if rows else {}

    wait_for(
        lambda: [states().get(name) for name in AGENTS] == ["armed", "armed", "armed", "starting"],
        60,
        "a, b, c armed and d starting in hilswarm ps",
    )
    run.process.send_signal(signal.SIGINT)
    assert run.wait(60) == 130, run.output()


def test_a_second_process_for_a_running_agent_is_refused_and_the_run_goes_on(
    tmp_path: Path, runs: list[RunProcess]
) -> None:
    """``hilswarm agent --name a`` while the run's own agent a is armed (the run waits for
    ``--remote d``): refused at once, exit 2, nothing of it on the bus; then d joins, and the
    run completes clean with every tick of every agent exactly once."""
    experiment = toy_run(tmp_path)
    run = RunProcess(tmp_path, experiment, "--no-check", "--remote", "d", "--start-timeout", "120")
    runs.append(run)
    entry = run.entry()
    run.remember_agents(3)

    def agent(name: str, log: Path) -> subprocess.Popen[bytes]:
        with log.open("wb") as out:
            return subprocess.Popen(
                [*CLI, "agent", "--experiment", str(experiment), "--name", name],
                env=run.env, cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=out,
                stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip

    def armed() -> bool:
        listed = subprocess.run(
            [*CLI, "ps", "--json"], capture_output=True, text=True, timeout=60, env=run.env,
            check=False,
        )  # fmt: skip
        rows = json.loads(listed.stdout)["runs"] if listed.returncode == 0 else []
        return bool(rows) and rows[0]["agents"].get("a") == "armed"

    wait_for(armed, 60, "agent a armed")
    duplicate = agent("a", tmp_path / "duplicate.log")
    runs_agent: list[subprocess.Popen[bytes]] = [duplicate]
    try:
        assert duplicate.wait(60) == 2, (tmp_path / "duplicate.log").read_text()
        said = (tmp_path / "duplicate.log").read_text()
        assert "agent 'a' is already running" in said and entry.run_id in said, said
        assert "Traceback" not in said, said
        remote = agent("d", tmp_path / "remote.log")
        runs_agent.append(remote)
        assert run.wait(240) == 0, run.output() + (tmp_path / "remote.log").read_text()
        assert remote.wait(60) == 0, (tmp_path / "remote.log").read_text()
    finally:
        for process in runs_agent:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(10)
    recording = read_recording(run.out)
    for name in AGENTS:
        assert [m["k"] for m in recording[f"/{name}/y"]] == list(range(N_TICKS)), name
        dropped = [m.get("dropped") for m in recording[f"/{name}/status"] if m.get("dropped")]
        assert not dropped, (name, dropped)

"""The swarm runtime end to end: real `hilswarm run` processes, agents, Zenoh on loopback."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hilswarm.agents import bus
from hilswarm.orchestrator.experiment import load_experiment
from mcap.reader import make_reader
from swarm_harness import (
    TOY_NEIGHBOURS,
    RunProcess,
    Spy,
    agent_name_of,
    child_pids,
    connect_spy,
    pid_alive,
    read_recording,
    thread_policies,
    wait_for,
    write_toy_experiment,
)

pytestmark = pytest.mark.integration

AGENTS = ("a", "b", "c", "d")
CLI = (sys.executable, "-m", "hilswarm.orchestrator.cli")


@pytest.fixture
def spies() -> Iterator[list[Spy]]:
    opened: list[Spy] = []
    yield opened
    for spy in opened:
        spy.close()


def start(runs: list[RunProcess], tmp_path: Path, experiment: Path, *args: str) -> RunProcess:
    run = RunProcess(tmp_path, experiment, "--no-check", *args)
    runs.append(run)
    return run


def statuses(recording: dict, agent: str) -> list[dict]:
    return recording.get(f"/{agent}/status", [])


def states(recording: dict, agent: str) -> list[str]:
    return [m["state"] for m in statuses(recording, agent)]


def test_lockstep_run_records_every_tick_and_delivers_only_to_neighbours(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=4.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    assert run.wait(120) == 0, run.output()

    recording = read_recording(run.out)
    n_ticks = 200
    for name in AGENTS:
        ys = recording[f"/{name}/y"]
        assert [m["k"] for m in ys] == list(range(n_ticks))
        assert [m["k"] for m in recording[f"/{name}/u"]] == list(range(1, n_ticks))
        assert states(recording, name) == [
            "connected",
            "configured",
            "armed",
            "running",
            "safe",
            "stopped",
        ]
        # The agent reports which outputs it actually received: exactly its neighbours'.
        final = statuses(recording, name)[-1]["detail"]
        received = set(final.removeprefix("received from: ").split(", ")) - {"-"}
        assert received == TOY_NEIGHBOURS[name], (name, final)
    assert [m["k"] for m in recording["/orchestrator/ticks"]] == list(range(n_ticks))
    tick = recording["/orchestrator/ticks"][10]
    assert set(tick["agents"]) == set(AGENTS)
    assert {"answer_s", "sense_s", "compute_s", "actuate_s"} <= set(tick["agents"]["a"])

    # The spy saw every agent's y on the bus: delivery is restricted by subscriptions, not
    # by hiding data; nobody subscribes to d's output, and d's y is still recorded. (Every
    # one from the spy's first: it may have subscribed after tick 0, see ``Spy``.)
    for name in AGENTS:
        first, last, count = spy.answers(name)
        assert (last, count) == (n_ticks - 1, n_ticks - first), (name, first, last, count)
    # Lockstep releases the first window of ticks, then at least half a window per tick
    # message (default window 8: at most one message per 4 ticks); the last releases the end.
    window = load_experiment(experiment).lockstep_window
    assert 1 <= spy.count("hilswarm/toy/tick") <= 1 + (n_ticks - window) // (window // 2)
    assert spy.last_tick() == n_ticks - 1

    # Lockstep is deterministic: replay the toy closed loop exactly.
    x = np.array([0.0, 1.0, 5.0, 10.0])
    hears = [1, 2, 0, 0]
    dt, gain = 1 / 50, 2.0
    expected = [x.copy()]
    for _ in range(1, n_ticks):
        u = gain * (x[hears] - x)
        x = x + dt * u
        expected.append(x.copy())
    got = np.array([[m["values"][0] for m in recording[f"/{n}/y"]] for n in AGENTS]).T
    np.testing.assert_allclose(got, np.array(expected), rtol=0, atol=1e-12)


def test_kill_9_with_policy_stop_stops_everyone_safely(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = write_toy_experiment(
        tmp_path / "toy.toml", mode="realtime", duration_s=60.0, on_agent_loss="stop"
    )
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    pids = run.remember_agents(4)
    wait_for(lambda: spy.last_tick() >= 20, 60, "tick 20")
    victim = _pid_of(pids, "b")
    os.kill(victim, signal.SIGKILL)
    assert run.wait(20) == 1, run.output()
    recording = read_recording(run.out)
    lost = [m for m in statuses(recording, "b") if m["state"] == "lost"]
    assert lost, states(recording, "b")
    # The loss report says what became of the process (when the manager heard of it).
    assert "liveliness token lost" in lost[0]["detail"], lost[0]
    assert "killed by SIGKILL" in lost[0]["detail"] or "still running" in lost[0]["detail"]
    for name in ("a", "c", "d"):
        assert states(recording, name)[-2:] == ["safe", "stopped"], states(recording, name)
    assert "failed: agent b lost" in run.output(), run.output()
    for pid in pids:
        wait_for(lambda pid=pid: not pid_alive(pid), 15, f"agent {pid} to exit")


def test_kill_9_with_policy_continue_marks_agent_missing(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = write_toy_experiment(
        tmp_path / "toy.toml", mode="realtime", duration_s=4.0, on_agent_loss="continue"
    )
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    pids = run.remember_agents(4)
    wait_for(lambda: spy.last_tick() >= 30, 60, "tick 30")
    os.kill(_pid_of(pids, "b"), signal.SIGKILL)
    assert run.wait(30) == 3, run.output()  # completed, degraded: an agent was lost
    assert "degraded: agent b lost at tick" in run.output() and "ticks missed" in run.output()
    recording = read_recording(run.out)
    assert [m["state"] for m in statuses(recording, "b")][-1] == "lost"
    # The run went on to the end without b.
    assert recording["/a/y"][-1]["k"] == 199
    assert recording["/c/y"][-1]["k"] == 199
    # a hears b: after the loss a's controller saw None ("no data") on every tick it ran.
    # Realtime skips the ticks an agent fell behind on, so count the ticks a actually ran
    # (one y each), from the tick after the one the loss was announced at.
    missing_ticks = recording["/a/x_hat"][-1]["values"][0]
    k_lost = next(m["k"] for m in statuses(recording, "b") if m["state"] == "lost")
    ran_after_loss = [m["k"] for m in recording["/a/y"] if m["k"] > k_lost + 1]
    assert missing_ticks >= len(ran_after_loss), (k_lost, missing_ticks, ran_after_loss)
    # Fewer ticks than the run had only when a skipped some, and the record says so.
    ticks = recording["/orchestrator/ticks"]
    if len(ran_after_loss) < 199 - k_lost - 1:
        skips = [m["k"] for m in ticks if m["agents"].get("a", {}).get("skipped")]
        assert skips, (k_lost, ran_after_loss)
    # c does not hear b: it saw "no data" only at ticks after which a, the one agent it hears,
    # was late (in realtime a late answer is listed missing in the next tick; under load that
    # happens), never because of b, which was missing for the last ~170 ticks.
    a_late = sum(1 for m in ticks if "a" in m["late"])
    c_missing = recording["/c/x_hat"][-1]["values"][0]
    assert c_missing <= a_late, (c_missing, a_late)
    assert ticks[-1]["missing"] == ["b"], ticks[-1]


def test_hung_agent_is_detected_and_stops_the_run(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = write_toy_experiment(
        tmp_path / "toy.toml", mode="realtime", duration_s=60.0, on_agent_loss="stop"
    )
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    pids = run.remember_agents(4)
    wait_for(lambda: spy.last_tick() >= 20, 60, "tick 20")
    victim = _pid_of(pids, "c")
    os.kill(victim, signal.SIGSTOP)
    try:
        # The 1 s lease drops the hung client; then every other agent goes safe and stops.
        assert run.wait(20) == 1, run.output()
    finally:
        with contextlib.suppress(ProcessLookupError):  # the launcher may have killed it
            os.kill(victim, signal.SIGCONT)
    recording = read_recording(run.out)
    assert "lost" in states(recording, "c")
    lost_tick = next(m["k"] for m in statuses(recording, "c") if m["state"] == "lost")
    detail = next(m["detail"] for m in statuses(recording, "c") if m["state"] == "lost")
    assert "still running" in detail or "no answer within" in detail, detail
    # Bounded detection: within 3 s (150 ticks at 50 Hz) of the last answer of c.
    last_answer = recording["/c/y"][-1]["k"]
    assert lost_tick - last_answer <= 150
    ticks = recording["/orchestrator/ticks"]
    late_for_c = [m["k"] for m in ticks if "c" in m["late"]]
    assert late_for_c, "the late answers of the hung agent must be counted"
    for name in ("a", "b", "d"):
        assert states(recording, name)[-2:] == ["safe", "stopped"]


def test_ctrl_c_brings_agents_to_safe_and_completes_the_recording(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = write_toy_experiment(tmp_path / "toy.toml", mode="realtime", duration_s=60.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    pids = run.remember_agents(4)
    wait_for(lambda: spy.last_tick() >= 20, 60, "tick 20")
    run.process.send_signal(signal.SIGINT)
    assert run.wait(20) == 130, run.output()
    with run.out.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None, "the MCAP file must be closed properly (summary section)"
    recording = read_recording(run.out)
    for name in AGENTS:
        assert states(recording, name)[-2:] == ["safe", "stopped"], states(recording, name)
        assert "interrupted" in statuses(recording, name)[-2]["detail"]
    for pid in pids:
        wait_for(lambda pid=pid: not pid_alive(pid), 15, f"agent {pid} to exit")


def test_orchestrator_killed_agents_exit_and_recording_is_recoverable(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = write_toy_experiment(tmp_path / "toy.toml", mode="realtime", duration_s=60.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    pids = run.remember_agents(4)
    wait_for(lambda: spy.last_tick() >= 100, 60, "tick 100")
    os.killpg(run.process.pid, signal.SIGKILL)
    run.wait(10)
    # Agents notice the manager's liveliness token vanish and stop by themselves.
    for pid in pids:
        wait_for(lambda pid=pid: not pid_alive(pid), 15, f"orphaned agent {pid} to exit")
    recovered = tmp_path / "recovered.mcap"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "hilswarm.orchestrator.cli",
            "recover",
            str(run.out),
            "-o",
            str(recovered),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    recording = read_recording(recovered)
    assert len(recording["/a/y"]) > 10
    with recovered.open("rb") as f:
        assert make_reader(f).get_summary() is not None


def test_recorder_killed_run_goes_on_into_the_next_segment(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    """kill -9 of the recorder: a new one continues in run.1.mcap; nothing lost; exit 3."""
    experiment = write_toy_experiment(tmp_path / "toy.toml", mode="realtime", duration_s=4.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    run.remember_agents(4)
    wait_for(lambda: spy.last_tick() >= 60, 60, "tick 60")
    recorders = [
        pid
        for pid in child_pids(run.process.pid)
        if b"recorder_process" in Path(f"/proc/{pid}/cmdline").read_bytes()
    ]
    assert len(recorders) == 1
    os.kill(recorders[0], signal.SIGKILL)
    # The swarm is not stopped; the recording goes on in a new segment, the summary says so.
    assert run.wait(60) == 3, run.output()
    output = run.output()
    assert "killed by SIGKILL" in output and "continued in run.1.mcap" in output, output
    assert "records lost" not in output, output
    assert spy.last_tick() == 199
    segments = [run.out, run.out.with_name("run.1.mcap")]
    ticks: list[int] = []
    for segment in segments:  # each a complete file, with the run's start
        with segment.open("rb") as f:
            assert make_reader(f).get_summary() is not None
        recording = read_recording(segment)
        assert recording["/experiment"]
        ticks += [m["k"] for m in recording["/a/y"]]
    # Every y once, in order, across the segments (realtime: an agent that fell behind under
    # load runs the newest tick and skips the ones it missed), and none lost: at least every
    # y the spy saw (it may have missed the first ones).
    assert ticks == sorted(set(ticks)) and ticks[0] == 0 and ticks[-1] <= 199, ticks
    missing = sorted(set(range(200)) - set(ticks))
    assert len(ticks) >= spy.count("hilswarm/toy/agent/a/y"), f"not recorded: ticks {missing}"


def test_estop_reaches_every_agent_within_one_tick(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = write_toy_experiment(tmp_path / "toy.toml", mode="realtime", duration_s=60.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    run.remember_agents(4)
    wait_for(lambda: spy.last_tick() >= 25, 60, "tick 25")
    for pid in run.agent_pids:  # realtime keeps the default policy (agents/scheduling.py)
        assert thread_policies(pid) == {os.SCHED_OTHER}, agent_name_of(pid)
    spy.control(bus.ControlCommand.ESTOP, "test e-stop")
    assert run.wait(20) == 3, run.output()  # every agent safe: degraded
    assert "degraded: e-stop at tick" in run.output(), run.output()
    recording = read_recording(run.out)
    estop = [m for m in recording["/orchestrator/status"] if m["state"] == "estop"]
    assert len(estop) == 1
    k_estop = estop[0]["k"]
    for name in AGENTS:
        safe = next(m for m in statuses(recording, name) if m["state"] == "safe")
        assert "e-stop" in safe["detail"]
        assert safe["k"] <= k_estop + 1, (name, safe["k"], k_estop)
        # Actuators off: the integrator never moves again after the safe tick.
        after = [m["values"][0] for m in recording[f"/{name}/y"] if m["k"] > safe["k"]]
        assert all(v == after[0] for v in after), name


def test_set_changes_parameters_between_ticks_and_is_acknowledged(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = write_toy_experiment(tmp_path / "toy.toml", mode="realtime", duration_s=60.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    run.remember_agents(4)
    wait_for(lambda: spy.last_tick() >= 10, 60, "tick 10")
    cli = CLI
    # set and stop find the run by name in the run registry: no port, no endpoint.
    ok = subprocess.run(
        [*cli, "set", "toy", "b", "gain=0.25"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env=run.env,
    )
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert "set {'gain': 0.25}" in ok.stdout
    bad = subprocess.run(
        [*cli, "set", "toy", "b", 'gain="fast"'],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env=run.env,
    )
    assert bad.returncode == 2
    assert "gain must be a number" in bad.stderr
    stop = subprocess.run(
        [*cli, "stop", "toy"], capture_output=True, text=True, timeout=60, check=False, env=run.env
    )
    assert stop.returncode == 0, stop.stdout + stop.stderr
    assert run.wait(20) == 0, run.output()
    recording = read_recording(run.out)
    details = [m["detail"] for m in statuses(recording, "b")]
    assert any("set {'gain': 0.25}" in d for d in details), details
    assert any("set refused" in d for d in details), details


def _pid_of(pids: list[int], agent: str) -> int:
    """The pid of ``agent`` among agent processes (its name is in the --config JSON)."""
    for pid in pids:
        if agent_name_of(pid) == agent:
            return pid
    raise AssertionError(f"no process for agent {agent}")


def test_realtime_overload_is_reported_while_running(
    tmp_path: Path, runs: list[RunProcess]
) -> None:
    """An agent too slow for the rate: its late ticks are counted and the run says why."""
    experiment = write_toy_experiment(tmp_path / "toy.toml", mode="realtime", duration_s=3.0)
    text = experiment.read_text(encoding="utf-8")
    slow = "[agents.b]\ninitial_state = [1.0]\nparams = { gain = 2.0, work_s = 0.03 }"
    experiment.write_text(text.replace("[agents.b]\ninitial_state = [1.0]", slow, 1))
    run = start(runs, tmp_path, experiment)
    assert run.wait(120) == 3, run.output()  # late ticks above max_late_fraction
    output = run.output()
    assert "do not keep up with 50 Hz" in output, output
    assert "% busy over those ticks" in output, output  # the CPUs' share, to tell the cause
    assert "degraded: " in output and "ticks late" in output, output
    assert "late answers: " in output and "b=" in output, output
    recording = read_recording(run.out)
    late = [m for m in recording["/orchestrator/ticks"] if "b" in m["late"]]
    assert len(late) > 50  # b takes 30 ms per 20 ms tick


def test_lockstep_pause_holds_the_ticks_and_resume_goes_on(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    """``hilswarm stop --pause`` / ``--resume`` with a window of ticks in flight."""
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=600.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    wait_for(lambda: spy.last_tick() >= 100, 60, "tick 100")
    # Lockstep is batch work: every agent thread under SCHED_BATCH (agents/scheduling.py).
    for pid in run.remember_agents(4):
        assert thread_policies(pid) == {os.SCHED_BATCH}, agent_name_of(pid)
    spy.control(bus.ControlCommand.PAUSE, "test pause")
    # The manager says it is paused; it sends no tick message after that. The ticks released
    # before the pause are answered (tick 0 to the last released one), then nothing moves.
    # (Counted from the spy's first answer: it may have subscribed after tick 0, see ``Spy``;
    # the recording below has every tick from 0.)
    wait_for(lambda: spy.manager_state() == "paused", 30, "the manager's paused status")
    last_released = spy.last_tick()

    def answered() -> bool:
        first, last, count = spy.answers("a")
        return last == last_released and count == last - first + 1

    wait_for(
        answered,
        30,
        lambda: (
            f"the answers to the ticks released before the pause (up to {last_released};"
            f" a's first, last and count seen: {spy.answers('a')})"
        ),
    )
    held = (last_released, spy.answers("a"))
    time.sleep(0.5)  # held paused for a while: nothing may move meanwhile
    assert (spy.last_tick(), spy.answers("a")) == held
    spy.control(bus.ControlCommand.RESUME, "test resume")
    wait_for(lambda: spy.last_tick() >= held[0] + 100, 60, "100 more ticks after resume")
    spy.control(bus.ControlCommand.STOP, "test done")
    assert run.wait(30) == 0, run.output()
    recording = read_recording(run.out)
    manager = [m["state"] for m in recording["/orchestrator/status"]]
    assert manager[manager.index("paused") + 1] == "running", manager
    for name in AGENTS:
        ks = [m["k"] for m in recording[f"/{name}/y"]]
        assert ks == list(range(len(ks))), name  # no tick lost or repeated across the pause
        assert ks[-1] > held[0]
        agent_states = states(recording, name)
        assert agent_states[agent_states.index("paused") + 1] == "running", agent_states
        assert agent_states[-2:] == ["safe", "stopped"]


def test_malformed_and_forged_input_is_dropped_counted_and_never_fatal(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    """Garbage on every key an agent listens to, and ticks far ahead of the window: the
    lockstep run still completes every tick, no agent runs away, and the agents' status
    messages count what they dropped. The agents' own defence: the run is ``--insecure``, so
    the router's access control (tests/integration/test_bus_security.py) lets it all through."""
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=4.0)
    run = start(runs, tmp_path, experiment, "--insecure")
    spy = connect_spy(run, "toy")
    spies.append(spy)
    keys = spy.keys
    wait_for(lambda: spy.last_tick() >= 5, 60, "tick 5")
    forged_tick = bus.encode_tick(bus.TickMessage(1_000_000, 1_000_000 * 0.02))
    garbage = {
        keys.tick: [b"\x01", b"\x00" * 21, forged_tick],
        keys.y("a"): [b"\x01\x02\x03", b"", bus.encode_vector(10**9, 0.0, [1.0])],
        keys.control: [b"\xff\xfe", b"[1, 2]", b'{"command": "fly"}', b"[" * 100_000],
    }
    for key, payloads in garbage.items():
        for payload in payloads:  # blocking: a dropped put would not be counted (100 kB ones)
            spy.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
    replies = list(spy.session.get(keys.set("b"), payload=b"\x00not json", timeout=10.0))
    assert replies and replies[0].err is not None
    # never fatal, but not a clean run: the summary lists the counts, exit status 3
    assert run.wait(60) == 3, run.output()
    assert "malformed messages" in run.output(), run.output()
    recording = read_recording(run.out)
    for name in AGENTS:
        ks = [m["k"] for m in recording[f"/{name}/y"]]
        if name == "a":  # the recorder keeps what was put on a's key (the bus ACL stops that)
            ks = [k for k in ks if k != 10**9]
        assert ks == list(range(200)), name  # every tick once, none beyond the run
        assert states(recording, name)[-2:] == ["safe", "stopped"]
    last_b = statuses(recording, "b")[-1]  # b hears c, listens to tick, control and set
    assert last_b["malformed"]["tick"] == 2, last_b
    assert last_b["malformed"]["control"] == 4, last_b
    assert last_b["malformed"]["set"] == 1, last_b
    assert last_b["dropped"]["tick_ahead"] == 1, last_b
    last_c = statuses(recording, "c")[-1]  # c hears a
    assert last_c["malformed"]["y"] == 2, last_c
    assert last_c["dropped"]["y_ahead"] == 1, last_c

"""Self-clocked realtime runs end to end: the agents keep the manager's schedule themselves.

Real ``hilswarm run`` processes, agents and Zenoh on loopback (``realtime_clock = "shared"``).
"""

from __future__ import annotations

import os
import re
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hilswarm.agents import bus
from swarm_harness import (
    REPO,
    RunProcess,
    Spy,
    agent_name_of,
    connect_spy,
    read_recording,
    wait_for,
    write_toy_experiment,
)

pytestmark = pytest.mark.integration

AGENTS = ("a", "b", "c", "d")
HEARS = {"a": "b", "b": "c", "c": "a", "d": "a"}  # the toy graph: one neighbour each


@pytest.fixture
def spies() -> Iterator[list[Spy]]:
    opened: list[Spy] = []
    yield opened
    for spy in opened:
        spy.close()


def shared_clock_experiment(path: Path, **kwargs: object) -> Path:
    """The toy experiment, realtime and self-clocked; late ticks do not degrade the outcome
    (a loaded test machine may make some late; the accounting is what is tested)."""
    write_toy_experiment(path, mode="realtime", **kwargs)
    text = path.read_text(encoding="utf-8").replace(
        'mode = "realtime"\n',
        'mode = "realtime"\nrealtime_clock = "shared"\nmax_late_fraction = 1.0\n',
    )
    path.write_text(text, encoding="utf-8")
    return path


def start(runs: list[RunProcess], tmp_path: Path, experiment: Path, *args: str) -> RunProcess:
    run = RunProcess(tmp_path, experiment, "--no-check", *args)
    runs.append(run)
    return run


def statuses(recording: dict, agent: str) -> list[dict]:
    return recording.get(f"/{agent}/status", [])


def noted_missing(recording: dict, agent: str) -> dict[str, list[int]]:
    """The ticks ``agent`` ran without a neighbour's output, from its status messages."""
    noted: dict[str, list[int]] = {}
    for message in statuses(recording, agent):
        for name, ticks in message.get("inputs_missing", {}).items():
            noted.setdefault(name, []).extend(ticks)
    return noted


def schedule(spy: Spy) -> bus.ScheduleMessage | None:
    """The last schedule the manager sent (``None``: none yet)."""
    with spy._lock:  # the spy keeps the last payload of each key
        payload = spy.last.get(spy._legacy.tick)
    return None if payload is None else bus.decode_schedule(payload)


def y_count(spy: Spy, agent: str) -> int:
    return spy.count(f"hilswarm/toy/agent/{agent}/y")


def last_k(spy: Spy, agent: str) -> int:
    """The tick of ``agent``'s last y (-1 before any)."""
    with spy._lock:
        payload = spy.last.get(f"hilswarm/toy/agent/{agent}/y")
    return -1 if payload is None else bus.decode_vector(payload)[0]


def schedule_last(spy: Spy) -> int:
    found = schedule(spy)
    return -1 if found is None else found.last


def test_self_clocked_run_completes_and_accounts_every_tick(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = shared_clock_experiment(tmp_path / "toy.toml", duration_s=1.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    assert run.wait(60) == 0, run.output()
    recording = read_recording(run.out)
    ticks = recording["/orchestrator/ticks"]
    assert [m["k"] for m in ticks] == list(range(50))  # every tick accounted, once
    # No tick messages: the manager sent schedules only (the start and its repeats).
    first = schedule(spy)
    assert first is not None and (first.first, first.last) == (0, 49)
    assert spy.count("hilswarm/toy/tick") <= 3
    events = [m for m in recording["/orchestrator/status"] if m.get("state") == "schedule"]
    assert len(events) == 1 and events[0]["detail"].startswith("self-clocked: ticks 0..49")
    for name in AGENTS:
        ks = [m["k"] for m in recording[f"/{name}/y"]]
        assert ks == sorted(set(ks)) and ks[-1] == 49, (name, ks)
        last = statuses(recording, name)[-1]
        assert last["state"] == "stopped" and "dropped" not in last, last
        # Each agent left ``armed`` when the schedule came, in the lead before tick 0 (the
        # transition's cost is off tick 0), not on its first tick.
        started = [m for m in statuses(recording, name) if m["state"] == "running"]
        assert [m["detail"] for m in started] == ["schedule received"], started
        # The record says which ticks ran without the neighbour's output: exactly the ticks
        # the toy controller counted (x_hat[0]: ticks with a neighbour's output missing).
        noted = noted_missing(recording, name)
        assert set(noted) <= {HEARS[name]}, noted
        seen_missing = recording[f"/{name}/x_hat"][-1]["values"][0]
        assert seen_missing == sum(len(v) for v in noted.values()), (name, noted)
        assert set(noted.get(HEARS[name], [])) <= set(ks), (name, noted)


def test_self_clocked_ticks_without_a_slow_neighbours_output_are_recorded(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    """b takes 30 ms per 20 ms tick: a (which hears b) runs its ticks on time without b's
    output on many of them, and says which in its status messages; the record matches what
    a's controller saw exactly."""
    experiment = shared_clock_experiment(tmp_path / "toy.toml", duration_s=2.0)
    text = experiment.read_text(encoding="utf-8").replace(
        "[agents.b]\ninitial_state = [1.0]\n",
        "[agents.b]\ninitial_state = [1.0]\nparams = { gain = 2.0, work_s = 0.03 }\n",
    )
    experiment.write_text(text, encoding="utf-8")
    run = start(runs, tmp_path, experiment)
    # b's skipped ticks are late ticks, within the experiment's max_late_fraction (1.0):
    # listed as a note, the run clean
    assert run.wait(60) == 0, run.output()
    assert re.search(
        r"note: ticks skipped by agents that fell behind: b=\d+$", run.output(), re.M
    ), run.output()
    recording = read_recording(run.out)
    ticks = recording["/orchestrator/ticks"]
    assert [m["k"] for m in ticks] == list(range(100))
    noted = noted_missing(recording, "a")
    assert set(noted) == {"b"} and len(noted["b"]) > 10, noted
    assert recording["/a/x_hat"][-1]["values"][0] == len(noted["b"])
    a_ticks = {m["k"] for m in recording["/a/y"]}
    b_late = {m["k"] + 1 for m in ticks if "b" in m["late"]}
    assert set(noted["b"]) <= a_ticks and len(set(noted["b"]) & b_late) > 10
    late_ks = [m["k"] for m in ticks if m["late"]]  # the outcome places the late ticks
    where = f"; between ticks {late_ks[0]} and {late_ks[-1]}); late answers:"
    assert where in run.output(), run.output()


def test_self_clocked_pause_ends_the_schedule_and_resume_re_anchors_it(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = shared_clock_experiment(tmp_path / "toy.toml", duration_s=600.0)
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    wait_for(lambda: min(y_count(spy, n) for n in AGENTS) >= 30, 60, "30 ticks")
    spy.control(bus.ControlCommand.PAUSE, "test pause")
    wait_for(lambda: spy.manager_state() == "paused", 30, "the manager's paused status")
    wait_for(lambda: 0 <= schedule_last(spy) < 29_999, 30, "the schedule's end")
    halted = schedule(spy)
    assert halted is not None and halted.first == 0
    held = halted.last  # the agents run up to this tick, then wait
    wait_for(lambda: all(last_k(spy, n) == held for n in AGENTS), 30, "the ticks up to the end")
    counts = [y_count(spy, n) for n in AGENTS]
    time.sleep(0.5)  # held paused for a while: nothing may move meanwhile
    assert [y_count(spy, n) for n in AGENTS] == counts
    spy.control(bus.ControlCommand.RESUME, "test resume")
    wait_for(lambda: (schedule(spy) or halted).first == held + 1, 30, "the re-anchored schedule")
    resumed = schedule(spy)
    assert resumed is not None and resumed.t0 > halted.t0 and resumed.last == 29_999
    wait_for(lambda: min(y_count(spy, n) for n in AGENTS) >= held + 50, 60, "50 more ticks")
    spy.control(bus.ControlCommand.STOP, "test done")
    assert run.wait(30) == 0, run.output()
    recording = read_recording(run.out)
    ticks = [m["k"] for m in recording["/orchestrator/ticks"]]
    assert ticks == list(range(len(ticks))) and ticks[-1] > held + 40  # each tick once
    for name in AGENTS:
        ks = [m["k"] for m in recording[f"/{name}/y"]]
        assert ks == sorted(set(ks)) and held in ks and held + 1 in ks, name
        assert next(k for k in ks if k > held) == held + 1, name  # no tick lost to the pause
        late = [m["k"] for m in recording["/orchestrator/ticks"] if name in m["late"]]
        assert held not in late and held + 1 not in late, (name, held, late)
        agent_states = [m["state"] for m in statuses(recording, name)]
        assert agent_states[agent_states.index("paused") + 1] == "running", agent_states
    schedules = [m["detail"] for m in recording["/orchestrator/status"] if m["state"] == "schedule"]
    assert [d.split(" due")[0] for d in schedules] == [
        "self-clocked: ticks 0..29999",
        f"self-clocked: ticks 0..{held}",  # the pause
        f"self-clocked: ticks {held + 1}..29999",  # the resume
    ], schedules


def test_self_clocked_killed_agent_is_lost_and_announced(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    experiment = shared_clock_experiment(
        tmp_path / "toy.toml", duration_s=4.0, on_agent_loss="continue"
    )
    run = start(runs, tmp_path, experiment)
    spy = connect_spy(run, "toy")
    spies.append(spy)
    pids = run.remember_agents(4)
    wait_for(lambda: y_count(spy, "b") >= 30, 60, "tick 30")
    genuine = schedule(spy)
    assert genuine is not None and genuine.missing == ()
    os.kill(next(p for p in pids if agent_name_of(p) == "b"), signal.SIGKILL)
    wait_for(lambda: (schedule(spy) or genuine).missing == (1,), 30, "b announced lost")
    assert run.wait(30) == 3, run.output()  # completed, degraded: an agent was lost
    assert "degraded: agent b lost at tick" in run.output(), run.output()
    recording = read_recording(run.out)
    assert statuses(recording, "b")[-1]["state"] == "lost"
    assert recording["/a/y"][-1]["k"] == 199 and recording["/c/y"][-1]["k"] == 199
    ticks = recording["/orchestrator/ticks"]
    assert [m["k"] for m in ticks] == list(range(200))
    assert ticks[-1]["missing"] == ["b"]
    # a hears b: every tick a ran after b died used no data for b; those before the loss was
    # announced are noted in a's statuses, the later ones are the recorded loss.
    k_lost = next(m["k"] for m in statuses(recording, "b") if m["state"] == "lost")
    noted = set(noted_missing(recording, "a").get("b", []))
    after = [m["k"] for m in recording["/a/y"] if m["k"] > k_lost + 2]
    seen_missing = recording["/a/x_hat"][-1]["values"][0]
    assert seen_missing >= len(after) and seen_missing >= len(noted), (seen_missing, noted)
    # once announced lost, b is no longer noted as missing: it is in every tick's "missing"
    assert all(k <= k_lost + 10 for k in noted), (k_lost, sorted(noted))


def test_forged_and_odd_schedules_are_rejected_counted_and_never_fatal(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    """On an ``--insecure`` run (no access control) forged schedules reach the agents: each
    is rejected by the tick engine and counted, and the run keeps its schedule."""
    experiment = shared_clock_experiment(tmp_path / "toy.toml", duration_s=4.0)
    run = start(runs, tmp_path, experiment, "--insecure")
    spy = connect_spy(run, "toy")
    spies.append(spy)
    wait_for(lambda: min(y_count(spy, n) for n in AGENTS) >= 20, 60, "tick 20")
    genuine = schedule(spy)
    assert genuine is not None
    dt = genuine.dt
    forged = [
        bus.ScheduleMessage(0, 199, genuine.t0, 2 * dt),  # another period
        bus.ScheduleMessage(0, 199, genuine.t0 + 3600.0, dt),  # an hour ahead: a freeze
        bus.ScheduleMessage(0, 10**9, genuine.t0 - 3600.0, dt),  # an hour behind: a race
    ]
    payloads = [bus.encode_schedule(m) for m in forged]
    payloads.append(bus.encode_tick(bus.TickMessage(25, 25 * dt, realtime=True)))  # mode
    for payload in payloads:
        spy.session.put(spy.keys.tick, payload, congestion_control=zenoh.CongestionControl.BLOCK)
    assert run.wait(60) == 3, run.output()  # never fatal; the counts make it degraded
    recording = read_recording(run.out)
    ticks = recording["/orchestrator/ticks"]
    assert [m["k"] for m in ticks] == list(range(200))
    for name in AGENTS:
        ks = [m["k"] for m in recording[f"/{name}/y"]]
        assert ks == sorted(set(ks)) and ks[-1] == 199, name  # none beyond the run
        dropped = statuses(recording, name)[-1]["dropped"]
        assert dropped == {"schedule_dt": 1, "schedule_time": 2, "tick_mode": 1}, (name, dropped)
    # the forgeries did not move the schedule: hardly any tick was late after them
    assert sum(1 for m in ticks if m["late"]) < 40


FRAME_S = 0.01  # the demo's mocap frame period [s] (100 Hz)


def phase_spread(times: np.ndarray, period: float) -> float:
    """Half-width of the smallest arc (modulo ``period``) holding 90 % of ``times`` [s]."""
    phases = np.sort(np.mod(times, period))
    n = phases.size
    keep = max(1, int(np.ceil(0.9 * n)))
    wrapped = np.concatenate([phases, phases + period])
    return float(np.min(wrapped[keep - 1 : keep - 1 + n] - wrapped[:n]) / 2)


@pytest.mark.slow
def test_self_clocked_ticks_follow_the_frame_lock(
    tmp_path: Path, runs: list[RunProcess], spies: list[Spy]
) -> None:
    """With ``[mocap]`` the frame lock moves each tick's due time; self-clocked, the manager
    sends the moved schedule and the agents wake on the frame grid (23 Hz ticks, 100 Hz
    frames: a new anchor about every tick)."""
    lag_ms = 2.0
    text = (REPO / "graphs" / "lead_follow_mocap.toml").read_text()
    for old, new in {
        "rate_hz = 20.0": "rate_hz = 23.0",
        'mode = "realtime"': 'mode = "realtime"\nrealtime_clock = "shared"\n'
        "max_late_fraction = 1.0\n#",
        "hold_frames = 50 ": f"tick_lag_ms = {lag_ms}\nhold_frames = 500 ",
        "latency_s = 0.003 ": "latency_s = 0.0 ",
        "dropout_rate = 0.002": "dropout_rate = 0.0",
    }.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    experiment = tmp_path / "experiment.toml"
    experiment.write_text(text)
    run = start(runs, tmp_path, experiment, "--duration", "4")
    spy = connect_spy(run, "lead_follow_mocap")
    spies.append(spy)
    assert run.wait(240) == 0, run.output()
    recording = read_recording(run.out)
    events = [m["detail"] for m in recording["/orchestrator/status"] if m["state"] == "frame_lock"]
    assert events and events[0].startswith("locked"), events
    ticks = recording["/orchestrator/ticks"]
    ks = np.array([m["k"] for m in ticks])
    assert ks.tolist() == list(range(92))
    assert spy.count("hilswarm/lead_follow_mocap/tick") > 20  # schedules as the lock moved
    # Each moved schedule went out once the senses of the tick before its first were over
    # (FrameSchedule.quiet_send_time: a frame after that tick's due time), not into them.
    # The anchor moves by under a frame, so sent at once they would come ~1 ms after that
    # due time; held, a frame (10 ms) and ~1 ms later. (Repeats, the same message, aside.)
    after_due = []
    previous = b""
    for arrived, payload in list(spy.tick_messages):
        if payload != previous and bus.is_schedule(payload):
            moved = bus.decode_schedule(payload)
            if moved.first >= 2:
                after_due.append(arrived - (moved.t0 + (moved.first - 1) * moved.dt))
        previous = payload
    assert len(after_due) > 20, after_due
    assert np.median(after_due) > 0.7 * FRAME_S, np.percentile(after_due, [10, 50, 90])
    scheduled = np.array([m["scheduled_s"] for m in ticks])[10:]
    assert phase_spread(scheduled, FRAME_S) < 0.5e-3, phase_spread(scheduled, FRAME_S)
    for agent in ("leader", "f1", "f2"):  # the agents sensed just after the newest frame
        rows = recording[f"/{agent}/telemetry/mocap"]
        latency = np.array([r["latency_s"] for r in rows if r["k"] >= 10])
        latency = latency[np.isfinite(latency)]
        assert latency.size > 60, (agent, latency.size)
        since_frame = np.mod(latency, FRAME_S)
        window = (since_frame >= lag_ms * 1e-3 - 1e-3) & (since_frame < lag_ms * 1e-3 + 3e-3)
        assert np.mean(window) > 0.6, (agent, np.percentile(since_frame, [10, 50, 90]))
        assert np.median(latency) < FRAME_S, agent

"""Pose latency: simulator frame time to the controller's use, in a real ``hilswarm run``.

What is measured (issue 11 item 9): for each mocap frame rate, a real experiment is run with
``hilswarm run`` exactly as a user runs one: N Frisbee bots on simulated boards (``sim://``)
in a lead/follow chain, ``[mocap] system = "sim"``, so the run starts the protocol-level
Qualisys simulator (Qualisys RT over TCP on loopback, fed by the agents' true plant poses) and
the mocap process with the real client library (qtm-rt, Kalman filter, one message per body
on the bus); one process per agent, each receiving its own body; the instance manager ticking
on the wall clock; the recorder writing an MCAP file. The benchmark then reads, from that
file, what every agent recorded on every tick: ``/<agent>/telemetry/mocap`` ``latency_s``,
**frame time to the sense that feeds the controller** (the pose in ``y_k``; the controller
steps on ``y_k`` at the next tick, ``u_{k+1} = f(y_k)``, one control period later, which is not
counted). p50/p99 are over every tick of every agent after a warm-up.

Clocks: the frame time is the simulator's camera time stamp, read from CLOCK_MONOTONIC
(``time.monotonic_ns``) when it builds the frame; the sense time is the agent's
``time.monotonic()`` (CLOCK_MONOTONIC) when its vehicle senses. Both are this machine's one
CLOCK_MONOTONIC (system-wide on Linux), so the difference needs no clock synchronisation.
With a real mocap system the frame time is the frame's arrival at the mocap process instead
(docs/mocap.md), so the same figure there leaves out the system's own latency.

The latency includes the pose's wait in the agent until its next tick. By default the run's
ticks are locked to the frames (``[mocap] tick_lock``: each tick a lag after a frame,
docs/mocap.md), so that wait is the lag and the tick's way to the agent; ``--free`` runs them free
of the frames (``tick_lock = false``, as before that existed): the cameras and the control loop
then run on independent clocks, so the pose a tick uses is the newest that arrived before it,
on average half a frame period older than a pose used the instant it arrived. ``within_frame``
is the fraction of ticks whose pose was less than one frame period old, i.e. ticks that used
the newest frame the cameras had taken. With free ticks at evenly spread phases of the frame
period, a tick misses the newest frame exactly when it comes less than the delivery time after
that frame, so ``delivery_mean_ms`` = frame period x (1 - ``within_frame``) estimates the mean
delivery frame time -> pose stored in the agent (valid while deliveries stay under one frame
period; free ticks only, ``null`` when locked). The control rate (default 23 Hz) is chosen so
that the ticks sample every phase of the frame period evenly: the figures cover every phase,
not the one phase that chance set at start (as a control rate dividing the frame rate, e.g.
20 Hz, would).

Also measured (unless ``--no-subscriber``), and labelled "subscriber": the same simulator and
mocap process with no run and no agent, and one subscription per body in this benchmark's
process decoding each pose message as an agent's pose source does: frame time -> a bus
subscriber's decoded pose, the bus delivery alone (no wait for a tick), paired with the
baseline frame time -> the client library in the mocap process (the TCP hop and qtm-rt,
carried in every message). Target: p99 under one frame period, for 16 bodies at 100 and
240 Hz.

    python benchmarks/mocap_latency.py            # 16 agents, 100 and 240 Hz, 10 s each
    python benchmarks/mocap_latency.py --short    # CI size: 4 agents, 2 s per rate (< 60 s)
    python benchmarks/mocap_latency.py --free     # ticks free of the frames, for comparison
    python benchmarks/mocap_latency.py --rates 240 --agents 4 8 16   # by agents per core
    python benchmarks/mocap_latency.py --spread   # the ticks spread over the frames, as
                                                  # docs/mocap.md gives it for many agents
    python benchmarks/mocap_latency.py --settle-load 1   # each rate begun on a quiet machine

Prints the 1-minute load at the start, one line per rate with the verdict, and one JSON line
per rate (``{"rate_hz": ...}``; keys in docs/mocap.md, "Benchmark"); exit status 0 when every
run recorded figures (the lead judges them on a quiet machine), 1 when a run recorded none.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import resource
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.agents.mocap import message
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.orchestrator.checks import fitting_spread
from swarm_ticks import settle

EXPERIMENT = "mocap_latency"
#: What the p50/p99 figures are.
MEASURED = "mocap frame time to the controller's use (an agent's sense), per tick, hilswarm run"
#: What the subscriber figures are (no run, no agent).
SUBSCRIBER = "mocap frame time to a bus subscriber's decoded pose (no agent)"
START_TIMEOUT_S = 30.0
#: Bound on one ``hilswarm run`` beyond its duration (start-up, shutdown, recording) [s].
RUN_SLACK_S = 180.0
#: The agents' control rate [Hz]: near the demo's 20 Hz, but not a divisor of 100 or 240 Hz,
#: so successive ticks fall at every phase of the frame period (23 phases, evenly spread). At
#: 20 Hz every tick of a run would meet the frames at one phase, set by chance at start, and
#: the figures would measure that one phase.
CONTROL_RATE_HZ = 23.0
#: Ticks before this experiment time are the warm-up, not measured [s].
WARMUP_S = 1.0
#: The mocap system's hold: a body unseen this long puts its agent safe [s]; generous, so a
#: busy machine shows as latency rather than as a stopped run.
HOLD_S = 1.0


def load_1min() -> float:
    """The 1-minute load average now."""
    return round(os.getloadavg()[0], 2)


def percentile_ms(values: np.ndarray, q: float) -> float | None:
    """The ``q``-th percentile of ``values`` [s] in ms (``None`` when empty)."""
    return round(float(np.percentile(values, q)) * 1e3, 3) if values.size else None


# -- frame time to the controller: a real run -------------------------------------------------


def experiment_text(*, agents: int, mocap_rate_hz: float, control_rate_hz: float,
                    seconds: float, locked: bool = True, lag_ms: float | None = None,
                    pose_wait_ms: float | None = None, tick_frames_only: bool = False,
                    tick_spread: int = 1) -> str:  # fmt: skip
    """The experiment: ``agents`` Frisbee bots in a lead/follow chain, poses from ``sim``.

    Agent ``a00`` drives a 1 m square of waypoints; agent ``aNN`` follows ``a(NN-1)`` at 0.3 m
    (the demo ``graphs/lead_follow_mocap.toml``, longer). Camera noise as in the demo, no
    simulated camera latency and no dropouts: the figures are the software path's. ``locked``:
    the ticks in step with the frames (``[mocap] tick_lock``, the default), ``lag_ms`` its
    ``tick_lag_ms``, ``pose_wait_ms`` the agents' ``pose_wait_ms`` (``None``: the defaults),
    ``tick_frames_only`` the mocap process's ``tick_frames_only``, ``tick_spread`` the
    ticks' ``tick_spread_frames``.
    """
    names = [f"a{i:02d}" for i in range(agents)]
    rows = [[1 if j == i - 1 else 0 for j in range(agents)] for i in range(agents)]
    hold_frames = max(1, round(HOLD_S * mocap_rate_hz))
    lines = [
        "[experiment]",
        f'name = "{EXPERIMENT}"',
        f"rate_hz = {control_rate_hz!r}",
        f"duration_s = {seconds!r}",
        'mode = "realtime"',
        'on_agent_loss = "continue"',
        'on_agent_safe = "continue"',
        "seed = 7",
        "",
        "[mocap]",
        'system = "sim"',
        f"rate_hz = {mocap_rate_hz!r}",
        f"hold_frames = {hold_frames}",
        "start_timeout_s = 30.0",
        f"tick_lock = {'true' if locked else 'false'}",
        *([] if lag_ms is None else [f"tick_lag_ms = {lag_ms!r}"]),
        *([] if pose_wait_ms is None else [f"pose_wait_ms = {pose_wait_ms!r}"]),
        *(["tick_frames_only = true"] if tick_frames_only else []),
        *([f"tick_spread_frames = {tick_spread}"] if tick_spread > 1 else []),
        "",
        "[mocap.sim]",
        "noise_std_m = 0.002",
        "noise_std_rad = 0.01",
        "latency_s = 0.0",
        "dropout_rate = 0.0",
        "",
        "[graph]",
        "agents = [" + ", ".join(f'"{n}"' for n in names) + "]",
        "adjacency = [" + ",\n  ".join(str(row) for row in rows) + "]",
        "",
        "[defaults]",
        'vehicle = "frisbee"',
        'link = "sim://"',
        "",
    ]
    for i, name in enumerate(names):
        lines.append(f"[agents.{name}]")
        lines.append(f"initial_state = [{-0.3 * i!r}, 0.0, 0.0]")
        if i == 0:
            lines += [
                'controller = "waypoint"',
                "params = { waypoints = [[1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.0]], "
                'mode = "pi", kp = 1.0, ki = 0.2 }',
            ]
        else:
            lines += [
                'controller = "follower"',
                f'params = {{ leader = "{names[i - 1]}", distance_m = 0.3, lateral_m = 0.0 }}',
            ]
        lines.append("")
    return "\n".join(lines)


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (by parent pid, from /proc)."""
    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rpartition(")")[2].split()[1])
        parents.setdefault(ppid, []).append(int(entry))
    found, todo = [], [pid]
    while todo and len(found) < 10_000:
        for child in parents.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def children_cpu_s() -> float:
    """CPU time [s] (user + system) of this process's waited-for descendants so far: after a
    ``hilswarm run`` ends, its own and that of every process it started and reaped (agents,
    mocap process and simulator, recorder)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_experiment(folder: Path, experiment: Path, seconds: float) -> tuple[int, Path, str]:
    """``hilswarm run experiment`` in its own process group (own run registry in ``folder``);
    returns its exit status, the recording and the tail of its output. Killed (with every
    process it started) if it outlives its duration by :data:`RUN_SLACK_S`."""
    runtime = folder / "xdg"
    runtime.mkdir(mode=0o700, exist_ok=True)
    out = folder / "run.mcap"
    log = folder / "run.log"
    env = {**os.environ, "XDG_RUNTIME_DIR": str(runtime)}
    command = [sys.executable, "-m", "hilswarm.orchestrator.cli", "run", str(experiment),
               "--out", str(out), "--force"]  # fmt: skip
    with log.open("wb") as output:
        process = subprocess.Popen(
            command, cwd=folder, env=env, stdin=subprocess.DEVNULL, stdout=output,
            stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        try:
            status = process.wait(timeout=seconds + RUN_SLACK_S)
        except subprocess.TimeoutExpired:
            for pid in [*descendants(process.pid), process.pid]:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(pid, signal.SIGKILL)  # agents run in process groups of their own
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.kill(pid, signal.SIGKILL)
            process.wait(10.0)
            status = -signal.SIGKILL
    tail = "\n".join(log.read_text(errors="replace").splitlines()[-15:])
    return status, out, tail


def controller_latencies(out: Path, agents: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """From the recording, for every tick at or after :data:`WARMUP_S` with a pose:
    ``latency_s`` [s] (frame time -> the sense) and ``delivery_s`` [s] (frame time -> the pose's
    arrival at the agent); the number of such ticks, and how many had none (NaN: lost)."""
    topics = [f"/a{i:02d}/telemetry/mocap" for i in range(agents)]
    values: list[float] = []
    deliveries: list[float] = []
    ticks = 0
    if out.exists():
        for _topic, _time, row in iter_messages(out, topics):
            if row.get("t") is None or row["t"] < WARMUP_S:
                continue
            ticks += 1
            latency = row.get("latency_s")
            if latency is not None and math.isfinite(latency):
                values.append(latency)
                delivery = row.get("delivery_s")
                if delivery is not None and math.isfinite(delivery):
                    deliveries.append(delivery)
    return np.array(values), np.array(deliveries), ticks, ticks - len(values)


def ticks_locked(out: Path) -> float | None:
    """Fraction of the run's ticks the manager released locked to the frames (its last
    ``frame_lock`` record on ``/orchestrator/status``); ``None``: no record."""
    last = None
    if out.exists():
        for _topic, _time, row in iter_messages(out, ["/orchestrator/status"]):
            if row.get("state") == "frame_lock":
                last = str(row.get("detail", ""))
    found = re.search(r"ticks locked (\d+), free (\d+)", last or "")
    if found is None:
        return None
    locked, free = int(found[1]), int(found[2])
    return round(locked / (locked + free), 4) if locked + free else None


def measure_controller(rate_hz: float, agents: int, seconds: float, control_rate_hz: float,
                       *, locked: bool = True, lag_ms: float | None = None,
                       pose_wait_ms: float | None = None, tick_frames_only: bool = False,
                       tick_spread: int = 1) -> dict[str, Any]:  # fmt: skip
    """One ``hilswarm run`` at mocap rate ``rate_hz``: frame time -> controller figures."""
    load = load_1min()
    with tempfile.TemporaryDirectory(prefix="mocap_latency-") as tmp:
        folder = Path(tmp)
        experiment = folder / "experiment.toml"
        experiment.write_text(
            experiment_text(agents=agents, mocap_rate_hz=rate_hz,
                            control_rate_hz=control_rate_hz, seconds=WARMUP_S + seconds,
                            locked=locked, lag_ms=lag_ms, pose_wait_ms=pose_wait_ms,
                            tick_frames_only=tick_frames_only, tick_spread=tick_spread)
        )  # fmt: skip
        began = time.monotonic()
        cpu_before = children_cpu_s()
        status, out, tail = run_experiment(folder, experiment, WARMUP_S + seconds)
        wall = time.monotonic() - began
        cpu = children_cpu_s() - cpu_before
        latency, delivery, ticks, lost = controller_latencies(out, agents)
        locked_fraction = ticks_locked(out)
    period = 1.0 / rate_hz
    settings = MocapSettings(
        system="sim", rate_hz=rate_hz, tick_lock=locked, tick_lag_ms=lag_ms,
        pose_wait_ms=pose_wait_ms,
    )  # fmt: skip
    p99 = percentile_ms(latency, 99)
    within = round(float(np.mean(latency < period)), 4) if latency.size else None
    expected = round(agents * control_rate_hz * seconds)
    return {
        "measured": MEASURED,
        "rate_hz": rate_hz,
        "bodies": agents,
        "seconds": seconds,
        "poses": int(latency.size),
        "delivered": round(latency.size / expected, 3) if expected else 0.0,
        "p50_ms": percentile_ms(latency, 50),
        "p99_ms": p99,
        "target_p99_ms": round(period * 1e3, 3),
        "agents": agents,
        "control_rate_hz": control_rate_hz,
        "ticks": ticks,
        "ticks_without_pose": lost,
        "min_ms": round(float(latency.min()) * 1e3, 3) if latency.size else None,
        "max_ms": round(float(latency.max()) * 1e3, 3) if latency.size else None,
        "within_frame": within,
        # the estimate assumes ticks at every phase of the frames: free ticks only
        "delivery_mean_ms": None
        if within is None or locked
        else round((1.0 - within) * period * 1e3, 3),
        "delivery_p50_ms": percentile_ms(delivery, 50),
        "delivery_p99_ms": percentile_ms(delivery, 99),
        "meets_target": p99 is not None and p99 < period * 1e3,
        "locked": locked,
        "tick_lag_ms": round(settings.tick_lag_s * 1e3, 3) if locked else None,
        "ticks_locked": locked_fraction,
        "pose_wait_ms": round(settings.pose_wait_s * 1e3, 3),
        "tick_frames_only": tick_frames_only,
        "tick_spread_frames": tick_spread,
        "run_cpu_s": round(cpu, 2),
        "load_1min": load,
        "run_exit": status,
        "run_wall_s": round(wall, 1),
        "_tail": tail,
    }


# -- frame time to a bus subscriber: the mocap path alone ---------------------------------------


def start(command: list[str], *, pipe: bool = False) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", *command],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE if pipe else subprocess.DEVNULL,
        start_new_session=True,
    )


def read_port(process: subprocess.Popen[bytes]) -> int:
    deadline = time.monotonic() + START_TIMEOUT_S
    line = b""
    while not line.endswith(b"\n"):
        if time.monotonic() > deadline or process.poll() is not None:
            raise RuntimeError("the simulator did not start")
        ready, _, _ = select.select([process.stdout], [], [], 0.2)
        if ready:
            line += os.read(process.stdout.fileno(), 64)  # type: ignore[union-attr]
    return int(line.split()[1])


def stop(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
    try:
        process.wait(5.0)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(5.0)


def measure_subscriber(rate_hz: float, n_bodies: int, seconds: float) -> dict[str, Any]:
    """The mocap path alone at ``rate_hz``: latencies [s] frame time -> a bus subscriber's
    decoded pose (in this process) and frame time -> the client library (the baseline)."""
    router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
    endpoints = bus.bound_endpoints(router)  # the free port the router bound
    bodies = [f"b{i:02d}" for i in range(n_bodies)]
    settings = MocapSettings(system="sim", rate_hz=rate_hz, hold_frames=10)
    common = ["--experiment", EXPERIMENT, "--bodies", ",".join(bodies), "--connect",
              endpoints[0], "--settings", json.dumps(settings.to_dict())]  # fmt: skip
    keys = bus.BusKeys(EXPERIMENT)
    end_to_end: list[float] = []
    at_client: list[float] = []
    lock = threading.Lock()
    recording = threading.Event()

    def on_pose(sample: zenoh.Sample) -> None:
        now = time.monotonic()
        pose = message.decode(sample.payload.to_bytes())
        if recording.is_set():
            with lock:
                end_to_end.append(pose.latency_s(now))
                at_client.append(pose.source_latency_s)

    entities: list[Any] = []
    sim = start(["hilswarm.agents.mocap.sim_process", *common], pipe=True)
    mocap = None
    try:
        port = read_port(sim)
        for i, body in enumerate(bodies):
            entities.append(router.declare_subscriber(keys.mocap(body), on_pose))
            router.put(keys.mocap_truth(body), message.encode_truth(np.array([i, 0, 0, 0, 0, 0.0])))
        mocap = start(["hilswarm.agents.mocap.process", *common, "--port", str(port)])
        time.sleep(1.0)  # a benchmark's warm-up (connection, first frames), not a synchronisation
        for i, body in enumerate(bodies):  # again, in case the simulator subscribed late
            router.put(keys.mocap_truth(body), message.encode_truth(np.array([i, 0, 0, 0, 0, 0.0])))
        recording.set()
        time.sleep(seconds)
        recording.clear()
    finally:
        if mocap is not None:
            stop(mocap)
        stop(sim)
        entities.clear()
        router.close()
    e2e, client = np.array(end_to_end), np.array(at_client)
    expected = rate_hz * seconds * n_bodies
    return {
        "subscriber_p50_ms": percentile_ms(e2e, 50),
        "subscriber_p99_ms": percentile_ms(e2e, 99),
        "subscriber_delivered": round(e2e.size / expected, 3) if expected else 0.0,
        "baseline_p50_ms": percentile_ms(client, 50),
        "baseline_p99_ms": percentile_ms(client, 99),
    }


#: ``--spread`` at the rates where it was measured: ``tick_lag_ms``, ``pose_wait_ms`` [ms]
#: (docs/mocap.md, "Ticks spread over the frames"); other rates: :data:`SPREAD_LAG_MS` and
#: :data:`SPREAD_WAIT_FRAMES` of a frame period.
SPREAD_MEASURED = {240.0: (0.25, 4.0), 100.0: (0.5, 8.5)}
SPREAD_LAG_MS = 0.25
SPREAD_WAIT_FRAMES = 0.95


def spread_settings(
    rate_hz: float, control_rate_hz: float, agents: int
) -> tuple[int, float, float]:
    """``--spread``: ``(tick_spread_frames, tick_lag_ms, pose_wait_ms)`` for ``agents`` at a
    mocap rate ``rate_hz`` and control rate ``control_rate_hz`` [Hz]: as many frames as leave
    the last phase a fifth of the control period to answer (what ``hilswarm check`` asks for
    without a warning), at most one per agent; the lag and the wait measured best there."""
    spread = max(1, min(agents, fitting_spread(rate_hz, control_rate_hz)))
    lag_ms, wait_ms = SPREAD_MEASURED.get(
        rate_hz, (SPREAD_LAG_MS, SPREAD_WAIT_FRAMES * 1e3 / rate_hz)
    )
    return spread, lag_ms, wait_ms


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=f"mocap pose latency: {MEASURED}")
    parser.add_argument("--short", action="store_true", help="CI size: 4 agents, 2 s per rate")
    parser.add_argument(
        "--agents",
        "--bodies",
        type=int,
        nargs="+",
        default=None,
        dest="agents",
        help="agents, one rigid body each; several: each count in turn (default 16; --short 4)",
    )
    parser.add_argument(
        "--rates",
        type=float,
        nargs="+",
        default=[100.0, 240.0],
        help="mocap frame rates [Hz] (default 100 240)",
    )
    parser.add_argument(
        "--seconds",
        type=float,
        default=None,
        help="measured time per rate [s] (default 10; --short 2)",
    )
    parser.add_argument(
        "--control-rate",
        type=float,
        default=CONTROL_RATE_HZ,
        help=f"the agents' control rate [Hz] (default {CONTROL_RATE_HZ:g})",
    )
    parser.add_argument(
        "--free",
        action="store_true",
        help="ticks free of the frames ([mocap] tick_lock = false; before this version)",
    )
    parser.add_argument(
        "--lag-ms",
        type=float,
        default=None,
        help="[mocap] tick_lag_ms of the locked ticks (default: the experiment default)",
    )
    parser.add_argument(
        "--pose-wait-ms",
        type=float,
        default=None,
        help="[mocap] pose_wait_ms of the agents (default: the experiment default; 0: no wait)",
    )
    parser.add_argument(
        "--tick-frames-only",
        action="store_true",
        help="[mocap] tick_frames_only = true: only the poses of the frames the ticks use",
    )
    parser.add_argument(
        "--tick-spread",
        type=int,
        default=None,
        metavar="N",
        help="[mocap] tick_spread_frames: the agents' ticks spread over N frames (default 1: "
        "all at once); e.g. --tick-spread 8 --lag-ms 0.25 --pose-wait-ms 4 at 240 Hz",
    )
    parser.add_argument(
        "--spread",
        action="store_true",
        help="the ticks spread over the frames with the lag and wait measured best for them, "
        "per rate (240 Hz, 23 Hz control: --tick-spread 8 --lag-ms 0.25 --pose-wait-ms 4; "
        "100 Hz: 3, 0.5, 8.5); explicit --tick-spread/--lag-ms/--pose-wait-ms win",
    )
    parser.add_argument(
        "--settle-load",
        type=float,
        metavar="LOAD",
        help="before each rate's run, wait (up to 4 min) until the 1-minute load average is "
        "below LOAD (the previous run's processes raise it)",
    )
    parser.add_argument(
        "--no-subscriber",
        action="store_true",
        help="skip the subscriber-level figure (mocap path without a run)",
    )
    args = parser.parse_args(argv)
    seconds = args.seconds if args.seconds is not None else (2.0 if args.short else 10.0)
    counts = args.agents if args.agents is not None else [4 if args.short else 16]
    if any(n < 1 for n in counts):
        parser.error(f"--agents must be >= 1, got {counts}")
    if args.tick_spread is not None and args.tick_spread < 1:
        parser.error(f"--tick-spread must be >= 1 [frames], got {args.tick_spread}")
    one, five, fifteen = os.getloadavg()
    print(f"load at start: {one:.2f} {five:.2f} {fifteen:.2f} (1/5/15 min), "
          f"{os.cpu_count()} cores; latency on CLOCK_MONOTONIC (the simulator's frame time "
          f"stamp and the agent's sense, one machine clock)")  # fmt: skip
    failed = False
    if args.spread and (args.free or args.tick_frames_only):
        parser.error("--spread needs locked ticks and every frame (not --free, --tick-frames-only)")
    for agents, rate in ((n, r) for n in counts for r in args.rates):
        spread, lag_ms, wait_ms = args.tick_spread or 1, args.lag_ms, args.pose_wait_ms
        if args.spread:  # what is given explicitly wins
            best = spread_settings(rate, args.control_rate, agents)
            spread = best[0] if args.tick_spread is None else args.tick_spread
            lag_ms = best[1] if lag_ms is None else lag_ms
            wait_ms = best[2] if wait_ms is None else wait_ms
        settle(args.settle_load)
        result = measure_controller(
            rate, agents, seconds, args.control_rate, locked=not args.free, lag_ms=lag_ms,
            pose_wait_ms=wait_ms, tick_frames_only=args.tick_frames_only, tick_spread=spread,
        )  # fmt: skip
        tail = result.pop("_tail")
        subscriber: dict[str, Any] = {
            "subscriber_p50_ms": None, "subscriber_p99_ms": None, "subscriber_delivered": None,
            "baseline_p50_ms": None, "baseline_p99_ms": None,
        }  # fmt: skip
        if not args.no_subscriber:
            subscriber = measure_subscriber(rate, agents, seconds)
        result.update(subscriber)
        verdict = "meets" if result["meets_target"] else "MISSES"
        within = result["within_frame"]
        print(
            f"{agents} agents at {rate:g} Hz mocap, {args.control_rate:g} Hz control "
            f"(load {result['load_1min']:.2f}, hilswarm run exit {result['run_exit']}): frame "
            f"time -> controller p50 {result['p50_ms']} ms, p99 {result['p99_ms']} ms, max "
            f"{result['max_ms']} ms over {result['poses']} ticks with a pose "
            f"({result['ticks_without_pose']} without); "
            f"{'-' if within is None else f'{within * 100:.1f}%'} of ticks used a pose under "
            f"one frame old (mean delivery to the agent, estimated from it: "
            f"{result['delivery_mean_ms']} ms); {verdict} the target p99 < "
            f"{result['target_p99_ms']} ms; "
            + (
                f"ticks locked to the frames ({result['ticks_locked']} of them), lag "
                f"{result['tick_lag_ms']} ms, pose wait at most {result['pose_wait_ms']} ms"
                + (f", spread over {spread} frames" if spread > 1 else "")
                if result["locked"]
                else "ticks free of the frames"
            )
        )
        print(
            f"  of which the delivery, frame time -> the pose's arrival at the agent (recorded): "
            f"p50 {result['delivery_p50_ms']} ms, p99 {result['delivery_p99_ms']} ms"
        )
        print(
            f"  CPU of the run and every process it started: {result['run_cpu_s']} s in "
            f"{result['run_wall_s']} s; poses of "
            + ("the frames the ticks use" if args.tick_frames_only else "every frame on the bus")
        )
        if not args.no_subscriber:
            print(
                f"  subscriber (no run, no agent): frame time -> decoded pose p50 "
                f"{result['subscriber_p50_ms']} ms, p99 {result['subscriber_p99_ms']} ms, "
                f"{(result['subscriber_delivered'] or 0) * 100:.1f}% delivered; baseline frame "
                f"time -> client library p50 {result['baseline_p50_ms']} ms, p99 "
                f"{result['baseline_p99_ms']} ms"
            )
        if not result["poses"]:
            failed = True
            print(f"  the run recorded no pose; its output ended with:\n{tail}")
        print(json.dumps(result))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

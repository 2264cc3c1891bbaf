"""Pose latency: mocap frame to a bus subscriber's decoded pose.

What is measured: the mocap path with real processes up to the bus: the protocol-level
simulator (Qualisys RT over TCP on loopback, ``hilswarm.agents.mocap.sim_process``), the mocap
process with the real client library (qtm-rt) filtering and publishing every body
(``hilswarm.agents.mocap.process``), a Zenoh router, and **in this benchmark process** one
explicit subscription per body (on the router's own session) that decodes each pose message
as an agent's pose source does. Latency is the frame's camera time (this host's
CLOCK_MONOTONIC, stamped by the simulator) to the moment that subscriber has decoded the pose.

What is not measured: no agent process, no pose source's lost/hold checks, no tick and no
controller. The pose's wait in an agent until its next tick's sense (up to a control period)
and the agent's own bus hop are not included; a run records that latency per tick
(``/<agent>/telemetry/mocap`` ``latency_s``, frame time to the sense that feeds the
controller).

Paired baseline: frame time -> arrival at the client library in the mocap process (the TCP
hop and qtm-rt alone, carried in every message); the difference is the filter, the bus and
the decoding subscriber. Target: p99 under one frame period, for 16 bodies at 100 and
240 Hz.

    python benchmarks/mocap_latency.py            # 16 bodies, 100 and 240 Hz, 10 s each
    python benchmarks/mocap_latency.py --short    # CI size (about 3 s per rate)

Prints one line per rate and a JSON line per rate (``{"rate_hz": ...}``) for tools; exit
status 0 (figures only: the lead judges them on a quiet machine).
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.mocap import message
from hilswarm.agents.mocap.config import MocapSettings

EXPERIMENT = "mocap_latency"
#: What the p50/p99 figures are (the benchmark stops at a subscriber, not at an agent).
MEASURED = "mocap frame to a bus subscriber's decoded pose"
START_TIMEOUT_S = 30.0


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


def measure(rate_hz: float, n_bodies: int, seconds: float) -> dict[str, Any]:
    """One run at ``rate_hz``: latencies [s] frame time -> a bus subscriber's decoded pose (in
    this process) and frame time -> the client library."""
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
        "measured": MEASURED,
        "rate_hz": rate_hz,
        "bodies": n_bodies,
        "seconds": seconds,
        "poses": int(e2e.size),
        "delivered": round(e2e.size / expected, 3) if expected else 0.0,
        "p50_ms": round(float(np.percentile(e2e, 50)) * 1e3, 3) if e2e.size else None,
        "p99_ms": round(float(np.percentile(e2e, 99)) * 1e3, 3) if e2e.size else None,
        "baseline_p50_ms": round(float(np.percentile(client, 50)) * 1e3, 3)
        if client.size
        else None,
        "baseline_p99_ms": round(float(np.percentile(client, 99)) * 1e3, 3)
        if client.size
        else None,
        "target_p99_ms": round(1e3 / rate_hz, 3),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=f"mocap pose latency: {MEASURED}")
    parser.add_argument("--short", action="store_true", help="CI size (about 3 s per rate)")
    parser.add_argument("--bodies", type=int, default=16, help="rigid bodies (default 16)")
    parser.add_argument("--rates", type=float, nargs="+", default=[100.0, 240.0])
    parser.add_argument("--seconds", type=float, default=None, help="measured time per rate")
    args = parser.parse_args(argv)
    seconds = args.seconds if args.seconds is not None else (2.0 if args.short else 10.0)
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f} "
          f"(1/5/15 min), {os.cpu_count()} cores")  # fmt: skip
    for rate in args.rates:
        result = measure(rate, args.bodies, seconds)
        verdict = (
            "meets" if result["p99_ms"] is not None and result["p99_ms"] < result["target_p99_ms"]
            else "MISSES"
        )  # fmt: skip
        print(
            f"{result['bodies']} bodies at {rate:g} Hz: {MEASURED} (no agent process): p50 "
            f"{result['p50_ms']} ms, p99 {result['p99_ms']} ms (baseline, frame time -> client "
            f"library: p50 {result['baseline_p50_ms']} ms, p99 {result['baseline_p99_ms']} ms); "
            f"{result['delivered'] * 100:.1f}% of poses delivered; {verdict} the target p99 < "
            f"{result['target_p99_ms']} ms"
        )
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

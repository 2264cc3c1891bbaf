"""What a recorder subscribed to the bus would cost the manager's process (the recorder choice).

The recorder could be an ordinary subscriber of the experiment's bus instead of a process fed
by the manager through a pipe. This measures the price of that on the manager's side, where
the run's router lives: a router session (the manager) subscribed to every agent's ``y``,
publishers in another process putting ``n`` agents' ``y`` (64 bytes, the tick path's QoS) at
``rate`` Hz, and, paired in the same run, a second client process subscribed to the same keys
(the recorder as a bus subscriber). Figures: CPU of the manager's process per published message
without and with the subscribing recorder (the router's extra routing), and what the pipe
path costs the manager per message instead: the record stream (MCAP, foxglove-sdk writer),
``RecordWriter.y`` per message + ``take()`` + ``RecorderProcess.write`` per batch of 20 ms
amortised, measured in-process on the same payloads.

    python benchmarks/recorder_choice.py            # 64 agents at 100 Hz, 5 s per figure
    python benchmarks/recorder_choice.py --short    # 2 s per figure
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh
from hilswarm.agents import bus, bus_callback

#: A Frisbee bot's y (k, t, x, y, psi), as the agents publish it.
PAYLOAD = bus.encode_vector(0, 0.0, [0.0, 0.0, 0.0])


def publisher(endpoint: str, n: int, rate: float, seconds: float) -> None:
    """Child: ``n`` keys put at ``rate`` Hz for ``seconds``."""
    session = bus.open_session(bus.client_config([endpoint]))
    pubs = [session.declare_publisher(f"bench/a{i}/y", **bus.TICK_PATH_QOS) for i in range(n)]
    time.sleep(1.0)  # subscriptions propagate
    start = time.perf_counter()
    k = 0
    while time.perf_counter() - start < seconds:
        for pub in pubs:
            pub.put(PAYLOAD)
        k += 1
        delay = start + k / rate - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    session.close()


def subscriber(endpoint: str, seconds: float) -> None:
    """Child: the recorder as a bus subscriber (counts what it receives)."""
    session = bus.open_session(bus.client_config([endpoint]))
    count = [0]

    def on_sample(_sample: zenoh.Sample) -> None:
        count[0] += 1

    keep = session.declare_subscriber("bench/*/y", zenoh.handlers.Callback(on_sample))
    time.sleep(seconds + 3.0)
    del keep
    session.close()
    print(count[0])


def cpu_s() -> float:
    """CPU of this process, every thread (Zenoh's too) [s]."""
    return time.process_time()


def manager_figure(n: int, rate: float, seconds: float, *, with_recorder: bool) -> float:
    """CPU [µs] of the manager's process per message, with or without a subscribing recorder."""
    session = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
    endpoint = bus.bound_endpoints(session)[0]  # the free port the router bound
    received = [0]

    def on_y(_sample: zenoh.Sample) -> None:
        received[0] += 1

    keep = session.declare_subscriber("bench/*/y", bus_callback.callback(on_y))
    me = [sys.executable, __file__]
    children = []
    if with_recorder:
        children.append(
            subprocess.Popen(
                [*me, "--child", "sub", endpoint, str(seconds)], stdout=subprocess.PIPE, text=True
            )
        )
        time.sleep(1.0)
    pub = subprocess.Popen([*me, "--child", "pub", endpoint, str(n), str(rate), str(seconds)])
    time.sleep(1.0)
    before, count0 = cpu_s(), received[0]
    pub.wait(timeout=seconds + 60)
    used, count = cpu_s() - before, received[0] - count0
    for child in children:
        child.wait(timeout=seconds + 60)
    del keep
    session.close()
    return 1e6 * used / max(count, 1)


def pipe_figure(n: int, ticks: int) -> float:
    """CPU [µs] per message of the manager's pipe path: ``RecordWriter.y``, ``take()``,
    ``RecorderProcess.write``."""
    from hilswarm.orchestrator.experiment import load_experiment  # noqa: PLC0415
    from hilswarm.orchestrator.record_stream import RecordWriter, hand_over  # noqa: PLC0415
    from hilswarm.orchestrator.recorder_process import RecorderProcess  # noqa: PLC0415

    graphs = Path(__file__).resolve().parents[1] / "graphs"
    experiment = load_experiment(graphs / "lead_follow.toml", overrides={"duration_s": 1.0})
    payload = PAYLOAD
    with tempfile.TemporaryDirectory() as tmp:
        process = RecorderProcess(Path(tmp) / "run.mcap", experiment, log_time_ns=0)
        try:
            process.wait_ready()
            writer = RecordWriter(experiment.agent_names)
            agents = len(writer.names)
            first = 0
            start = cpu_s()
            for k in range(ticks):
                for i in range(n):
                    writer.y(i % agents, time.time_ns(), payload, b"")
                if k % 2:
                    batch = writer.take(time.time_ns())
                    if batch is not None:
                        hand_over(process, batch, tick=k, first_tick=first)
                    first = k + 1
            used = cpu_s() - start
            # the end of the stream (not timed: once per run)
            batch = writer.close(time.time_ns())
            process.write(
                batch.data,
                seq=batch.seq,
                count=batch.count,
                tick=ticks - 1,
                first_tick=first,
                defines=batch.defines,
            )
        finally:
            code = process.close()
    if code != 0:
        raise SystemExit(f"the recorder process exited with status {code}")
    return 1e6 * used / (n * ticks)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--short", action="store_true", help="2 s per figure")
    parser.add_argument("--agents", type=int, default=64)
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        kind, endpoint, *rest = args.child
        if kind == "pub":
            publisher(endpoint, int(rest[0]), float(rest[1]), float(rest[2]))
        else:
            subscriber(endpoint, float(rest[0]))
        return
    seconds = 2.0 if args.short else 5.0
    load = subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout
    print(f"machine: {os.cpu_count()} cores; uptime: {load.strip()}")
    alone = manager_figure(args.agents, args.rate, seconds, with_recorder=False)
    subscribed = manager_figure(args.agents, args.rate, seconds, with_recorder=True)
    pipe = pipe_figure(args.agents, int(seconds * args.rate))
    print(
        f"{args.agents} agents at {args.rate:g} Hz, manager process CPU per y: "
        f"{alone:.1f} µs alone (baseline), {subscribed:.1f} µs with a recorder subscribed to "
        f"the bus (+{subscribed - alone:.1f} µs routing); the pipe to the recorder process "
        f"instead: +{pipe:.1f} µs"
    )


if __name__ == "__main__":
    main()

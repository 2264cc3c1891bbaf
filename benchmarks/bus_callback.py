"""Bus callback benchmark: what a message costs the receiving process, with the Zenoh thread's
Python thread state kept (``agents/bus_callback.py``) and without.

The parent opens a loopback router and puts y-sized messages (3 values and a tick report, as an
agent's) at a steady rate; a client process subscribes with a callback on Zenoh's receiving
thread that decodes each message as the agents do (``bus.decode_vector``). The client runs
once per way, alternately, each time a fresh process (a kept thread state outlives its
callback, so the two ways cannot share a process):

* ``plain`` — ``zenoh.handlers.Callback(..., indirect=False)``: PyO3 creates a Python thread
  state for each callback and deletes it afterwards;
* ``kept``  — ``bus_callback.callback(...)``: the product's way.

Reported: the client process's CPU time per message (all its threads, user and system, from
its first message to its last; the messages are paced, so the figure is per callback, not per
batch), the median of the rounds, and the ratio kept / plain. CPU time, not wall time: a busy
machine slows both ways alike.

    python benchmarks/bus_callback.py            # 5 rounds of 4000 messages per way
    python benchmarks/bus_callback.py --short    # CI-sized (a few seconds)

The last line is one JSON object, with stable keys: ``plain_us`` and ``kept_us`` (median CPU
per message [µs]), ``ratio`` (kept / plain), ``messages`` (per round and way), ``rounds``,
``load_1min`` (when the run began).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time

import numpy as np
import zenoh
from hilswarm.agents import bus, bus_callback

#: The client: subscribes, counts N messages, prints its CPU seconds from first to last.
_CLIENT = """
import sys, threading, time
import zenoh
from hilswarm.agents import bus, bus_callback

endpoint, way, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
session = bus.open_session(bus.client_config([endpoint]))
done = threading.Event()
state = {"count": 0, "first": None}

def on_y(sample):
    bus.decode_vector(sample.payload.to_bytes())
    state["count"] += 1
    if state["count"] == 1:
        state["first"] = time.process_time()
    elif state["count"] == n:
        state["last"] = time.process_time()
        done.set()

handler = bus_callback.callback(on_y) if way == "kept" else zenoh.handlers.Callback(
    on_y, indirect=False
)
subscriber = session.declare_subscriber(bus.BusKeys("bench").y("a0"), handler)
print("ready", flush=True)
if not done.wait(120):
    print(f"only {state['count']} of {n} messages within 120 s", file=sys.stderr)
    sys.exit(1)
print(f"{(state['last'] - state['first']) / (n - 1)!r}", flush=True)
subscriber.undeclare()
session.close()
"""


def one_round(
    endpoint: str, publisher: zenoh.Publisher, matched: threading.Event, way: str, *, n: int,
    rate_hz: float,
) -> float:  # fmt: skip
    """CPU seconds per message of a fresh client process receiving ``n`` messages ``way``."""
    matched.clear()  # the previous client's unmatch may not have been heard yet
    client = subprocess.Popen(
        [sys.executable, "-c", _CLIENT, endpoint, way, str(n)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = client.stdout.readline() if client.stdout else ""
        if line.strip() != "ready":
            raise RuntimeError(f"the {way} client did not start: {client.stderr.read()}")
        if not matched.wait(10.0):
            raise RuntimeError(f"the {way} client's subscription did not reach the router")
        values = np.array([0.5, -0.25, 1.0])
        report = bus.encode_report(bus.AgentTiming(), np.zeros(2), np.zeros(2))
        period = 1.0 / rate_hz
        start = time.perf_counter()
        for k in range(n):
            # paced, so that every message is a callback of its own (not one batch of many)
            pause = start + k * period - time.perf_counter()
            if pause > 0:
                time.sleep(pause)
            publisher.put(bus.encode_vector(k, k * 0.01, values), attachment=report)
        out, err = client.communicate(timeout=130)
    finally:
        if client.poll() is None:
            client.kill()
            client.wait()
    if client.returncode != 0:
        raise RuntimeError(f"the {way} client failed: {err.strip()}")
    return float(out.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--short", action="store_true", help="CI-sized run (a few seconds)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--messages", type=int, default=4000, help="per round and way")
    parser.add_argument("--rate", type=float, default=2000.0, help="messages per second")
    args = parser.parse_args(argv)
    if args.short:
        args.rounds, args.messages = 2, 1000
    if args.rounds < 1 or args.messages < 2 or args.rate <= 0:
        parser.error("--rounds >= 1, --messages >= 2 and --rate > 0")
    load = os.getloadavg()[0]
    router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
    try:
        endpoint = bus.bound_endpoints(router)[0]
        publisher = router.declare_publisher(bus.BusKeys("bench").y("a0"), **bus.TICK_PATH_QOS)
        matched = threading.Event()  # set while a client subscribes

        def on_matching(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                matched.set()
            else:
                matched.clear()

        listener = publisher.declare_matching_listener(bus_callback.callback(on_matching))
        figures: dict[str, list[float]] = {"plain": [], "kept": []}
        for round_ in range(args.rounds):
            for way in ("plain", "kept") if round_ % 2 == 0 else ("kept", "plain"):
                figures[way].append(
                    one_round(endpoint, publisher, matched, way, n=args.messages, rate_hz=args.rate)
                )
        listener.undeclare()
        publisher.undeclare()
    finally:
        router.close()
    plain = statistics.median(figures["plain"]) * 1e6
    kept = statistics.median(figures["kept"]) * 1e6
    print(f"{args.messages} messages per round at {args.rate:g}/s, {args.rounds} rounds per way")
    for way in ("plain", "kept"):
        rounds = " ".join(f"{1e6 * value:.1f}" for value in figures[way])
        print(f"{way:6s} {statistics.median(figures[way]) * 1e6:6.1f} us CPU/message ({rounds})")
    print(f"kept / plain: {kept / plain:.2f}   (load {load:.2f} at the start)")
    result = {
        "plain_us": round(plain, 2),
        "kept_us": round(kept, 2),
        "ratio": round(kept / plain, 3),
        "messages": args.messages,
        "rounds": args.rounds,
        "load_1min": round(load, 2),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

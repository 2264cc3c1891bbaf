"""Live-view benchmark: what ``hilswarm run --live`` costs the recorder, with and without clients.

The live view lives in the recorder process (:mod:`hilswarm.orchestrator.live_view`), never on
the tick path: the agents and the manager are other processes. What it can cost is recorder CPU
per message (and so, on a busy machine, CPU the ticks might have had). This benchmark feeds the
record stream (MCAP, foxglove-sdk writer) of a Frisbee swarm (``benchmarks/record_stream.py``'s
batches, 100 Hz, writes of 20 ms) through the real StreamRecorder into a real MCAP file, paired,
in one process:

* ``no live view`` — the baseline (``hilswarm run`` without ``--live``);
* ``live, no client`` — the server runs, nobody is connected;
* ``live, slow client`` — a real WebSocket client subscribed to every channel that never reads
  (its queue fills, the server drops its oldest messages; nothing may wait for it);
* ``live, reading client`` — a client subscribed to every channel that reads everything.

Figures: CPU [µs] per recorded message (best of the repeats), the ratio to the baseline, and
the messages the reading client received. Then the ticks themselves, paired: ``hilswarm run
graphs/lead_follow.toml --mode realtime`` without ``--live``, with it and no client, and with a
stalled client subscribed to everything: tick completion p50 / p99 [ms] from the run's summary.
``uptime`` load is printed beside them.

    python benchmarks/live_view.py            # 8 and 32 agents
    python benchmarks/live_view.py --short    # < 30 s
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import websockets
from hilswarm.orchestrator.live_view import LiveView
from hilswarm.orchestrator.record_stream import RecordBatch
from hilswarm.orchestrator.recorder import Recorder, record_vehicles
from hilswarm.orchestrator.stream_recorder import StreamRecorder
from record_stream import T0, build_batches, frisbee_experiment

SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
#: Batches fed before the timed part (every topic is registered and advertised by then).
WARM_BATCHES = 13
CLIENT_TIMEOUT_S = 10.0


class Client:
    """A real WebSocket client in a thread: subscribes to everything, then reads or stalls."""

    def __init__(self, url: str, *, read: bool) -> None:
        self.url = url
        self.read = read
        self.received = 0
        self.subscribed = threading.Event()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self.thread.start()
        if not self.subscribed.wait(CLIENT_TIMEOUT_S):
            raise RuntimeError("the benchmark client did not subscribe in time")

    async def _run(self) -> None:
        async with websockets.connect(self.url, subprotocols=SUBPROTOCOLS, max_size=None) as ws:
            ids: list[int] = []
            end = time.monotonic() + 1.0  # gather the advertisements
            while time.monotonic() < end:
                try:
                    frame = await asyncio.wait_for(ws.recv(), timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, str) and json.loads(frame)["op"] == "advertise":
                    ids += [c["id"] for c in json.loads(frame)["channels"]]
            subscriptions = [{"id": i + 1, "channelId": c} for i, c in enumerate(ids)]
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            await asyncio.sleep(0.3)  # the server has taken the subscriptions
            self.subscribed.set()
            while not self.stop.is_set():
                if not self.read:
                    await asyncio.sleep(0.05)  # a stalled client: reads nothing
                    continue
                try:
                    frame = await asyncio.wait_for(ws.recv(), timeout=0.05)
                except TimeoutError:
                    continue
                if isinstance(frame, bytes):
                    self.received += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join(CLIENT_TIMEOUT_S)


def measure(n: int, batches: list[RecordBatch], folder: Path, mode: str) -> tuple[float, int, int]:
    """One paired run: (CPU [s] of the timed batches, messages recorded, messages received)."""
    experiment = frisbee_experiment(folder, n)
    live = None if mode == "none" else LiveView(0)
    recorder = Recorder(folder / f"{mode}.mcap", experiment, log_time_ns=T0, mirror=live)
    record_vehicles(recorder, experiment, log_time_ns=T0)
    stream = StreamRecorder(recorder, experiment)
    for batch in batches[:WARM_BATCHES]:
        stream.write(batch.data, seq=batch.seq, count=batch.count, defines=batch.defines)
    client = None
    if live is not None and mode != "no client":
        client = Client(live.url, read=mode == "reading client")
    before = recorder.message_count
    start = time.process_time()
    for batch in batches[WARM_BATCHES:]:
        stream.write(batch.data, seq=batch.seq, count=batch.count, defines=batch.defines)
    recorder.close()
    cpu = time.process_time() - start
    if stream.errors:
        raise RuntimeError(f"{mode}: {stream.errors} record-stream messages not recorded")
    recorded = recorder.message_count - before
    received = 0
    if client is not None:
        time.sleep(0.5)  # let a reading client drain
        received = client.received
        client.close()
    if live is not None:
        live.close()
    return cpu, recorded, received


REPO = Path(__file__).resolve().parent.parent
_URL = re.compile(r"^(ws://127\.0\.0\.1:\d+)$", re.MULTILINE)
_COMPLETION = re.compile(r"tick completion p50 ([\d.]+) ms, p99 ([\d.]+) ms")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def run_ticks(duration_s: float, mode: str, folder: Path) -> tuple[float, float]:
    """One realtime lead/follow run: tick completion (p50, p99) [ms] from its summary."""
    args = [sys.executable, "-m", "hilswarm.orchestrator.cli", "run",
            str(REPO / "graphs" / "lead_follow.toml"), "--mode", "realtime",
            "--duration", str(duration_s), "--out", str(folder / f"{mode}.mcap"),
            "--port", str(_free_port())]  # fmt: skip
    if mode != "none":
        args.append("--live")
    output = folder / f"{mode}.out"
    with output.open("wb") as sink:
        process = subprocess.Popen(args, stdout=sink, stderr=subprocess.STDOUT)
        client = None
        try:
            if mode == "slow client":
                deadline = time.monotonic() + 120
                while not _URL.search(output.read_text()) and time.monotonic() < deadline:
                    if process.poll() is not None:
                        break
                    time.sleep(0.05)
                match = _URL.search(output.read_text())
                if match:
                    client = Client(match.group(1), read=False)
            process.wait(timeout=duration_s + 180)
        finally:
            if client is not None:
                client.close()
            if process.poll() is None:
                process.kill()
                process.wait()
    found = _COMPLETION.search(output.read_text())
    if not found:
        raise RuntimeError(f"no tick summary in the run's output:\n{output.read_text()}")
    return float(found.group(1)), float(found.group(2))


def best_of(repeats: int, run: Callable[[], tuple[float, int, int]]) -> tuple[float, int, int]:
    """The least disturbed of ``repeats`` runs (smallest CPU)."""
    return min((run() for _ in range(repeats)), key=lambda r: r[0])


def main() -> None:
    """Measure and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--short", action="store_true", help="a quick run (< 30 s)")
    parser.add_argument("--agents", type=int, nargs="*", default=None)
    parser.add_argument("--repeats", type=int, default=0)
    args = parser.parse_args()
    agents = args.agents or ([8] if args.short else [8, 32])
    ticks = 300 if args.short else 1500
    repeats = args.repeats or (1 if args.short else 3)
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (uptime 1, 5 min)")
    modes = ("none", "no client", "slow client", "reading client")
    for n in agents:
        batches, _ = build_batches(n, ticks)
        with tempfile.TemporaryDirectory() as tmp:
            results = {
                mode: best_of(
                    repeats,
                    lambda mode=mode, n=n, batches=batches: measure(n, batches, Path(tmp), mode),
                )
                for mode in modes
            }
        base_cpu, base_count, _ = results["none"]
        base = base_cpu / base_count * 1e6
        print(f"{n} agents, {ticks} ticks at 100 Hz, {base_count} messages timed:")
        for mode, (cpu, count, received) in results.items():
            per = cpu / count * 1e6
            label = "no live view" if mode == "none" else f"live, {mode}"
            extra = f", client received {received}" if mode == "reading client" else ""
            print(f"  {label:<22} {per:6.2f} µs/message  ({per / base:4.2f}x baseline){extra}")
    duration = 2.0 if args.short else 20.0
    print(f"realtime lead/follow, 20 Hz, {duration:g} s per run, tick completion [ms]:")
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("none", "no client", "slow client"):
            p50, p99 = run_ticks(duration, mode, Path(tmp))
            label = "no live view" if mode == "none" else f"live, {mode}"
            print(f"  {label:<22} p50 {p50:7.2f}  p99 {p99:7.2f}")
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (uptime 1, 5 min)")


if __name__ == "__main__":
    main()

"""The live view never waits for a client: a stalled subscriber costs it nothing but drops."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path

import websockets
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.live_view import LiveView
from hilswarm.orchestrator.recorder import Recorder
from swarm_harness import REPO

SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
T0 = 1_800_000_000_000_000_000
MESSAGES = 20_000
BACKLOG = 64


def stalled_client(url: str, subscribed: threading.Event, stop: threading.Event) -> None:
    """Subscribe to every advertised channel, then never read again."""

    async def run() -> None:
        async with websockets.connect(url, subprotocols=SUBPROTOCOLS, max_size=None) as ws:
            advertised = json.loads(await asyncio.wait_for(ws.recv(), 10))  # serverInfo
            while advertised.get("op") != "advertise":
                advertised = json.loads(await asyncio.wait_for(ws.recv(), 10))
            subscriptions = [
                {"id": i + 1, "channelId": c["id"]} for i, c in enumerate(advertised["channels"])
            ]
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            await asyncio.sleep(0.5)
            subscribed.set()
            while not stop.is_set():  # a stalled client: reads nothing
                await asyncio.sleep(0.05)

    asyncio.run(run())


def test_a_stalled_client_neither_blocks_nor_loses_the_recording(tmp_path: Path) -> None:
    experiment = load_experiment(REPO / "graphs" / "lead_follow.toml")
    live = LiveView(0, backlog=BACKLOG)
    subscribed, stop = threading.Event(), threading.Event()
    path = tmp_path / "run.mcap"
    try:
        with Recorder(path, experiment, log_time_ns=T0, mirror=live) as recorder:
            recorder.add_topic("/leader/y", fields=["x", "y", "psi"])
            recorder.write_floats("/leader/y", k=0, t=0.0, values=[0.0, 0.0, 0.0], log_time_ns=T0)
            client = threading.Thread(
                target=stalled_client, args=(live.url, subscribed, stop), daemon=True
            )
            client.start()
            assert subscribed.wait(30), "the client did not subscribe"
            assert "/leader/y" in live.subscribed_topics
            started = time.monotonic()
            for k in range(1, MESSAGES):
                recorder.write_floats(
                    "/leader/y", k=k, t=k * 0.05, values=[k * 1e-3, 0.5, 0.1], log_time_ns=T0 + k
                )
            elapsed = time.monotonic() - started
        assert live.messages_sent >= MESSAGES - 1  # every one handed over; the server drops
        # bounded by the machine, not by the client: far below one blocking wait per message
        assert elapsed < 60, elapsed
    finally:
        stop.set()
        live.close()
    ks = [m["k"] for topic, _, m in iter_messages(path) if topic == "/leader/y"]
    assert ks == list(range(MESSAGES))

"""``hilswarm run --live``: a real WebSocket client (foxglove.websocket.v1) watches a real run."""

from __future__ import annotations

import asyncio
import json
import re
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
import websockets
from swarm_harness import REPO, RunProcess, run_env, wait_for

LEAD_FOLLOW = REPO / "graphs" / "lead_follow.toml"
# foxglove-sdk >= 0.x negotiates "foxglove.sdk.v1": the foxglove.websocket.v1 protocol under its
# new name (same messages); a client offers both, as the Foxglove app does.
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
WANTED = ("/leader/y", "/leader/u", "/leader/x_hat", "/f1/y", "/orchestrator/ticks", "/leader/pose")
_MESSAGE_DATA = 0x01
_URL = re.compile(rb"^(ws://127\.0\.0\.1:\d+)$", re.MULTILINE)


async def watch(url: str, deadline_s: float) -> tuple[dict[str, dict], dict[str, list[bytes]]]:
    """Advertisements by topic, and the messages of the wanted topics, until all came."""
    channels: dict[str, dict] = {}
    received: dict[str, list[bytes]] = {topic: [] for topic in WANTED}
    by_subscription: dict[int, str] = {}
    end = time.monotonic() + deadline_s
    async with websockets.connect(url, subprotocols=SUBPROTOCOLS, max_size=None) as socket:
        assert socket.subprotocol in SUBPROTOCOLS
        while time.monotonic() < end and not all(len(v) >= 3 for v in received.values()):
            try:
                frame = await asyncio.wait_for(
                    socket.recv(), timeout=max(0.1, end - time.monotonic())
                )
            except TimeoutError:
                break
            if isinstance(frame, str):
                message = json.loads(frame)
                if message["op"] != "advertise":
                    continue
                subscriptions = []
                for channel in message["channels"]:
                    channels[channel["topic"]] = channel
                    if channel["topic"] in WANTED:
                        by_subscription[len(by_subscription) + 1] = channel["topic"]
                        subscriptions.append(
                            {"id": len(by_subscription), "channelId": channel["id"]}
                        )
                if subscriptions:
                    await socket.send(
                        json.dumps({"op": "subscribe", "subscriptions": subscriptions})
                    )
            elif frame[0] == _MESSAGE_DATA:
                subscription, _log_time = struct.unpack_from("<IQ", frame, 1)
                received[by_subscription[subscription]].append(frame[13:])
    return channels, received


def test_a_client_sees_channels_and_messages_of_a_running_experiment(
    tmp_path: Path, runs: list[RunProcess]
) -> None:
    run = RunProcess(
        tmp_path, LEAD_FOLLOW, "--no-check", "--mode", "realtime", "--duration", "30", "--live",
    )  # fmt: skip
    runs.append(run)
    wait_for(
        lambda: (
            _URL.search(run.stdout_path.read_bytes()) is not None or run.process.poll() is not None
        ),
        120,
        "the live view's ws:// URL on its own line",
    )
    match = _URL.search(run.stdout_path.read_bytes())
    assert match, run.output()
    try:
        channels, received = asyncio.run(watch(match.group(1).decode(), deadline_s=60))
    except websockets.ConnectionClosed as exc:  # say what the run did meanwhile
        pytest.fail(f"the live view closed the connection ({exc}); the run:\n{run.output()}")
    assert {"/experiment", "/leader/y", "/leader/u", "/orchestrator/ticks"} <= set(channels)
    y_schema = json.loads(channels["/leader/y"]["schema"])
    assert y_schema["properties"]["psi"]["description"] == "values[2] [rad]"
    assert channels["/leader/pose"]["schemaName"] == "foxglove.PoseInFrame"
    for topic in WANTED:
        assert len(received[topic]) >= 3, (topic, {t: len(m) for t, m in received.items()})
    y = json.loads(received["/leader/y"][-1])
    assert set(y) >= {"k", "t", "values", "x", "y", "psi", "wall_ns"}
    u = json.loads(received["/leader/u"][-1])
    assert set(u) >= {"v_left", "v_right"}
    tick = json.loads(received["/orchestrator/ticks"][-1])
    assert "completion_s" in tick and "leader" in tick["agents"]
    assert run.process.poll() is None  # all this while the run goes
    # every topic the shipped layout shows is served
    layout = json.loads((REPO / "docs" / "foxglove-layout.json").read_text())
    panels = layout["configById"].values()
    paths = [p["value"] for panel in panels for p in panel.get("paths", [])]
    topics = {path.split(".")[0] for path in paths} | {
        topic for panel in panels for topic in panel.get("topics", {})
    }
    event_only = {"/orchestrator/status"}  # first written when the run stops or pauses
    assert topics - event_only <= set(channels), topics - set(channels)


def test_a_busy_live_port_is_refused_before_anything_starts(tmp_path: Path) -> None:
    from hilswarm.orchestrator.live_view import LiveView

    busy = LiveView(0)
    try:
        result = subprocess.run(
            [sys.executable, "-m", "hilswarm.orchestrator.cli", "run", str(LEAD_FOLLOW),
             "--out", str(tmp_path / "run.mcap"), "--live", str(busy.port)],
            capture_output=True, text=True, timeout=120, check=False, env=run_env(tmp_path),
        )  # fmt: skip
    finally:
        busy.close()
    assert result.returncode == 2, result.stderr
    assert f"--live: cannot listen on 127.0.0.1:{busy.port}" in result.stderr
    assert not (tmp_path / "run.mcap").exists()

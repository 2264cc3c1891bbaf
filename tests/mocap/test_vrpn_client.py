"""The VRPN path end to end: ``motioncapture``'s VRPN client (the real library, in its worker
process) against the protocol-level VRPN server on loopback
(:mod:`hilswarm.agents.mocap.vrpn_sim`)."""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from hilswarm.agents.mocap.clients import MocapServerLost, MotionCaptureClient
from hilswarm.agents.mocap.frames import convention, pose_from
from hilswarm.agents.mocap.vrpn_sim import VrpnTrackerServer
from mocap_stream import stream

pytest.importorskip("motioncapture")

YAW = 0.7  # [rad]
#: A yaw of 0.7 rad about z, as (w, x, y, z).
QUAT = (math.cos(YAW / 2), 0.0, 0.0, math.sin(YAW / 2))


def test_the_real_client_reads_names_positions_and_rotations() -> None:
    poses = {"cf1": ((1.0, 2.0, 0.5), QUAT), "cf2": ((-1.0, 0.25, 0.0), (1.0, 0.0, 0.0, 0.0))}
    with VrpnTrackerServer(list(poses), lambda: poses, rate_hz=100.0) as server:
        client = MotionCaptureClient("vrpn", f"127.0.0.1:{server.port}", rate_hz=100.0)
        frames, error = stream(client, 10)
    assert error is None, error
    last = frames[-1]
    assert set(last.bodies) == {"cf1", "cf2"}
    position, rotation = last.bodies["cf1"]  # type: ignore[misc]
    assert np.allclose(position, (1.0, 2.0, 0.5))
    p, r = convention("vrpn").to_world(position, rotation)
    # x y z [m] roll pitch yaw [rad]; VRPN sends x y z w, the library gives w x y z (float32)
    np.testing.assert_allclose(pose_from(p, r), (1.0, 2.0, 0.5, 0.0, 0.0, YAW), atol=1e-6)
    assert client.bodies == ("cf1", "cf2")


def test_a_body_out_of_view_is_not_reported() -> None:
    visible = {"cf1": True}
    poses = {"cf1": ((0.0, 0.0, 0.0), QUAT), "cf2": ((1.0, 1.0, 0.0), QUAT)}

    def current() -> dict[str, object]:
        return {name: pose for name, pose in poses.items() if name != "cf1" or visible["cf1"]}

    visible["cf1"] = False
    with VrpnTrackerServer(list(poses), current, rate_hz=100.0) as server:
        client = MotionCaptureClient("vrpn", f"127.0.0.1:{server.port}", rate_hz=100.0)
        frames, error = stream(client, 5)
    assert error is None, error
    assert all("cf1" not in frame.bodies for frame in frames)
    assert all("cf2" in frame.bodies for frame in frames)


def test_a_server_that_goes_away_is_a_lost_server() -> None:
    poses = {"cf1": ((0.0, 0.0, 0.0), QUAT)}
    server = VrpnTrackerServer(list(poses), lambda: poses, rate_hz=100.0).start()
    client = MotionCaptureClient("vrpn", f"127.0.0.1:{server.port}", rate_hz=100.0)
    got_one = threading.Event()
    errors: list[BaseException] = []

    def target() -> None:
        try:
            client.run(lambda frame: got_one.set(), lambda: None)
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    try:
        assert got_one.wait(20.0)
        stopped = time.monotonic()
        server.stop()
        thread.join(20.0)
        took = time.monotonic() - stopped
    finally:
        client.stop()
        server.stop()
    assert not thread.is_alive()
    assert errors and isinstance(errors[0], MocapServerLost), errors
    assert "silent" in str(errors[0])
    assert took < 10.0  # 50 frame periods of silence (0.5 s) plus the poll


def test_a_client_of_another_major_version_is_refused() -> None:
    poses = {"cf1": ((0.0, 0.0, 0.0), QUAT)}
    with VrpnTrackerServer(list(poses), lambda: poses) as server:
        with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as sock:
            assert sock.recv(24).startswith(b"vrpn: ver. 07.")
            sock.sendall(b"vrpn: ver. 06.00  0".ljust(24, b"\0"))
            assert sock.recv(64) == b""  # closed: refused
        deadline = time.monotonic() + 5.0
        while server.refused == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert server.refused == 1


def test_hilswarm_mocap_lists_the_vrpn_bodies() -> None:
    poses = {"cf1": ((1.0, 2.0, 0.5), QUAT)}
    with VrpnTrackerServer(list(poses), lambda: poses, rate_hz=100.0) as server:
        done = subprocess.run(
            [sys.executable, "-m", "hilswarm.orchestrator.cli", "mocap", "--system", "vrpn",
             "--host", "127.0.0.1", "--port", str(server.port), "--seconds", "1"],
            capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL, check=False,
        )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    row = next(line for line in done.stdout.splitlines() if line.strip().startswith("cf1"))
    words = row.split()
    assert [float(w) for w in words[-4:]] == pytest.approx(
        [1.0, 2.0, 0.5, math.degrees(YAW)], abs=0.01
    )

"""The OptiTrack path end to end: ``motioncapture``'s NatNet client (the real library, in its
worker process) against the protocol-level NatNet server on loopback, unicast
(:mod:`hilswarm.agents.mocap.natnet_sim`), in both NatNet versions it speaks."""

from __future__ import annotations

import math
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.mocap.clients import MocapServerLost, MotionCaptureClient
from hilswarm.agents.mocap.frames import convention, pose_from
from hilswarm.agents.mocap.mc_worker import library_config
from hilswarm.agents.mocap.natnet_sim import (
    NAT_CONNECT,
    NAT_SERVERINFO,
    NAT_UNRECOGNIZED_REQUEST,
    VERSIONS,
    NatNetServer,
    packet,
)
from hilswarm.orchestrator.cli import main
from mocap_stream import stream

pytest.importorskip("motioncapture")

YAW = 0.7  # [rad] about the world's z (up)
#: The world pose (x, y, z) [m] of the test body, z up.
WORLD = (1.0, 2.0, 0.5)
#: The same pose as Motive streams it, y up (hand-computed, not through hilswarm's frames):
#: world = (x, -z, y), so the system's (x, y, z) = (world x, world z, -world y), and a yaw about
#: the world's z is a rotation about the system's +y: (w, x, y, z) = (cos yaw/2, 0, sin yaw/2, 0).
Y_UP_POSITION = (WORLD[0], WORLD[2], -WORLD[1])
Y_UP_QUAT = (math.cos(YAW / 2), 0.0, math.sin(YAW / 2), 0.0)
LEVEL = (1.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("version", VERSIONS, ids=lambda v: f"natnet{v[0]}.{v[1]}")
def test_the_real_client_reads_names_positions_and_rotations(version: tuple[int, int]) -> None:
    poses = {"cf1": (Y_UP_POSITION, Y_UP_QUAT), "cf2": ((-1.0, 0.0, 0.25), LEVEL)}
    with NatNetServer(list(poses), lambda: poses, rate_hz=100.0, version=version) as server:
        client = MotionCaptureClient("optitrack", f"127.0.0.1:{server.command_port}", rate_hz=100.0)
        frames, error = stream(client, 10)
    assert error is None, error
    assert len(frames) >= 10
    last = frames[-1]
    assert set(last.bodies) == {"cf1", "cf2"}
    position, rotation = last.bodies["cf1"]  # type: ignore[misc]
    assert np.allclose(position, Y_UP_POSITION)
    # Motive's y up turned into hilswarm's world frame (z up): x y z [m], roll pitch yaw [rad]
    p, r = convention("optitrack").to_world(position, rotation)
    np.testing.assert_allclose(pose_from(p, r), (*WORLD, 0.0, 0.0, YAW), atol=1e-6)
    assert client.bodies == ("cf1", "cf2")


def test_a_body_out_of_view_is_not_reported() -> None:
    poses = {"cf1": None, "cf2": ((1.0, 0.0, 1.0), LEVEL)}
    with NatNetServer(list(poses), lambda: poses, rate_hz=100.0) as server:
        client = MotionCaptureClient("optitrack", f"127.0.0.1:{server.command_port}", rate_hz=100.0)
        frames, error = stream(client, 5)
    assert error is None, error
    assert all("cf1" not in frame.bodies for frame in frames)  # sent untracked, as Motive does
    assert all("cf2" in frame.bodies for frame in frames)


def test_a_server_that_goes_away_is_a_lost_server() -> None:
    poses = {"cf1": ((0.0, 0.0, 0.0), LEVEL)}
    server = NatNetServer(list(poses), lambda: poses, rate_hz=100.0).start()
    client = MotionCaptureClient("optitrack", f"127.0.0.1:{server.command_port}", rate_hz=100.0)
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


def test_what_the_server_does_not_know_is_refused() -> None:
    poses = {"cf1": ((0.0, 0.0, 0.0), LEVEL)}
    with (
        NatNetServer(list(poses), lambda: poses) as server,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
    ):
        sock.settimeout(5.0)
        address = ("127.0.0.1", server.command_port)
        sock.sendto(packet(NAT_CONNECT, b""), address)
        reply, _ = sock.recvfrom(65535)
        assert struct.unpack_from("<H", reply)[0] == NAT_SERVERINFO
        data_port, multicast = struct.unpack_from("<H?", reply, 4 + 256 + 4 + 4 + 8)
        assert (data_port, multicast) == (server.data_port, False)  # unicast only
        for bad in (packet(42, b""), struct.pack("<HH", NAT_CONNECT, 8), b"\x00"):
            sock.sendto(bad, address)
            reply, _ = sock.recvfrom(65535)
            assert struct.unpack_from("<H", reply)[0] == NAT_UNRECOGNIZED_REQUEST
        assert server.refused == 3


@pytest.mark.parametrize(
    ("system", "hostname", "config"),
    [("optitrack", "10.0.0.5", {"hostname": "10.0.0.5"}),
     ("optitrack", "10.0.0.5:1512", {"hostname": "10.0.0.5", "port_command": "1512"}),
     ("vrpn", "10.0.0.5:3883", {"hostname": "10.0.0.5:3883"}),
     ("vicon", "10.0.0.5:801", {"hostname": "10.0.0.5:801"})],
)  # fmt: skip
def test_the_library_gets_the_port_its_backend_reads(
    system: str, hostname: str, config: dict[str, str]
) -> None:
    assert library_config(system, hostname) == config


def test_hilswarm_mocap_lists_the_optitrack_bodies_in_the_world_frame() -> None:
    poses = {"cf1": (Y_UP_POSITION, Y_UP_QUAT)}
    with NatNetServer(list(poses), lambda: poses, rate_hz=100.0) as server:
        done = subprocess.run(
            [sys.executable, "-m", "hilswarm.orchestrator.cli", "mocap", "--system", "optitrack",
             "--host", "127.0.0.1", "--port", str(server.command_port), "--seconds", "1"],
            capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL, check=False,
        )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    row = next(line for line in done.stdout.splitlines() if line.strip().startswith("cf1"))
    words = row.split()
    assert [float(w) for w in words[-4:]] == pytest.approx([*WORLD, math.degrees(YAW)], abs=0.01)


def test_check_names_a_body_motive_does_not_track(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    demo = (Path(__file__).resolve().parents[2] / "graphs" / "lead_follow_mocap.toml").read_text()
    head, _, rest = demo.partition("\n[mocap]\n")
    _, _, graph = rest.partition("\n[graph]\n")
    poses = {
        "frisbee1": (Y_UP_POSITION, Y_UP_QUAT),
        "frisbee2": None,  # listed in the model definitions, not tracked
        "frisbee3": (Y_UP_POSITION, LEVEL),
    }
    with NatNetServer(list(poses), lambda: poses, rate_hz=100.0) as server:
        path = tmp_path / "experiment.toml"
        path.write_text(
            f'{head}\n[mocap]\nsystem = "optitrack"\nhost = "127.0.0.1"\n'
            f"port = {server.command_port}\nrate_hz = 100.0\n\n[graph]\n{graph}"
        )
        assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "agents.f1.mocap_body: body 'frisbee2' is not visible to optitrack" in err
    assert "it sees: frisbee1, frisbee3" in err
    assert "agents.leader" not in err and "agents.f2" not in err

"""The protocol-level simulator against the real client library (qtm-rt), unchanged.

Every test starts its own simulator on a free loopback port and talks to it with Qualisys'
own Python SDK (through :class:`QualisysClient`) or with raw RT packets; every wait is bounded.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import socket
import struct
import threading

import numpy as np
import pytest
import qtm_rt
from hilswarm.agents.mocap.clients import (
    Frame,
    MocapConnectionError,
    MocapServerLost,
    QualisysClient,
    qtm_bodies,
)
from hilswarm.agents.mocap.frames import convention, pose_from, rotation_zyx
from hilswarm.agents.mocap.qtm_sim import (
    HEADER,
    TYPE_COMMAND,
    TYPE_ERROR,
    QtmSimulator,
    SimSettings,
    SimulatorError,
    data_packet,
    pack_bodies,
    pack_body,
)

POSE_A = np.array([1.25, -0.5, 0.75, 0.1, -0.2, 2.5])
TIMEOUT_S = 30.0


def collect(client: QualisysClient, n: int) -> list[Frame]:
    """Run ``client`` on a thread until ``n`` frames came (bounded)."""
    frames: list[Frame] = []
    errors: list[BaseException] = []

    def on_frame(frame: Frame) -> None:
        frames.append(frame)
        if len(frames) >= n:
            client.stop()

    def run() -> None:
        try:
            client.run(on_frame, lambda: None)
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(TIMEOUT_S)
    client.stop()
    if thread.is_alive():
        pytest.fail(f"client got {len(frames)} of {n} frames in {TIMEOUT_S} s")
    if errors:
        raise errors[0]
    return frames


def test_the_real_client_reads_bodies_poses_rate_and_occlusion() -> None:
    settings = SimSettings(bodies=("frisbee1", "blimp1"), rate_hz=200.0)
    with QtmSimulator(settings) as sim:
        sim.set_truth("frisbee1", POSE_A)  # blimp1 has no truth yet: not tracked
        client = QualisysClient("127.0.0.1", sim.port)
        frames = collect(client, 40)
    assert client.bodies == ("frisbee1", "blimp1")
    assert client.rate_hz == 200.0
    # None lost on TCP: a frame the client dropped (it fell behind) is counted in `skipped`.
    for previous, frame in itertools.pairwise(frames):
        assert frame.number - previous.number == frame.skipped + 1, (previous, frame)
    last = frames[-1]
    assert last.bodies["blimp1"] is None  # QTM's NaN body
    position, rotation = last.bodies["frisbee1"]
    p, r = convention("qualisys").to_world(position, rotation)
    np.testing.assert_allclose(pose_from(p, r), POSE_A, atol=1e-5)  # float32 on the wire
    # Camera time is this host's CLOCK_MONOTONIC: frame -> arrival is small and positive.
    latencies = [f.received_s - f.time_s for f in frames]
    assert min(latencies) >= 0.0
    # Frame times step by one period per frame number (the simulator keeps a fixed grid).
    steps = np.diff([f.time_s for f in frames]) / np.diff([f.number for f in frames])
    assert np.median(steps) == pytest.approx(1 / 200.0, rel=0.2)


def test_noise_is_seeded_and_scripted_occlusion_and_latency_apply() -> None:
    def run_once() -> list[Frame]:
        settings = SimSettings(
            bodies=("a",), rate_hz=100.0, noise_std_m=0.01, noise_std_rad=0.01, seed=5,
            latency_s=0.02, occlusions={"a": (0.1, 0.2)},
        )  # fmt: skip
        with QtmSimulator(settings) as sim:
            sim.set_truth("a", POSE_A)
            return collect(QualisysClient("127.0.0.1", sim.port), 30)

    first, second = run_once(), run_once()
    by_number = [{f.number: f for f in frames} for frames in (first, second)]
    common = sorted(set(by_number[0]) & set(by_number[1]))
    assert common
    for n in common:
        a, b = by_number[0][n].bodies["a"], by_number[1][n].bodies["a"]
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a[0], b[0])  # same seed, same noise
    # Frames 11..20 (0.1 s .. 0.2 s from the first) are occluded, the others are not.
    for frames in (first, second):
        for frame in frames:
            occluded = 0.1 <= (frame.number - 1) / 100.0 < 0.2 - 1e-9
            assert (frame.bodies["a"] is None) == occluded, frame.number
    # 20 ms of latency: every frame arrives at least that long after its camera time.
    assert min(f.received_s - f.time_s for f in first) >= 0.019


def _raw_exchange(port: int, commands: list[bytes]) -> list[tuple[int, bytes]]:
    """Send raw command packets; return the (type, body) answers after the greeting."""
    answers: list[tuple[int, bytes]] = []
    with socket.create_connection(("127.0.0.1", port), timeout=5.0) as sock:
        buffer = b""

        def read_packet() -> tuple[int, bytes]:
            nonlocal buffer
            while True:
                if len(buffer) >= HEADER.size:
                    size, kind = HEADER.unpack_from(buffer)
                    if len(buffer) >= size:
                        body, buffer = buffer[HEADER.size : size], buffer[size:]
                        return kind, body
                chunk = sock.recv(4096)
                if not chunk:
                    return -1, b""
                buffer += chunk

        assert read_packet() == (TYPE_COMMAND, b"QTM RT Interface connected\0")
        for command in commands:
            sock.sendall(command)
            answers.append(read_packet())
    return answers


def command(text: str) -> bytes:
    body = text.encode() + b"\0"
    return struct.pack("<II", 8 + len(body), TYPE_COMMAND) + body


def test_the_simulator_is_stricter_than_qtm() -> None:
    with QtmSimulator(SimSettings(bodies=("a",))) as sim:
        answers = _raw_exchange(
            sim.port,
            [
                command("GetParameters 6D"),  # before the version: refused
                command("Version 1.25"),
                command("GetParameters 6D"),
                command("StreamFrames AllFrames 3D"),  # only 6D is simulated
                command("Fly"),
                struct.pack("<II", 8 + 3, TYPE_COMMAND) + b"abc",  # no NUL
            ],
        )
        kinds = [kind for kind, _ in answers]
        assert kinds == [TYPE_ERROR, TYPE_COMMAND, 2, TYPE_ERROR, TYPE_ERROR, TYPE_ERROR]
        assert answers[1][1] == b"Version set to 1.25\0"
        assert b"<Name>a</Name>" in answers[2][1]
        # A malformed packet (wrong type) closes the connection after an error.
        closing = _raw_exchange(sim.port, [struct.pack("<II", 12, 3) + b"1234", b""])
        assert closing[0][0] == TYPE_ERROR


def test_a_six_d_packet_maps_to_each_bodys_position_and_attitude() -> None:
    """qtm-rt parses the simulator's packet bytes; ``qtm_bodies`` turns the entries into
    positions [mm] and R (body -> system) from QTM's column-major matrices, in the order of the
    6D parameters' bodies; an untracked body (NaN) is ``None``; extra entries are ignored."""
    poses = [POSE_A, None, np.array([-3.0, 0.25, 0.0, 0.0, 0.3, -1.0])]
    raw = data_packet(1_000_000, 7, [pack_body(p) for p in poses])
    packet = qtm_rt.QRTPacket(raw[HEADER.size :])
    _header, entries = packet.get_6d()
    bodies = qtm_bodies(("a", "b", "c"), entries)
    assert list(bodies) == ["a", "b", "c"]
    assert bodies["b"] is None
    for name, pose in (("a", poses[0]), ("c", poses[2])):
        position, rotation = bodies[name]
        np.testing.assert_allclose(position, pose[:3] * 1e3, rtol=1e-6)
        np.testing.assert_allclose(rotation, rotation_zyx(*pose[3:]), atol=1e-6)
    assert list(qtm_bodies(("a",), entries)) == ["a"]  # more entries than names
    assert list(qtm_bodies(("a", "b", "c", "d"), entries)) == ["a", "b", "c"]
    assert qtm_bodies(("a",), []) == {}


def test_bodies_packed_at_once_are_the_bytes_of_each_packed_alone() -> None:
    """The simulator packs a frame's bodies in one go; each entry is exactly pack_body's
    (float32 position [mm] and column-major matrix; NaN everywhere for an untracked body)."""
    rng = np.random.default_rng(11)
    poses = rng.normal(size=(64, 6)) * [2.0, 2.0, 1.0, 3.0, 1.5, 3.0]
    poses[5] = np.nan
    poses[9, 2] = np.inf
    packed = pack_bodies(poses)
    assert packed == b"".join(pack_body(pose) for pose in poses)
    assert pack_bodies(np.empty((0, 6))) == b""


def test_qtm_rt_directly_streams_six_d() -> None:
    """The SDK's own calls, as a Qualisys user writes them (no hilswarm client in between)."""

    async def session(port: int) -> tuple[str, int, int]:
        connection = await qtm_rt.connect("127.0.0.1", port=port, version="1.25", timeout=5)
        assert connection is not None
        version = await connection.qtm_version()
        xml = await connection.get_parameters(parameters=["6d"])
        got: list[qtm_rt.QRTPacket] = []
        done = asyncio.Event()

        def on_packet(packet: qtm_rt.QRTPacket) -> None:
            got.append(packet)
            if len(got) >= 5:
                done.set()

        await connection.stream_frames(components=["6d"], on_packet=on_packet)
        await asyncio.wait_for(done.wait(), TIMEOUT_S)
        await connection.stream_frames_stop()
        header, _bodies = got[-1].get_6d()
        connection.disconnect()
        return version.decode(), header.body_count, len(xml)

    with QtmSimulator(SimSettings(bodies=("a", "b"))) as sim:
        version, count, xml_size = asyncio.run(session(sim.port))
    assert "QTM Version" in version
    assert count == 2
    assert xml_size > 0


def test_a_refused_connection_and_a_lost_server_are_reported() -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # nothing listens on it once closed
    with pytest.raises(MocapConnectionError, match="cannot connect"):
        QualisysClient("127.0.0.1", port, timeout_s=2.0).run(lambda f: None, lambda: None)

    sim = QtmSimulator(SimSettings(bodies=("a",)))
    sim.start()
    client = QualisysClient("127.0.0.1", sim.port)
    frames: list[Frame] = []

    def on_frame(frame: Frame) -> None:
        frames.append(frame)
        if len(frames) == 10:
            threading.Thread(target=sim.close, daemon=True).start()  # the server goes away

    with pytest.raises(MocapServerLost, match="lost"):
        client.run(on_frame, lambda: None)
    assert len(frames) >= 10


def test_bad_settings_are_refused() -> None:
    with pytest.raises(SimulatorError, match="distinct"):
        SimSettings(bodies=("a", "a"))
    with pytest.raises(SimulatorError, match="rate_hz"):
        SimSettings(bodies=("a",), rate_hz=0.0)
    with pytest.raises(SimulatorError, match="unknown bodies"):
        SimSettings(bodies=("a",), occlusions={"b": (0.0, 1.0)})
    assert math.isfinite(SimSettings(bodies=("a",)).rate_hz)

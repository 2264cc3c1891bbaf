"""Vicon / OptiTrack / VRPN through ``motioncapture``, the library in a worker process.

The real library, with no server on the host (loopback): libmotioncapture holds the GIL while it
connects, and an OptiTrack connect with no server never returns, so the client runs it in a
worker process and keeps every wait bounded. The worker's record stream is tested on a pipe."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest
from hilswarm.agents.mocap.clients import (
    MocapConnectionError,
    MocapServerLost,
    MotionCaptureClient,
)
from hilswarm.agents.mocap.mc_worker import RecordError, RecordReader, encode

pytest.importorskip("motioncapture")

#: Bound on one client run in these tests [s] (the connect bound below plus the worker's start).
RUN_BOUND_S = 30.0


def run_client(client: MotionCaptureClient) -> tuple[BaseException | None, float, list[object]]:
    """``client.run`` on a thread of this process, bounded; returns its error, its duration and
    the frames it gave. The test's own thread keeps running meanwhile (no GIL held for good)."""
    frames: list[object] = []
    box: list[BaseException] = []

    def target() -> None:
        try:
            client.run(frames.append, lambda: None)
        except BaseException as exc:
            box.append(exc)

    started = time.monotonic()
    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    beats = 0
    while thread.is_alive() and time.monotonic() - started < RUN_BOUND_S:
        thread.join(0.05)
        beats += 1  # this thread runs while the library waits in the worker
    assert not thread.is_alive(), "client.run did not return within its bound"
    assert beats >= 1
    return (box[0] if box else None), time.monotonic() - started, frames


def test_an_optitrack_connect_with_no_server_is_bounded_and_named() -> None:
    client = MotionCaptureClient("optitrack", "127.0.0.1", connect_timeout_s=1.0)
    error, took, frames = run_client(client)
    assert isinstance(error, MocapConnectionError), error
    assert "no optitrack server answered at 127.0.0.1 within 1 s" in str(error)
    assert took < 15.0 and frames == []


def test_vrpn_with_no_server_is_no_connection_not_an_empty_scene() -> None:
    # VRPN's client paces empty frames by itself, server or not: only a body proves a server.
    # (its connect alone takes about a second: the bound is 3 s)
    client = MotionCaptureClient("vrpn", "127.0.0.1", connect_timeout_s=3.0)
    error, _, frames = run_client(client)
    assert isinstance(error, MocapConnectionError), error
    assert "no body from vrpn at 127.0.0.1 within 3 s" in str(error)
    assert "unreachable or tracks no body" in str(error)
    assert frames == []


def test_stop_ends_a_waiting_client_at_once() -> None:
    client = MotionCaptureClient("optitrack", "127.0.0.1", connect_timeout_s=60.0)
    threading.Timer(0.5, client.stop).start()
    error, took, _ = run_client(client)
    assert error is None and took < 10.0


def test_the_worker_process_is_gone_after_the_client() -> None:
    client = MotionCaptureClient("optitrack", "127.0.0.1", connect_timeout_s=0.5)
    run_client(client)
    workers = subprocess.run(
        ["pgrep", "-f", "hilswarm.agents.mocap.mc_worker optitrack 127.0.0.1"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert workers.stdout.strip() == "", workers.stdout


def test_hilswarm_mocap_with_no_vrpn_server_exits_1_and_says_why() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "hilswarm.orchestrator.cli", "mocap", "--system", "vrpn",
         "--host", "127.0.0.1", "--seconds", "1"],
        capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL, check=False,
    )  # fmt: skip
    assert done.returncode == 1, done.stdout + done.stderr
    assert "no body from vrpn at 127.0.0.1" in done.stderr, done.stderr
    assert "frames" not in done.stdout  # no pretend frame rate of an absent server


# -- the worker's records ---------------------------------------------------------------------


def test_records_are_read_whole_across_partial_writes_and_timeouts() -> None:
    read_fd, write_fd = os.pipe()
    try:
        reader = RecordReader(read_fd)
        data = encode(("frame", 1.5, [("cf1", (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))]))
        assert reader.read(0.0) is None  # nothing yet: no wait
        os.write(write_fd, data[:5])
        assert reader.read(0.05) is None  # half a record: still none, bounded
        os.write(write_fd, data[5:] + encode(("ready",)))
        assert reader.read(1.0) == ("frame", 1.5, [("cf1", (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))])
        assert reader.read(1.0) == ("ready",)
        os.close(write_fd)
        write_fd = -1
        with pytest.raises(EOFError):
            reader.read(1.0)
    finally:
        os.close(read_fd)
        if write_fd >= 0:
            os.close(write_fd)


def test_a_malformed_record_is_refused() -> None:
    read_fd, write_fd = os.pipe()
    try:
        os.write(write_fd, (1 << 30).to_bytes(4, "little"))  # a length over the bound
        with pytest.raises(RecordError):
            RecordReader(read_fd).read(1.0)
    finally:
        os.close(read_fd)
        os.close(write_fd)


def test_a_truncated_pickle_is_a_malformed_record_not_the_workers_end() -> None:
    read_fd, write_fd = os.pipe()
    try:
        os.write(write_fd, (2).to_bytes(4, "little") + b"\x80\x05")  # pickle raises EOFError
        with pytest.raises(RecordError, match="malformed"):
            RecordReader(read_fd).read(1.0)
    finally:
        os.close(read_fd)
        os.close(write_fd)


def stream(
    client: MotionCaptureClient, *records: tuple[object, ...]
) -> tuple[BaseException | None, list[object]]:
    """``client._stream`` over a pipe holding ``records`` and then closed: what it raised and
    the frames it gave."""
    read_fd, write_fd = os.pipe()
    frames: list[object] = []
    try:
        os.write(write_fd, b"".join(encode(record) for record in records))
        os.close(write_fd)
        write_fd = -1
        client._stream(RecordReader(read_fd), frames.append, lambda: None)
    except (MocapConnectionError, MocapServerLost) as exc:
        return exc, frames
    finally:
        os.close(read_fd)
        if write_fd >= 0:
            os.close(write_fd)
    return None, frames


BODY = [("cf1", (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))]


def test_a_worker_error_while_streaming_is_reported_after_its_frames() -> None:
    client = MotionCaptureClient("vicon", "127.0.0.1", rate_hz=100.0)
    error, frames = stream(client, ("ready",), ("frame", 1.0, BODY), ("error", "vicon at x: gone"))
    # the library failed while streaming: the server is lost (the agents' "mocap server lost")
    assert isinstance(error, MocapServerLost) and "vicon at x: gone" in str(error)
    assert len(frames) == 1


def test_a_worker_that_dies_while_streaming_is_a_lost_server() -> None:
    client = MotionCaptureClient("vicon", "127.0.0.1", rate_hz=100.0)
    error, frames = stream(client, ("ready",), ("frame", 1.0, BODY), ("frame", 1.01, BODY))
    assert isinstance(error, MocapServerLost) and "closed its output" in str(error)
    assert len(frames) == 1  # the newest of the two (the backlog is dropped, counted)
    assert frames[0].skipped == 1 and frames[0].time_s == 1.01  # type: ignore[attr-defined]


def test_a_worker_that_dies_before_connecting_is_a_connection_error() -> None:
    client = MotionCaptureClient("vicon", "127.0.0.1")
    error, frames = stream(client)
    assert isinstance(error, MocapConnectionError), error
    assert "cannot connect to vicon at 127.0.0.1" in str(error) and frames == []


FAKE_LIBRARY = '''
"""A stand-in for libmotioncapture that prints on the C standard output, as VRPN does."""
import os, time

class _Q:
    w, x, y, z = 1.0, 0.0, 0.0, 0.0

class _Body:
    position = (1.0, 2.0, 3.0)
    rotation = _Q()

class _Mc:
    rigidBodies = {"cf1": _Body()}
    def waitForNextFrame(self):
        os.write(1, b"VRPN Warning: chatter on fd 1 in the middle of the stream\\n")
        time.sleep(0.01)

def connect(system, options):
    os.write(1, b"tracker: cf1\\n")
    return _Mc()
'''


def test_the_librarys_own_prints_never_reach_the_record_stream(tmp_path) -> None:
    # VRPN prints ("tracker: cf1", warnings) on the process's standard output; measured in a
    # loaded run, its "VRPN..." text landed in the middle of the record stream.
    (tmp_path / "motioncapture.py").write_text(FAKE_LIBRARY)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    worker = subprocess.Popen(
        [sys.executable, "-m", "hilswarm.agents.mocap.mc_worker", "vrpn", "127.0.0.1"],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
    )  # fmt: skip
    try:
        reader = RecordReader(worker.stdout.fileno())  # type: ignore[union-attr]
        records = [reader.read(10.0) for _ in range(20)]
    finally:
        worker.kill()
        _, err = worker.communicate(timeout=10)
    assert records[0] == ("ready",)
    assert all(r is not None and r[0] == "frame" for r in records[1:]), records
    assert records[-1][2] == [("cf1", (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))]  # type: ignore[index]
    assert b"tracker: cf1" in err and b"VRPN Warning" in err  # to the log instead

"""The record stream's recorder side: StreamRecorder's batching and the real recorder process
(lower CPU priority, writes that never wait for a lagging recorder, nothing dropped)."""

from __future__ import annotations

import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents import bus
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.orchestrator.cpu_priority import autogroup_niceness
from hilswarm.orchestrator.experiment import Experiment, load_experiment
from hilswarm.orchestrator.record_stream import RecordBatch, RecordWriter, hand_over
from hilswarm.orchestrator.recorder import Recorder, record_vehicles
from hilswarm.orchestrator.recorder_process import RECORDER_NICE, RecorderProcess
from hilswarm.orchestrator.recorder_spawn import start_recorder_process
from hilswarm.orchestrator.stream_recorder import StreamRecorder
from mcap.reader import make_reader

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
T0 = 1_800_000_000_000_000_000  # a log time [ns, Unix epoch]
NAMES = ("leader", "f1", "f2")


@pytest.fixture
def experiment() -> Experiment:
    return load_experiment(GRAPHS / "lead_follow.toml", overrides={"duration_s": 1.0})


def log_y(writer: RecordWriter, i: int, k: int, dt: float, *, n_y: int = 3) -> None:
    """Agent ``i``'s y of tick ``k`` (``u`` and ``x_hat`` from tick 1 on)."""
    u = None if k == 0 else np.array([0.1 * i, -0.1 * k])
    x_hat = None if k == 0 else np.array([float(k), 0.5])
    timing = bus.AgentTiming(
        compute_s=1e-4 * i, actuate_s=2e-4, sense_s=3e-4, skipped=i, link_s=5e-4, retries=i
    )
    payload = bus.encode_vector(k, k * dt, [float(i), k / 3, math.pi][:n_y])
    writer.y(i, T0 + k, payload, bus.encode_report(timing, u, x_hat))


def log_tick(writer: RecordWriter, k: int, dt: float) -> None:
    """Tick ``k``'s account as the manager records it."""
    writer.tick(
        k,
        T0 + k,
        scheduled_s=k * dt,
        send_delay_s=1e-5,
        completion_s=0.002,
        late=[],
        missing=[],
        answer_s=np.array([0.001, 0.002, 0.003]),
    )


def log_telemetry(writer: RecordWriter, i: int, k0: int, n: int, dt: float) -> None:
    ks = np.arange(k0, k0 + n, dtype=np.int64)
    battery = bus.telemetry_channel_head("battery", ("battery",))
    duty = bus.telemetry_channel_head("wheel_duty", ("left", "right"))
    batch = bus.encode_telemetry_batch(
        [
            (battery, ks, ks * dt, np.full((n, 1), 12.5)),
            (duty, ks, ks * dt, np.column_stack([ks * 0.01, -ks * 0.01])),
        ]
    )
    writer.telemetry(i, T0 + k0, batch)


def mixed_stream(dt: float) -> tuple[list[RecordBatch], list[tuple[str, int]]]:
    """A stream with messages of every kind (one of them bad), a batch per tick, and the
    (topic, k) the file must hold, in order."""
    writer = RecordWriter(NAMES)
    writer.status(1, T0, bus.encode_json({"state": "running", "k": 0, "t": 0.0}))
    expected = [("/f1/status", 0)]
    batches = []
    for k in range(6):
        for i, name in enumerate(NAMES):
            # at tick 3, f1 sends two values where its vehicle names three outputs: plain y
            log_y(writer, i, k, dt, n_y=2 if (k, i) == (3, 1) else 3)
            expected.append((f"/{name}/y", k))
            if k:
                expected += [(f"/{name}/u", k), (f"/{name}/x_hat", k)]
        log_tick(writer, k, dt)
        expected.append(("/orchestrator/ticks", k))
        if k == 2:
            log_telemetry(writer, 2, 0, 3, dt)
            expected += [("/f2/telemetry/battery", j) for j in range(3)]
            expected += [("/f2/telemetry/wheel_duty", j) for j in range(3)]
            writer.y(0, T0, b"bad", b"")  # a y of 3 bytes: logged, counted, skipped
        if k == 4:
            writer.event(T0 + k, "f2", "lost", k=k, t=k * dt, detail="gone")
            expected.append(("/f2/status", k))
        batch = writer.take(T0 + k)
        assert batch is not None
        batches.append(batch)
    batches.append(writer.close(T0 + 6))
    return batches, expected


def recorded(path: Path) -> list[tuple[str, int]]:
    return [
        (topic, message["k"])
        for topic, _, message in iter_messages(path)
        if not topic.endswith("/calibration") and topic != "/experiment"
    ]


def record_in_process(path: Path, experiment: Experiment, feed: Iterator[bytes]) -> StreamRecorder:
    with Recorder(path, experiment, log_time_ns=T0) as recorder:
        record_vehicles(recorder, experiment, log_time_ns=T0)
        stream = StreamRecorder(recorder, experiment)
        for data in feed:
            stream.feed(data)
        stream.feed(b"", whole=True)
        assert stream.pending == 0
    return stream


def test_messages_are_recorded_in_stream_order_however_they_arrive(
    tmp_path: Path, experiment: Experiment
) -> None:
    batches, expected = mixed_stream(experiment.dt)
    data = b"".join(batch.data for batch in batches)
    by_batch = tmp_path / "batches.mcap"
    with Recorder(by_batch, experiment, log_time_ns=T0) as recorder:
        record_vehicles(recorder, experiment, log_time_ns=T0)
        stream = StreamRecorder(recorder, experiment)
        for batch in batches:
            stream.write(batch.data, seq=batch.seq)
    assert stream.errors == 1 and stream.messages == sum(batch.count for batch in batches)
    assert recorded(by_batch) == expected
    whole = tmp_path / "whole.mcap"
    assert record_in_process(whole, experiment, iter([data])).errors == 1
    pieces = tmp_path / "pieces.mcap"
    record_in_process(pieces, experiment, (data[i : i + 7] for i in range(0, len(data), 7)))
    messages = list(iter_messages(by_batch))
    assert list(iter_messages(whole)) == messages == list(iter_messages(pieces))
    by_topic: dict[str, list[dict]] = {}
    for topic, log_time, message in messages:
        # experiment clock: log time = run start + t; the wall time kept in the message
        assert isinstance(message.pop("wall_ns"), int)
        assert log_time == T0 + round(message["t"] * 1e9)
        by_topic.setdefault(topic, []).append(message)
    # named outputs beside the values, except f1's from the y that did not match them on
    assert by_topic["/leader/y"][3] == {
        "k": 3, "t": 3 * experiment.dt, "values": [0.0, 1.0, math.pi], "x": 0.0, "y": 1.0,
        "psi": math.pi,
    }  # fmt: skip
    assert "x" in by_topic["/f1/y"][2] and "x" not in by_topic["/f1/y"][3]
    assert by_topic["/f1/y"][3]["values"] == [1.0, 1.0] and "x" not in by_topic["/f1/y"][5]
    assert by_topic["/f2/x_hat"][0] == {"k": 1, "t": 0.0, "values": [1.0, 0.5]}
    assert by_topic["/f2/telemetry/wheel_duty"][2] == {
        "k": 2, "t": 2 * experiment.dt, "values": [0.02, -0.02], "left": 0.02, "right": -0.02,
    }  # fmt: skip
    tick = by_topic["/orchestrator/ticks"][4]
    assert tick["agents"]["f1"] == {
        "answer_s": 0.002, "bus_s": 0.002 - (1e-4 + 2e-4 + 3e-4 + 5e-4), "compute_s": 1e-4,
        "actuate_s": 2e-4, "link_s": 5e-4, "sense_s": 3e-4, "skipped": 1, "retries": 1,
    }  # fmt: skip


class Ticks:
    """The manager's side of a run of lead_follow: batches of whole ticks, handed to a sink."""

    def __init__(self, experiment: Experiment) -> None:
        self.dt = experiment.dt
        self.writer = RecordWriter(NAMES)

    def batch(self, ticks: range) -> RecordBatch:
        for k in ticks:
            for i in range(len(NAMES)):
                log_y(self.writer, i, k, self.dt)
            log_tick(self.writer, k, self.dt)
        batch = self.writer.take(T0)
        assert batch is not None
        return batch

    def hand(self, recorder: RecorderProcess, ticks: range, **kwargs: int) -> int:
        """Hand ``ticks`` to ``recorder`` as one batch; returns its size [bytes]."""
        batch = self.batch(ticks)
        hand_over(recorder, batch, **kwargs)
        return len(batch.data)


def y_count(path: Path) -> int:
    with path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None  # a complete file
    leader = next(c.id for c in summary.channels.values() if c.topic == "/leader/y")
    return summary.statistics.channel_message_counts[leader]


def wait_until(condition: Callable[[], bool], timeout_s: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def test_a_recorder_process_started_early_is_given_its_set_up_and_records(
    tmp_path: Path, experiment: Experiment
) -> None:
    """``hilswarm run`` starts the recorder process before the run is known; the
    RecorderProcess made later adopts it (no second process) and the recording is whole."""
    early = start_recorder_process()
    path = tmp_path / "run.mcap"
    recorder = RecorderProcess(path, experiment, log_time_ns=T0, process=early)
    try:
        recorder.wait_ready()
        assert recorder.process is early
        batches, expected = mixed_stream(experiment.dt)
        for batch in batches:
            hand_over(recorder, batch)
    finally:
        assert recorder.close() == 0
    assert early.returncode == 0
    assert recorded(path) == expected


def test_recorder_process_lowers_its_priority(tmp_path: Path, experiment: Experiment) -> None:
    recorder = RecorderProcess(tmp_path / "run.mcap", experiment, log_time_ns=T0)
    try:
        recorder.wait_ready()
        niceness = os.getpriority(os.PRIO_PROCESS, recorder.process.pid)
        assert niceness == min(19, os.getpriority(os.PRIO_PROCESS, 0) + RECORDER_NICE)
        # Its session's autogroup too (the recorder leads a session of its own): else the
        # niceness would not count against the agents, each in a session of its own.
        assert autogroup_niceness(recorder.process.pid) in (None, niceness)
    finally:
        assert recorder.close() == 0


def test_write_does_not_wait_for_a_stopped_recorder(tmp_path: Path, experiment: Experiment):
    path = tmp_path / "run.mcap"
    recorder = RecorderProcess(path, experiment, log_time_ns=T0)
    ticks = 0
    try:
        recorder.wait_ready()
        pid = recorder.process.pid
        os.kill(pid, signal.SIGSTOP)
        try:
            stream = Ticks(experiment)
            target = 2 * recorder.pipe_size  # far more than the pipe holds
            done = threading.Event()

            def feed() -> None:
                nonlocal ticks
                sent = 0
                while sent < target:
                    sent += stream.hand(recorder, range(ticks, ticks + 100))
                    ticks += 100
                done.set()

            feeder = threading.Thread(target=feed, daemon=True)
            feeder.start()
            # The stopped recorder reads nothing, yet every write returns.
            assert done.wait(timeout=120), "write waited for the stopped recorder"
            assert recorder.queued_bytes > recorder.pipe_size
            assert recorder.write_waits == 0
        finally:
            os.kill(pid, signal.SIGCONT)
    finally:
        assert recorder.close() == 0
    assert recorder.bytes_written > 2 * recorder.pipe_size and recorder.queued_bytes == 0
    assert y_count(path) == ticks  # nothing dropped


def test_wait_written_returns_once_a_stopped_recorder_caught_up(
    tmp_path: Path, experiment: Experiment
) -> None:
    """Records handed to a stopped recorder are not written: the wait times out. Continued,
    it writes them, and the wait returns with nothing left unacknowledged."""
    path = tmp_path / "run.mcap"
    recorder = RecorderProcess(path, experiment, log_time_ns=T0)
    try:
        recorder.wait_ready()
        os.kill(recorder.process.pid, signal.SIGSTOP)
        try:
            Ticks(experiment).hand(recorder, range(200))
            assert recorder.queued_bytes > 0
            assert not recorder.wait_written(0.2)
        finally:
            os.kill(recorder.process.pid, signal.SIGCONT)
        assert recorder.wait_written(60.0)
        assert recorder.queued_bytes == 0
        assert recorder.process.poll() is None  # still recording: the file is not closed
    finally:
        assert recorder.close() == 0
    assert y_count(path) == 200


def test_write_waits_beyond_the_bound_and_says_so_once(
    tmp_path: Path, experiment: Experiment, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "run.mcap"
    bound = 128 * 1024
    recorder = RecorderProcess(path, experiment, log_time_ns=T0, queue_bytes=bound)
    ticks = 400
    try:
        recorder.wait_ready()
        pid = recorder.process.pid
        stream = Ticks(experiment)
        batches = [stream.batch(range(k, k + 20)) for k in range(0, ticks, 20)]
        per_batch = len(batches[-1].data)
        n_batches = (recorder.pipe_size + 4 * bound) // per_batch + 1
        batches += [
            stream.batch(range(k, k + 20)) for k in range(ticks, ticks + 20 * n_batches, 20)
        ]
        ticks += 20 * n_batches
        os.kill(pid, signal.SIGSTOP)
        try:
            feeder = threading.Thread(
                target=lambda: [hand_over(recorder, b) for b in batches],
                daemon=True,
            )
            with caplog.at_level(logging.WARNING):
                feeder.start()
                assert wait_until(lambda: recorder.write_waits > 0)
                assert feeder.is_alive()  # waiting for room, not dropping
                assert recorder.queued_bytes <= bound
        finally:
            os.kill(pid, signal.SIGCONT)
        feeder.join(timeout=120)
        assert not feeder.is_alive()
    finally:
        assert recorder.close() == 0
    lags = [r for r in caplog.records if "lags behind" in r.getMessage()]
    assert len(lags) == 1 and recorder.write_waits >= 1
    assert y_count(path) == ticks


def leader_ticks(path: Path) -> list[int]:
    return [m["k"] for topic, _, m in iter_messages(path) if topic == "/leader/y"]


def test_a_killed_recorder_is_restarted_into_the_next_segment(
    tmp_path: Path, experiment: Experiment
) -> None:
    """kill -9 of the recorder: a new process continues in run.1.mcap, nothing lost or doubled,
    and the dead segment is rewritten as a complete file."""
    path = tmp_path / "run.mcap"
    recorder = RecorderProcess(path, experiment, log_time_ns=T0)
    first_pid = 0
    try:
        recorder.wait_ready()
        first_pid = recorder.process.pid
        stream = Ticks(experiment)
        for k in range(0, 2000, 50):
            stream.hand(recorder, range(k, k + 50), tick=k)
        assert wait_until(lambda: recorder.bytes_written > 0)  # some of it on disk
        os.killpg(first_pid, signal.SIGKILL)  # whatever it had not acknowledged is sent again
        for k in range(2000, 4000, 50):
            stream.hand(recorder, range(k, k + 50), tick=k)
        assert wait_until(lambda: recorder.restarts == 1)
    finally:
        assert recorder.close() == 0
    assert recorder.process.pid != first_pid and not recorder.failed
    segments = [path, tmp_path / "run.1.mcap"]
    assert recorder.segments == segments
    report = recorder.report()
    assert report.complete and report.lost_records == 0
    assert "killed by SIGKILL" in report.failures[0] and "run.1.mcap" in report.failures[0]
    first, second = (leader_ticks(segment) for segment in segments)
    assert first + second == list(range(4000))  # every tick once, in order
    for segment in segments:  # both complete files, each with the run's start
        assert y_count(segment) == len(leader_ticks(segment))
        assert next(iter_messages(segment))[0] == "/experiment"


def test_batches_written_while_the_new_recorder_starts_are_not_lost(
    tmp_path: Path, experiment: Experiment
) -> None:
    """A manager keeps writing while its killed recorder is replaced: every batch reaches the
    new process (a batch handed to the dead process's pipe while the new one started was kept
    as sent and taken as acknowledged: lost without a word)."""
    path = tmp_path / "run.mcap"
    recorder = RecorderProcess(path, experiment, log_time_ns=T0)
    k = 0
    try:
        recorder.wait_ready()
        stream = Ticks(experiment)
        for _ in range(10):
            stream.hand(recorder, range(k, k + 5), tick=k)
            k += 5
        assert wait_until(lambda: recorder.bytes_written > 0)
        os.killpg(recorder.process.pid, signal.SIGKILL)
        # Small batches, one every ~ms, through the restart and beyond (bounded: 20 s).
        deadline, after = time.monotonic() + 20.0, 0
        while after < 200 and time.monotonic() < deadline:
            stream.hand(recorder, range(k, k + 1), tick=k)
            k += 1
            after += recorder.restarts == 1
            time.sleep(0.001)  # the pace of a manager's batches, not a synchronisation
        assert recorder.restarts == 1
    finally:
        assert recorder.close() == 0
    report = recorder.report()
    assert report.complete and report.lost_records == 0
    first, second = (leader_ticks(segment) for segment in recorder.segments)
    assert first + second == list(range(k))  # every tick once, in order


def test_a_recorder_that_keeps_dying_is_given_up_and_the_loss_counted(
    tmp_path: Path, experiment: Experiment
) -> None:
    path = tmp_path / "run.mcap"
    failures: list[str] = []
    recorder = RecorderProcess(
        path, experiment, log_time_ns=T0, max_restarts=0, on_failure=failures.append
    )
    try:
        recorder.wait_ready()
        stream = Ticks(experiment)
        stream.hand(recorder, range(0, 50), tick=0)
        assert wait_until(lambda: recorder.queued_bytes == 0)  # acknowledged: on disk
        os.killpg(recorder.process.pid, signal.SIGKILL)
        assert wait_until(lambda: bool(recorder.failed))
        stream.hand(recorder, range(50, 60), tick=50)
    finally:
        assert recorder.close() == -signal.SIGKILL
    assert failures == [recorder.failed] and "restarts used up" in failures[0]
    report = recorder.report()
    assert report.lost_records == 40 and report.lost_ticks == (50, 50)
    assert report.stopped_at_tick == 0 and not report.complete
    assert leader_ticks(path) == list(range(50))  # the dead file was rewritten, complete
    assert y_count(path) == 50


def test_the_loss_is_counted_from_the_first_tick_a_batch_can_hold(
    tmp_path: Path, experiment: Experiment
) -> None:
    """The manager hands over a batch at tick 60 whose records it gathered since tick 50: a
    recording given up reports ticks 50.. as not recorded, not 60.. (what it holds before
    tick 50 is on disk)."""
    path = tmp_path / "run.mcap"
    recorder = RecorderProcess(path, experiment, log_time_ns=T0, max_restarts=0)
    try:
        recorder.wait_ready()
        stream = Ticks(experiment)
        stream.hand(recorder, range(0, 50), tick=50)
        assert wait_until(lambda: recorder.queued_bytes == 0)  # acknowledged: on disk
        os.killpg(recorder.process.pid, signal.SIGKILL)
        assert wait_until(lambda: bool(recorder.failed))
        stream.hand(recorder, range(50, 60), tick=60, first_tick=50)
    finally:
        assert recorder.close() == -signal.SIGKILL
    report = recorder.report()
    assert report.lost_records == 40 and report.lost_ticks == (50, 60)
    assert report.stopped_at_tick == 50
    assert leader_ticks(path) == list(range(50))


def test_a_staged_recording_is_published_or_removed(tmp_path: Path, experiment: Experiment):
    kept = tmp_path / "kept.mcap"
    kept.write_bytes(b"an older recording")
    recorder = RecorderProcess(kept, experiment, log_time_ns=T0, staged=True)
    try:
        recorder.wait_ready()
        with pytest.raises(RecordingError, match="exists"):
            recorder.publish()
    finally:
        recorder.close()
    assert kept.read_bytes() == b"an older recording"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.mcap"]  # no file left
    fresh = tmp_path / "fresh.mcap"
    recorder = RecorderProcess(fresh, experiment, log_time_ns=T0, staged=True)
    try:
        recorder.wait_ready()
        recorder.publish()
        Ticks(experiment).hand(recorder, range(5))
    finally:
        assert recorder.close() == 0
    assert leader_ticks(fresh) == list(range(5))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh.mcap", "kept.mcap"]


def test_y_messages_of_one_length_with_other_layouts(tmp_path: Path, experiment: Experiment):
    """y messages of equal length but other sizes of y, u and x_hat are read with their own."""
    timing = bus.AgentTiming(compute_s=1e-4, actuate_s=2e-4, sense_s=3e-4, skipped=0)
    shapes = [
        (3, 2, 2), (3, 3, 1), (3, 1, 3), (3, 2, 2), (12, None, None), (7, 0, 0), (12, None, None),
        (3, 2, 2),
    ]  # fmt: skip
    writer, sizes, sent = RecordWriter(NAMES), [], []
    for k, (n_y, n_u, n_x) in enumerate(shapes):
        y = [k + j / 10 for j in range(n_y)]
        u = None if n_u is None else [-k - j / 10 for j in range(n_u)]
        x_hat = None if n_x is None else [100 + j for j in range(n_x)]
        report = b"" if u is None else bus.encode_report(timing, np.array(u), np.array(x_hat))
        payload = bus.encode_vector(k, k * 0.1, y)
        writer.y(2, T0 + k, payload, report)
        sizes.append(len(payload) + len(report))
        sent.append((y, u or [], x_hat if u else []))
    assert len(set(sizes)) == 1  # one length, five layouts
    path = tmp_path / "layouts.mcap"
    data = writer.close(T0).data
    assert record_in_process(path, experiment, iter([data])).errors == 0
    got: dict[str, dict[int, list]] = {}
    for topic, _, message in iter_messages(path):
        got.setdefault(topic, {})[message["k"]] = message["values"]
    assert [got["/f2/y"][k] for k in range(len(shapes))] == [y for y, _, _ in sent]
    assert got["/f2/u"] == {k: u for k, (_, u, _) in enumerate(sent) if u}
    assert got["/f2/x_hat"] == {k: x for k, (_, u, x) in enumerate(sent) if u and x}

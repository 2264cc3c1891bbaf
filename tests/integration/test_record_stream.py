"""The record stream and the recorder process: the manager's MCAP stream in, the MCAP topics of
the contract out."""

from __future__ import annotations

import io
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents import bus
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import iter_messages, json_safe, vector_json
from hilswarm.orchestrator.experiment import Experiment, load_experiment
from hilswarm.orchestrator.record_stream import (
    OP_MESSAGE,
    PROFILE,
    RecordBatch,
    RecordWriter,
    hand_over,
    records,
)
from hilswarm.orchestrator.recorder import Recorder
from hilswarm.orchestrator.recorder_process import RecorderProcess
from hilswarm.orchestrator.stream_recorder import StreamRecorder
from hypothesis import given
from hypothesis import strategies as st
from mcap.reader import make_reader
from swarm_harness import read_recording

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
T0 = 1_800_000_000_000_000_000  # a log time [ns, Unix epoch]


@pytest.fixture
def experiment() -> Experiment:
    return load_experiment(GRAPHS / "lead_follow.toml", overrides={"duration_s": 1.0})


floats = st.floats(allow_nan=True, allow_infinity=True, width=64)


@given(
    k=st.integers(0, 2**62),
    t=floats,
    values=st.lists(floats, max_size=6),
    named=st.booleans(),
)
def test_vector_json_is_what_json_dumps_gives(
    k: int, t: float, values: list[float], named: bool
) -> None:
    fields = [f"f{i}" for i in range(len(values))] if named else None
    message = {"k": k, "t": t, "values": values}
    if fields:
        message.update(zip(fields, values, strict=True))
    expected = json.dumps(json_safe(message), allow_nan=False, separators=(",", ":")).encode()
    quoted = [json.dumps(f) for f in fields] if fields else None
    assert vector_json(k, t, values, quoted) == expected


def stream_of_a_run(experiment: Experiment, ticks: int = 5) -> list[RecordBatch]:
    """The record stream a manager would hand over for ``ticks`` ticks of lead_follow (3
    agents), a batch per tick and the stream's end."""
    n = len(experiment.agent_names)
    writer = RecordWriter(experiment.agent_names)
    batches: list[RecordBatch] = []
    writer.status(0, T0, bus.encode_json({"state": "running", "k": 0, "t": 0.0}))
    for k in range(ticks):
        t = k * experiment.dt
        for i in range(n):
            u = None if k == 0 else np.array([0.1 * i, -0.1 * i])
            x_hat = None if k == 0 else np.array([float(k)])
            timing = bus.AgentTiming(compute_s=1e-4, actuate_s=2e-4, sense_s=3e-4, skipped=i)
            payload = bus.encode_vector(k, t, [float(i), float(k), math.nan if k == 2 else 0.5])
            writer.y(i, T0 + k, payload, bus.encode_report(timing, u, x_hat))
        answers = np.array([0.001, 0.002, math.nan])
        writer.tick(
            k,
            T0 + k,
            scheduled_s=t,
            send_delay_s=1e-5,
            completion_s=math.nan if k == 3 else 0.002,
            late=[2],
            missing=[2] if k == 4 else [],
            answer_s=answers,
        )
        batch = writer.take(T0 + k)
        assert batch is not None
        batches.append(batch)
    writer.vector(1, T0, "telemetry/battery", bus.encode_vector(4, 0.2, [11.9]))
    writer.event(T0, "f2", "lost", k=4, t=0.2, detail="killed")
    writer.event(T0, "orchestrator", "stopping", k=4, t=0.2, detail="completed")
    batches.append(writer.close(T0 + ticks))
    return batches


def check_recording(path: Path, experiment: Experiment) -> None:
    recording = read_recording(path)
    assert len(recording["/leader/y"]) == 5
    y = recording["/f1/y"][2]
    assert (y["k"], y["values"]) == (2, [1.0, 2.0, None])
    assert [m["k"] for m in recording["/f1/u"]] == [1, 2, 3, 4]
    u = recording["/f1/u"][0]
    assert u["t"] == pytest.approx(0.0) and u["values"] == [0.1, -0.1]
    assert recording["/f2/x_hat"][-1]["values"] == [4.0]
    ticks = recording["/orchestrator/ticks"]
    assert [m["k"] for m in ticks] == list(range(5))
    assert ticks[3]["completion_s"] is None and ticks[0]["completion_s"] == 0.002
    assert ticks[0]["late"] == ["f2"] and ticks[4]["missing"] == ["f2"]
    assert set(ticks[1]["agents"]) == {"leader", "f1"}  # f2 did not answer
    assert ticks[1]["agents"]["f1"] == {
        "answer_s": 0.002,
        "sense_s": 3e-4,
        "compute_s": 1e-4,
        "actuate_s": 2e-4,
        "link_s": 0.0,
        "bus_s": 0.002 - (1e-4 + 2e-4 + 3e-4),
        "skipped": 1,
        "retries": 0,
    }
    assert recording["/f1/telemetry/battery"][0]["values"] == [11.9]
    assert recording["/leader/status"][0]["state"] == "running"
    assert recording["/f2/status"][-1]["state"] == "lost"
    assert recording["/orchestrator/status"][-1]["detail"] == "completed"


def test_the_stream_in_process_gives_the_topics_of_the_contract(
    tmp_path: Path, experiment: Experiment
) -> None:
    path = tmp_path / "run.mcap"
    with Recorder(path, experiment, log_time_ns=T0) as recorder:
        stream = StreamRecorder(recorder, experiment)
        for batch in stream_of_a_run(experiment):
            hand_over(stream, batch)
        assert (stream.messages, stream.errors) == (5 * 4 + 4, 0)
    check_recording(path, experiment)


def test_the_stream_is_an_mcap_file_any_reader_opens(experiment: Experiment) -> None:
    batches = stream_of_a_run(experiment)
    assert [batch.seq for batch in batches] == list(range(1, 7))
    assert [batch.defines for batch in batches] == [True] + [False] * 4 + [True]
    reader = make_reader(io.BytesIO(b"".join(batch.data for batch in batches)))
    assert reader.get_header().profile == PROFILE
    messages = [(channel, message) for _, channel, message in reader.iter_messages()]
    topics = [channel.topic for channel, _ in messages]
    assert topics[:5] == [
        "agent/leader/status",
        "agent/leader/y",
        "agent/f1/y",
        "agent/f2/y",
        "orchestrator/ticks",
    ]
    assert topics.count("stream/batch") == 6 and topics[-1] == "stream/batch"
    channel, message = messages[2]
    assert channel.metadata == {"kind": "y", "agent": "1"}
    assert channel.message_encoding == "hilswarm.y" and message.log_time == T0
    vector_size = int.from_bytes(message.data[:4], "little")
    assert bus.unpack_vector(message.data[4 : 4 + vector_size])[0] == 0
    assert messages[0][0].message_encoding == "json"
    assert json.loads(messages[0][1].data)["state"] == "running"


def test_only_whole_batches_are_recorded_from_bytes_cut_anywhere(
    tmp_path: Path, experiment: Experiment
) -> None:
    batches = stream_of_a_run(experiment)
    data = b"".join(batch.data for batch in batches)
    ends = list(itertools.accumulate(len(batch.data) for batch in batches))
    # the last batch ends at its marker, the stream's last message (DataEnd and Footer follow)
    ends[-1] = max(stop for opcode, _, stop in records(data) if opcode == OP_MESSAGE)
    with Recorder(tmp_path / "run.mcap", experiment, log_time_ns=T0) as recorder:
        stream = StreamRecorder(recorder, experiment)
        for start in range(0, len(data), 7):
            stop = min(start + 7, len(data))
            seq = stream.feed(data[start:stop])
            whole = sum(1 for end in ends if end <= stop)  # batches complete so far
            recorded = sum(batch.count for batch in batches[:whole])
            if seq is not None:
                assert seq == whole
            assert stream.messages == recorded
            assert stream.pending == stop - (ends[whole - 1] if whole else 0)
        stream.feed(b"", whole=True)
        assert (stream.pending, stream.messages, stream.errors) == (0, 24, 0)
    check_recording(tmp_path / "run.mcap", experiment)


def test_the_recorder_process_records_the_stream_and_closes_the_file(
    tmp_path: Path, experiment: Experiment
) -> None:
    path = tmp_path / "out" / "run.mcap"
    recorder = RecorderProcess(path, experiment, log_time_ns=T0)
    try:
        recorder.wait_ready()
        for batch in stream_of_a_run(experiment):
            hand_over(recorder, batch)
    finally:
        assert recorder.close() == 0
    with path.open("rb") as f:
        assert make_reader(f).get_summary() is not None
    check_recording(path, experiment)
    topics = [topic for topic, _, _ in iter_messages(path)]
    assert topics[0] == "/experiment"
    # The run's start: every Frisbee bot's calibration, before any tick.
    assert topics[1:4] == ["/leader/calibration", "/f1/calibration", "/f2/calibration"]


def test_recorder_process_refuses_an_unwritable_file(
    tmp_path: Path, experiment: Experiment
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    recorder = RecorderProcess(blocker / "run.mcap", experiment, log_time_ns=T0)
    try:
        with pytest.raises(RecordingError, match="exited with status 1"):
            recorder.wait_ready(timeout_s=60)
    finally:
        assert recorder.close() != 0


def test_the_message_methods_only_keep_and_batches_follow_their_cuts(
    experiment: Experiment,
) -> None:
    """The manager's bus callbacks call the message methods under its lock: they must only keep
    (foxglove-sdk's log call lets go of the GIL); the MCAP records are made at the write, in the
    order of the cuts, whichever thread writes."""
    writer = RecordWriter(experiment.agent_names)
    payload = bus.encode_vector(0, 0.0, [1.0, 2.0, 3.0])
    writer.y(0, T0, payload, b"")
    writer.status(1, T0, bus.encode_json({"state": "running"}))
    assert writer.pending == 2
    first = writer.cut()
    writer.y(2, T0 + 1, payload, b"")
    second = writer.cut()
    assert writer.pending == 0 and len(first) == 2 and len(second) == 1
    batches = [writer.write(first, T0), writer.write_end(second, T0 + 1)]
    assert [(b.seq, b.count, b.defines) for b in batches if b] == [(1, 2, True), (2, 1, True)]
    reader = make_reader(io.BytesIO(b"".join(b.data for b in batches if b)))
    topics = [channel.topic for _, channel, _ in reader.iter_messages()]
    assert topics == [
        "agent/leader/y", "agent/f1/status", "stream/batch", "agent/f2/y", "stream/batch"
    ]  # fmt: skip
    assert writer.write([], T0) is None  # closed: nothing more

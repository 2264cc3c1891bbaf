"""The record stream and the recorder process: frames in, the MCAP topics of the contract out."""

from __future__ import annotations

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
    FrameReader,
    FrameRecorder,
    event_frame,
    status_frame,
    tick_frame,
    vector_frame,
    y_frame,
)
from hilswarm.orchestrator.recorder import Recorder
from hilswarm.orchestrator.recorder_process import RecorderProcess
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


def frames_of_a_run(experiment: Experiment, ticks: int = 5) -> bytes:
    """Frames a manager would send for ``ticks`` ticks of lead_follow (3 agents)."""
    n = len(experiment.agent_names)
    parts = [status_frame(0, T0, bus.encode_json({"state": "running", "k": 0, "t": 0.0}))]
    for k in range(ticks):
        t = k * experiment.dt
        for i in range(n):
            u = None if k == 0 else np.array([0.1 * i, -0.1 * i])
            x_hat = None if k == 0 else np.array([float(k)])
            timing = bus.AgentTiming(compute_s=1e-4, actuate_s=2e-4, sense_s=3e-4, skipped=i)
            payload = bus.encode_vector(k, t, [float(i), float(k), math.nan if k == 2 else 0.5])
            parts.append(y_frame(i, T0 + k, payload, bus.encode_report(timing, u, x_hat)))
        answers = np.array([0.001, 0.002, math.nan])
        parts.append(
            tick_frame(
                k,
                T0 + k,
                scheduled_s=t,
                send_delay_s=1e-5,
                completion_s=math.nan if k == 3 else 0.002,
                late=[2],
                missing=[2] if k == 4 else [],
                answer_s=answers,
            )
        )
    parts.append(vector_frame(1, T0, "telemetry/battery", bus.encode_vector(4, 0.2, [11.9])))
    parts.append(event_frame(T0, "f2", "lost", k=4, t=0.2, detail="killed"))
    parts.append(event_frame(T0, "orchestrator", "stopping", k=4, t=0.2, detail="completed"))
    return b"".join(parts)


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


def test_frames_in_process_give_the_topics_of_the_contract(
    tmp_path: Path, experiment: Experiment
) -> None:
    path = tmp_path / "run.mcap"
    with Recorder(path, experiment, log_time_ns=T0) as recorder:
        FrameRecorder(recorder, experiment).write(frames_of_a_run(experiment))
    check_recording(path, experiment)


def test_frame_reader_takes_bytes_cut_anywhere(experiment: Experiment) -> None:
    data = frames_of_a_run(experiment)
    whole = list(FrameReader().feed(data))
    reader = FrameReader()
    pieces = []
    for start in range(0, len(data), 7):
        pieces += list(reader.feed(data[start : start + 7]))
    assert pieces == whole and reader.pending == 0


def test_recorder_process_records_the_stream_and_closes_the_file(
    tmp_path: Path, experiment: Experiment
) -> None:
    path = tmp_path / "out" / "run.mcap"
    recorder = RecorderProcess(path, experiment, log_time_ns=T0)
    try:
        recorder.wait_ready()
        data = frames_of_a_run(experiment)
        recorder.write(data[:100])  # frames may be cut between writes
        recorder.write(data[100:])
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

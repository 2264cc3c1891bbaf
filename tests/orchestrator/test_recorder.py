"""Recorder: a run written to MCAP and read back (topics, fields, schemas, exit paths)."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import iter_messages, read_schemas
from hilswarm.orchestrator.experiment import Experiment, load_experiment
from hilswarm.orchestrator.recorder import Recorder
from mcap.reader import make_reader

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
T0 = 1_800_000_000_000_000_000  # a log time [ns, Unix epoch]


@pytest.fixture
def experiment() -> Experiment:
    return load_experiment(GRAPHS / "consensus_ring.toml", overrides={"duration_s": 1.0})


def record_run(path: Path, experiment: Experiment, ticks: int = 20) -> None:
    with Recorder(path, experiment) as recorder:
        recorder.add_topic("/a0/y", fields=["x", "y"])
        for name in experiment.agent_names:
            recorder.write_status(name, state="running", k=0, t=0.0, log_time_ns=T0)
        for k in range(ticks):
            t = k * experiment.dt
            log = T0 + k * 50_000_000
            for i, name in enumerate(experiment.agent_names):
                recorder.write_vector(
                    f"/{name}/y", k=k, t=t, values=np.array([i + k, -i]), log_time_ns=log
                )
                recorder.write_vector(f"/{name}/u", k=k, t=t, values=[0.5 * i], log_time_ns=log)
            recorder.write_ticks(
                k=k,
                t=t,
                log_time_ns=log,
                timings={
                    "completion_s": np.float64(0.001 + 1e-5 * k),
                    "late": [],
                    "agents": {"a0": {"sense_s": 1e-4, "compute_s": np.float32(2e-4)}},
                },
            )
        recorder.write_status(
            "a3", state="safe", k=ticks, t=1.0, log_time_ns=T0 + 10**9, detail="low battery"
        )


def test_run_round_trip(tmp_path: Path, experiment: Experiment) -> None:
    path = tmp_path / "runs" / "run.mcap"  # the folder is created
    record_run(path, experiment, ticks=20)
    messages = list(iter_messages(path))
    # /experiment comes first, with the file text, settings and graph as loaded.
    topic, log_time, first = messages[0]
    assert topic == "/experiment" and log_time == T0
    assert first["k"] == 0 and first["t"] == 0.0 and first["values"] == []
    assert first["name"] == "consensus_ring"
    assert first["text"] == experiment.source_text
    assert first["settings"]["duration_s"] == 1.0  # the override, as run
    assert first["graph"]["agents"] == list(experiment.agent_names)
    assert first["graph"]["adjacency"] == experiment.adjacency.tolist()
    assert first["agents"]["a0"]["vehicle_params"]["plant"] == "integrator"
    assert first["agents"]["a5"]["initial_state"] == [3.5, -0.5]

    by_topic: dict[str, list[dict]] = {}
    for topic, _, message in messages:
        by_topic.setdefault(topic, []).append(message)
    for name in experiment.agent_names:
        assert [m["k"] for m in by_topic[f"/{name}/y"]] == list(range(20))
        assert len(by_topic[f"/{name}/u"]) == 20
    y = by_topic["/a2/y"][7]
    assert y["values"] == [9.0, -2.0] and y["t"] == pytest.approx(7 * experiment.dt)
    named = by_topic["/a0/y"][3]
    assert named["x"] == 3.0 and named["y"] == 0.0  # entry names beside values
    ticks = by_topic["/orchestrator/ticks"]
    assert len(ticks) == 20
    assert ticks[5]["completion_s"] == pytest.approx(0.00105)
    assert ticks[5]["agents"]["a0"]["compute_s"] == pytest.approx(2e-4)
    assert ticks[5]["values"] == [] and ticks[5]["k"] == 5
    statuses = by_topic["/a3/status"]
    assert [s["state"] for s in statuses] == ["running", "safe"]
    assert statuses[-1]["detail"] == "low battery" and statuses[-1]["agent"] == "a3"

    schemas = read_schemas(path)
    assert schemas["/a0/y"]["properties"]["x"]["description"] == "values[0]"
    assert "state" in schemas["/a1/status"]["properties"]
    assert "graph" in schemas["/experiment"]["properties"]

    # A complete file: summary and statistics are there for seeking readers (Foxglove).
    with path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None
    assert summary.statistics.message_count == len(messages)
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}
    assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
    for schema in summary.schemas.values():
        json.loads(schema.data)


def test_experiment_message_can_be_written_up_front(tmp_path: Path, experiment: Experiment):
    path = tmp_path / "run.mcap"
    with Recorder(path, experiment, log_time_ns=T0 - 5):
        pass
    ((topic, log_time, message),) = list(iter_messages(path))
    assert topic == "/experiment" and log_time == T0 - 5
    assert message["name"] == "consensus_ring"


def test_empty_run_still_records_the_experiment(tmp_path: Path, experiment: Experiment):
    path = tmp_path / "run.mcap"
    recorder = Recorder(path, experiment)
    recorder.close()
    recorder.close()  # idempotent
    assert recorder.closed
    assert [topic for topic, _, _ in iter_messages(path)] == ["/experiment"]


def test_failure_inside_the_run_keeps_everything_recorded(
    tmp_path: Path, experiment: Experiment
) -> None:
    path = tmp_path / "run.mcap"
    with pytest.raises(RuntimeError, match="agent crashed"), Recorder(path, experiment) as rec:
        for k in range(500):
            rec.write_vector("/a0/y", k=k, t=k * 0.05, values=[k, 0], log_time_ns=T0 + k)
        raise RuntimeError("agent crashed")
    ks = [m["k"] for topic, _, m in iter_messages(path) if topic == "/a0/y"]
    assert ks == list(range(500))
    with path.open("rb") as handle:
        assert make_reader(handle).get_summary() is not None


def test_writing_after_close_and_bad_input_raise(tmp_path: Path, experiment: Experiment):
    recorder = Recorder(tmp_path / "run.mcap", experiment)
    with pytest.raises(RecordingError, match="starting with '/'"):
        recorder.write_vector("a0/y", k=0, t=0.0, values=[1], log_time_ns=T0)
    with pytest.raises(RecordingError, match="values must be numbers"):
        recorder.write_vector("/a0/y", k=0, t=0.0, values=["x"], log_time_ns=T0)
    with pytest.raises(RecordingError, match="clashes"):
        recorder.write_ticks(k=0, t=0.0, log_time_ns=T0, timings={"k": 3})
    recorder.close()
    with pytest.raises(RecordingError, match="closed"):
        recorder.write_status("a0", state="x", k=0, t=0.0, log_time_ns=T0)


def test_concurrent_writers(tmp_path: Path, experiment: Experiment) -> None:
    path = tmp_path / "run.mcap"
    per_thread = 300
    with Recorder(path, experiment, chunk_size=4096) as recorder:

        def write(name: str) -> None:
            for k in range(per_thread):
                recorder.write_vector(
                    f"/{name}/y", k=k, t=k * 0.05, values=[k, k], log_time_ns=T0 + k
                )

        threads = [threading.Thread(target=write, args=(n,)) for n in experiment.agent_names]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
        assert not any(thread.is_alive() for thread in threads)
        assert recorder.message_count == 1 + per_thread * len(threads)
    counts: dict[str, int] = {}
    for topic, _, _ in iter_messages(path):
        counts[topic] = counts.get(topic, 0) + 1
    assert all(counts[f"/{n}/y"] == per_thread for n in experiment.agent_names)

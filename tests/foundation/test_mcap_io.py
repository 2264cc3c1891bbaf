"""McapJsonWriter / readers: real MCAP files, read back with the mcap library."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import (
    McapJsonWriter,
    iter_messages,
    read_schemas,
    recover,
)
from mcap.reader import make_reader


def _write_run(path, n: int = 400, *, chunk_size: int = 1024) -> None:
    with McapJsonWriter(path, chunk_size=chunk_size) as writer:
        writer.add_topic("/a/y", fields=("x", "y", "psi"))
        writer.add_topic("/a/u")
        for k in range(n):
            writer.write("/a/y", k=k, t=0.1 * k, values=[k, -k, 0.5], log_time_ns=k * 100)
            writer.write("/a/u", k=k, t=0.1 * k, values=np.array([1.0, 2.0]), log_time_ns=k * 100)


def test_foxglove_encodings_and_schema(tmp_path) -> None:
    path = tmp_path / "run.mcap"
    _write_run(path, 10)
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == {"/a/y", "/a/u"}
        assert {c.message_encoding for c in channels.values()} == {"json"}
        schemas = summary.schemas
        assert {s.encoding for s in schemas.values()} == {"jsonschema"}
        y_schema = json.loads(schemas[channels["/a/y"].schema_id].data)
        assert summary.statistics.message_count == 20
    assert y_schema["required"] == ["k", "t", "values"]
    assert y_schema["properties"]["k"]["type"] == "integer"
    assert y_schema["properties"]["t"]["type"] == "number"
    assert y_schema["properties"]["values"]["type"] == "array"
    assert set(y_schema["properties"]) == {"k", "t", "values", "x", "y", "psi"}
    assert read_schemas(path)["/a/y"] == y_schema
    assert set(read_schemas(path)["/a/u"]["properties"]) == {"k", "t", "values"}


def test_messages_round_trip_with_named_fields(tmp_path) -> None:
    path = tmp_path / "run.mcap"
    _write_run(path, 3)
    messages = list(iter_messages(path))
    assert [(m[0], m[1]) for m in messages] == [
        ("/a/y", 0),
        ("/a/u", 0),
        ("/a/y", 100),
        ("/a/u", 100),
        ("/a/y", 200),
        ("/a/u", 200),
    ]
    assert messages[2][2] == {
        "k": 1,
        "t": 0.1,
        "values": [1.0, -1.0, 0.5],
        "x": 1.0,
        "y": -1.0,
        "psi": 0.5,
    }
    assert messages[3][2] == {"k": 1, "t": 0.1, "values": [1.0, 2.0]}
    only_u = list(iter_messages(path, topics=["/a/u"]))
    assert len(only_u) == 3 and {m[0] for m in only_u} == {"/a/u"}
    # the mcap library's own reader agrees
    with open(path, "rb") as stream:
        decoded = [json.loads(m.data) for _, _, m in make_reader(stream).iter_messages()]
    assert decoded == [m[2] for m in messages]


def test_nan_and_inf_become_null(tmp_path) -> None:
    path = tmp_path / "nan.mcap"
    with McapJsonWriter(path) as writer:
        writer.add_topic("/a/y", fields=("p", "q", "r"))
        writer.write(
            "/a/y",
            k=0,
            t=math.nan,
            values=[np.nan, np.inf, -np.inf],
            log_time_ns=0,
            extra=[1.0, float("nan")],
        )
        writer.write_json("/a/status", {"v": np.array([np.nan, 1.0]), "w": np.float32(2)}, 5)
    (_, _, y), (_, time_ns, status) = list(iter_messages(path))
    assert y == {
        "k": 0,
        "t": None,
        "values": [None, None, None],
        "p": None,
        "q": None,
        "r": None,
        "extra": [1.0, None],
    }
    assert status == {"v": [None, 1.0], "w": 2.0} and time_ns == 5
    with open(path, "rb") as stream:
        raw = [m.data for _, _, m in make_reader(stream).iter_messages()]
    assert raw and all(b"NaN" not in data and b"Infinity" not in data for data in raw)


def test_write_json_schema_rules(tmp_path) -> None:
    schema = {"type": "object", "properties": {"state": {"type": "string"}}}
    with McapJsonWriter(tmp_path / "s.mcap") as writer:
        writer.write_json("/experiment", {"name": "demo", "rate_hz": 10.0}, 0)
        writer.write_json("/a/status", {"state": "running"}, 1, schema)
        writer.write_json("/a/status", {"state": "stopped"}, 2)
        writer.write_json("/a/status", {"state": "again"}, 3, schema)
        with pytest.raises(RecordingError, match="another schema"):
            writer.write_json("/a/status", {"state": "x"}, 4, {"type": "object"})
        with pytest.raises(RecordingError, match="mapping"):
            writer.write_json("/a/status", ["not", "a", "dict"], 4)  # type: ignore[arg-type]
        with pytest.raises(RecordingError, match="cannot encode"):
            writer.write_json("/a/status", {"state": object()}, 4)
    schemas = read_schemas(tmp_path / "s.mcap")
    assert schemas["/a/status"] == schema and schemas["/experiment"] == {"type": "object"}


def test_bad_use_is_refused(tmp_path) -> None:
    writer = McapJsonWriter(tmp_path / "bad.mcap")
    with pytest.raises(RecordingError, match="not registered"):
        writer.write("/nope", k=0, t=0.0, values=[1.0], log_time_ns=0)
    with pytest.raises(RecordingError, match="start"):
        writer.add_topic("no_slash")
    with pytest.raises(RecordingError, match="other than"):
        writer.add_topic("/a/y", fields=("k",))
    writer.add_topic("/a/y", fields=("x", "y"))
    writer.add_topic("/a/y", fields=("x", "y"))  # same again: fine
    with pytest.raises(RecordingError, match="registered already"):
        writer.add_topic("/a/y", fields=("x",))
    with pytest.raises(RecordingError, match=r"expected 2 values \('x', 'y'\), got 3"):
        writer.write("/a/y", k=0, t=0.0, values=[1, 2, 3], log_time_ns=0)
    with pytest.raises(RecordingError, match="clashes"):
        writer.write("/a/y", k=0, t=0.0, values=[1, 2], log_time_ns=0, x=3)
    with pytest.raises(RecordingError, match="log_time_ns"):
        writer.write("/a/y", k=0, t=0.0, values=[1, 2], log_time_ns=-1)
    with pytest.raises(RecordingError, match="log_time_ns"):
        writer.write("/a/y", k=0, t=0.0, values=[1, 2], log_time_ns=1.5)  # type: ignore[arg-type]
    writer.close()
    writer.close()  # idempotent
    with pytest.raises(RecordingError, match="closed"):
        writer.write("/a/y", k=0, t=0.0, values=[1, 2], log_time_ns=0)
    with pytest.raises(RecordingError, match="chunk_size"):
        McapJsonWriter(tmp_path / "x.mcap", chunk_size=0)
    with pytest.raises(RecordingError, match="compression"):
        McapJsonWriter(tmp_path / "x.mcap", compression="gzip")


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_truncated_file_yields_complete_chunks(tmp_path, compression: str) -> None:
    path = tmp_path / "full.mcap"
    with McapJsonWriter(path, chunk_size=1024, compression=compression) as writer:
        writer.add_topic("/a/y", fields=("x", "y", "psi"))
        for k in range(400):
            writer.write("/a/y", k=k, t=0.1 * k, values=[k, -k, 0.5], log_time_ns=k * 100)
    full = list(iter_messages(path))
    assert len(full) == 400
    with open(path, "rb") as stream:
        chunks = sorted(
            make_reader(stream).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )
    assert len(chunks) > 4
    data = path.read_bytes()
    for i in (0, 1, len(chunks) // 2, len(chunks) - 1):
        # cut the file in the middle of chunk i: exactly the messages of chunks 0..i-1 remain
        cut_at = chunks[i].chunk_start_offset + chunks[i].chunk_length // 2
        cut = tmp_path / f"cut{i}.mcap"
        cut.write_bytes(data[:cut_at])
        expected = 0 if i == 0 else chunks[i - 1].message_end_time // 100 + 1
        partial = list(iter_messages(cut))
        assert partial == full[:expected]
        assert list(read_schemas(cut)) == (["/a/y"] if i > 0 else [])


def test_crash_mid_run_keeps_written_chunks(tmp_path) -> None:
    """Chunks reach the file while the writer is still open (no user-space buffering)."""
    path = tmp_path / "live.mcap"
    writer = McapJsonWriter(path, chunk_size=512)
    writer.add_topic("/a/u")
    for k in range(300):
        writer.write("/a/u", k=k, t=float(k), values=[float(k)], log_time_ns=k)
    snapshot = tmp_path / "snapshot.mcap"
    snapshot.write_bytes(path.read_bytes())  # what a crash right now would leave
    readable = list(iter_messages(snapshot))
    assert len(readable) > 250
    assert [m[2]["k"] for m in readable] == list(range(len(readable)))
    writer.close()
    recovered = tmp_path / "recovered.mcap"
    assert recover(snapshot, recovered) == len(readable)
    with open(recovered, "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary.statistics.message_count == len(readable)
    assert list(iter_messages(recovered)) == readable
    with pytest.raises(RecordingError, match="differ"):
        recover(recovered, recovered)


def test_every_message_validates_against_its_schema(tmp_path) -> None:
    jsonschema = pytest.importorskip("jsonschema")
    path = tmp_path / "valid.mcap"
    with McapJsonWriter(path) as writer:
        writer.add_topic("/a/y", fields=("x", "y"))
        writer.add_topic("/a/x_hat")
        for k in range(5):
            writer.write("/a/y", k=k, t=0.1 * k, values=[k, np.nan], log_time_ns=k)
            writer.write("/a/x_hat", k=k, t=0.1 * k, values=[], log_time_ns=k, phase="drive")
    schemas = read_schemas(path)
    for topic, _, message in iter_messages(path):
        jsonschema.Draft202012Validator.check_schema(schemas[topic])
        jsonschema.validate(message, schemas[topic], cls=jsonschema.Draft202012Validator)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"k": 1.5, "t": 0.0, "values": []}, schemas["/a/y"])

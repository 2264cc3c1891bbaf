"""recover: a real recorder process killed with SIGKILL mid-run, then rewritten and reopened."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import lz4.frame
import pytest
import zstandard
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.orchestrator.cli import main
from hilswarm.orchestrator.recover import MCAP_MAGIC, default_destination, recover
from mcap.reader import make_reader

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
CHUNK_SIZE = 4096
#: The writer is killed once the file holds at least this many bytes (many complete chunks).
KILL_AFTER_BYTES = 40 * CHUNK_SIZE

WRITER = textwrap.dedent(
    """
    import sys, time
    from hilswarm.orchestrator.experiment import load_experiment
    from hilswarm.orchestrator.recorder import Recorder

    experiment = load_experiment(sys.argv[2])
    deadline = time.monotonic() + 120.0  # bounded even if nobody kills it
    recorder = Recorder(sys.argv[1], experiment, chunk_size=int(sys.argv[3]))
    k = 0
    while k < 10_000_000 and time.monotonic() < deadline:
        for name in experiment.agent_names:
            recorder.write_vector(f"/{name}/y", k=k, t=k * 0.05, values=[k, -k],
                                  log_time_ns=1_800_000_000_000_000_000 + k)
        recorder.write_ticks(k=k, t=k * 0.05, log_time_ns=1_800_000_000_000_000_000 + k,
                             timings={"completion_s": 0.001})
        k += 1
    recorder.close()
    """
)


def messages_in_complete_chunks(data: bytes) -> int:
    """Count messages inside the complete chunk records of raw MCAP bytes (no mcap library)."""
    if not data.startswith(MCAP_MAGIC):
        raise ValueError("not MCAP")
    position, count = len(MCAP_MAGIC), 0
    while position + 9 <= len(data):
        opcode = data[position]
        length = int.from_bytes(data[position + 1 : position + 9], "little")
        end = position + 9 + length
        if end > len(data):
            break  # the cut record
        if opcode == 0x06:  # Chunk
            body = data[position + 9 : end]
            offset = 16  # message start and end times
            uncompressed_size = int.from_bytes(body[offset : offset + 8], "little")
            offset += 8 + 4  # size, crc
            name_length = int.from_bytes(body[offset : offset + 4], "little")
            offset += 4
            compression = body[offset : offset + name_length].decode()
            offset += name_length
            records_length = int.from_bytes(body[offset : offset + 8], "little")
            offset += 8
            if offset + records_length > len(body):
                break  # a chunk its writer had begun (all-ones sizes until it is finished)
            records = body[offset : offset + records_length]
            if compression == "zstd":
                records = zstandard.ZstdDecompressor().decompress(
                    records, max_output_size=uncompressed_size
                )
            elif compression == "lz4":
                records = lz4.frame.decompress(records)
            inner = 0
            while inner + 9 <= len(records):
                inner_length = int.from_bytes(records[inner + 1 : inner + 9], "little")
                count += records[inner] == 0x05
                inner += 9 + inner_length
        elif opcode == 0x05:  # a Message outside chunks
            count += 1
        position = end
    return count


def chunk_offsets(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of every complete chunk record."""
    position, chunks = len(MCAP_MAGIC), []
    while position + 9 <= len(data):
        length = int.from_bytes(data[position + 1 : position + 9], "little")
        end = position + 9 + length
        if end > len(data):
            break
        if data[position] == 0x06:
            chunks.append((position, end))
        position = end
    return chunks


@pytest.fixture(scope="module")
def killed_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recording whose writer process was killed with SIGKILL while writing."""
    path = tmp_path_factory.mktemp("killed") / "run.mcap"
    process = subprocess.Popen(
        [
            sys.executable,
            "-c",
            WRITER,
            str(path),
            str(GRAPHS / "consensus_ring.toml"),
            str(CHUNK_SIZE),
        ],
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            if path.exists() and path.stat().st_size >= KILL_AFTER_BYTES:
                break
            if process.poll() is not None:
                pytest.fail(f"writer exited early: {process.stderr.read().decode()}")
            time.sleep(0.02)
        else:
            pytest.fail("writer did not write enough within 60 s")
        assert process.poll() is None, "the writer must still be running when it is killed"
        os.killpg(process.pid, signal.SIGKILL)
        assert process.wait(timeout=10) == -signal.SIGKILL
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=10)
        process.stderr.close()
    return path


def test_killed_file_is_not_a_complete_mcap(killed_recording: Path) -> None:
    data = killed_recording.read_bytes()
    assert data.startswith(MCAP_MAGIC)
    assert not data.endswith(MCAP_MAGIC)  # no footer: the writer never finished
    with killed_recording.open("rb") as handle, pytest.raises(Exception):  # noqa: B017
        make_reader(handle).get_summary()


def test_recover_keeps_every_complete_chunk(killed_recording: Path, tmp_path: Path) -> None:
    data = killed_recording.read_bytes()
    expected = messages_in_complete_chunks(data)
    assert len(chunk_offsets(data)) >= 10
    target = tmp_path / "fixed.mcap"
    result = recover(killed_recording, target)
    assert result.messages == expected
    assert result.destination == target and result.source_bytes == len(data)
    assert result.topics["/experiment"] == 1
    # The writer wrote ticks in order; every tick of the kept chunks is there, without gaps.
    ks = [m["k"] for topic, _, m in iter_messages(target) if topic == "/orchestrator/ticks"]
    assert ks == list(range(len(ks))) and len(ks) > 100
    # The recovered file opens with the (seeking) mcap reader: summary, statistics, footer.
    with target.open("rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics.message_count == expected
        assert sum(1 for _ in reader.iter_messages()) == expected
    assert target.read_bytes().endswith(MCAP_MAGIC)


def test_a_cut_inside_a_chunk_drops_only_that_chunk(killed_recording: Path, tmp_path: Path):
    data = killed_recording.read_bytes()
    start, end = chunk_offsets(data)[5]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: (start + end) // 2])
    expected = messages_in_complete_chunks(data[:start])
    assert expected > 0
    result = recover(cut)
    assert result.destination == default_destination(cut) == tmp_path / "cut.recovered.mcap"
    assert result.messages == expected


#: A Chunk record as foxglove-sdk's (mcap-rust) writer leaves it when killed while the chunk is
#: open: its header holds all-ones sizes until the chunk is finished.
UNFINISHED_CHUNK_BODY = (
    bytes(16)  # message start and end times
    + b"\xff" * 8  # uncompressed size
    + b"\xff" * 4  # uncompressed CRC
    + len(b"zstd").to_bytes(4, "little")
    + b"zstd"
    + b"\xff" * 8  # records length
    + bytes(64)  # the compressed records written so far
)


def test_a_chunk_the_writer_had_begun_is_dropped_without_a_traceback(
    killed_recording: Path, tmp_path: Path
) -> None:
    data = killed_recording.read_bytes()
    start, _ = chunk_offsets(data)[5]
    begun = tmp_path / "begun.mcap"
    record = b"\x06" + len(UNFINISHED_CHUNK_BODY).to_bytes(8, "little") + UNFINISHED_CHUNK_BODY
    begun.write_bytes(data[:start] + record)
    expected = messages_in_complete_chunks(data[:start])
    assert expected > 0 and messages_in_complete_chunks(begun.read_bytes()) == expected
    assert recover(begun).messages == expected
    assert main(["recover", str(begun), "--in-place"]) == 0


def test_cli_recover_in_place_and_output(
    killed_recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(killed_recording.read_bytes())
    expected = messages_in_complete_chunks(copy.read_bytes())
    assert main(["recover", str(copy), "-o", str(tmp_path / "out.mcap")]) == 0
    out = capsys.readouterr().out
    assert f"recovered {expected} messages" in out and "/orchestrator/ticks" in out
    assert main(["recover", str(copy), "--in-place"]) == 0
    capsys.readouterr()
    with copy.open("rb") as handle:
        assert make_reader(handle).get_summary().statistics.message_count == expected
    assert not list(tmp_path.glob(".*recovering"))


def test_not_mcap_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("hello, not a recording")
    with pytest.raises(RecordingError, match="is not an MCAP file"):
        recover(text)
    assert main(["recover", str(text)]) == 2
    err = capsys.readouterr().err
    assert "is not an MCAP file" in err and "Traceback" not in err
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match="empty file"):
        recover(empty)
    with pytest.raises(RecordingError, match="does not exist"):
        recover(tmp_path / "missing.mcap")


def test_destination_must_differ(killed_recording: Path) -> None:
    with pytest.raises(RecordingError, match="is the source"):
        recover(killed_recording, killed_recording)
    with pytest.raises(RecordingError, match="not both"):
        recover(killed_recording, killed_recording.with_suffix(".x"), in_place=True)

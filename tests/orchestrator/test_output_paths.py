"""Output paths are checked before anything is written or started (exit status 2, one line
naming the path and the reason); "the disk is full" only for ENOSPC/EDQUOT; the recorder
process fails cleanly where its file cannot be created."""

from __future__ import annotations

import errno
import logging
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.pins import PROFILES
from hilswarm.orchestrator.cli import main
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.output_paths import (
    OutputPathError,
    check_output_file,
    check_output_folder,
    is_no_space,
)
from hilswarm.orchestrator.recorder import Recorder
from hilswarm.orchestrator.recorder_process import RecorderProcess

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))
from swarm_harness import finish_in_group

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
CLI = (sys.executable, "-m", "hilswarm.orchestrator.cli")
TIMEOUT_S = 120
#: A folder nothing can be created in, even by root (procfs).
UNWRITABLE = Path("/proc")


def hilswarm(*args: str, cwd: Path, wrap: tuple[str, ...] = ()) -> tuple[int, str]:
    """The CLI in a process group of its own (killed after TIMEOUT_S): status, output."""
    return finish_in_group([*wrap, *CLI, *args], cwd=cwd, timeout_s=TIMEOUT_S)


def read_only_mount_wrap(folder: Path) -> tuple[str, ...]:
    """A command prefix that runs the rest with a read-only tmpfs on ``folder`` (a mount
    namespace of its own); skips the test where that cannot be done."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare command: no read-only mount")
    folder.mkdir(exist_ok=True)
    script = f'mount -t tmpfs -o ro,size=64k tmpfs "{folder}" || exit 99; exec "$@"'
    probe = subprocess.run(
        ["unshare", "-m", "sh", "-c", script, "sh", "true"],
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    if probe.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs: {probe.stderr.strip()}")
    return ("unshare", "-m", "sh", "-c", script, "sh")


# -- the helper ------------------------------------------------------------------------------


def test_a_writable_file_or_folder_passes_and_nothing_is_left(tmp_path: Path) -> None:
    check_output_file(tmp_path / "new" / "deeper" / "run.mcap", what="the recording")
    check_output_folder(tmp_path / "plots" / "sub", what="the plots")
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"x")
    check_output_file(existing, what="the recording")  # replacing is --force's business
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.mcap"]  # no folder, no probe


@pytest.mark.parametrize(
    ("target", "reason"),
    [
        ("folder", "it is a directory"),
        ("file/x.mcap", "file is not a folder"),
        ("file/a/b.mcap", "file is not a folder"),
    ],
)
def test_a_file_path_that_cannot_be_written_is_refused(
    tmp_path: Path, target: str, reason: str
) -> None:
    (tmp_path / "folder").mkdir()
    (tmp_path / "file").write_bytes(b"x")
    with pytest.raises(OutputPathError, match=f"cannot write the recording to .*{target}: .*"):
        check_output_file(tmp_path / target, what="the recording")
    with pytest.raises(OutputPathError, match=reason):
        check_output_file(tmp_path / target, what="the recording")


def test_a_folder_nothing_can_be_created_in_is_refused() -> None:
    with pytest.raises(OutputPathError, match=r"cannot write the recording to /proc/x\.mcap: "):
        check_output_file(UNWRITABLE / "x.mcap", what="the recording")
    with pytest.raises(OutputPathError, match="cannot create files in /proc"):
        check_output_folder(UNWRITABLE / "plots", what="the plots")


def test_a_file_where_a_folder_is_wanted_is_refused(tmp_path: Path) -> None:
    (tmp_path / "file").write_bytes(b"x")
    with pytest.raises(OutputPathError, match="it is not a folder"):
        check_output_folder(tmp_path / "file", what="the plots")


def test_only_enospc_and_edquot_are_a_full_disk() -> None:
    assert is_no_space(OSError(errno.ENOSPC, "No space left on device"))
    assert is_no_space(OSError(errno.EDQUOT, "Disk quota exceeded"))
    wrapped = RecordingError("writing run.mcap failed")
    wrapped.__cause__ = RuntimeError("No space left on device (os error 28)")
    assert is_no_space(wrapped)
    assert not is_no_space(OSError(errno.ENOENT, "No such file or directory"))
    assert not is_no_space(RecordingError("cannot create x: No such file (os error 2)"))
    assert not is_no_space(OSError(errno.EFBIG, "File too large"))
    assert not is_no_space(RuntimeError("no errno at all"))
    logged = 'McapError(Io(Os { code: 28, kind: StorageFull, message: "No space left" }))'
    assert is_no_space(logged) and not is_no_space(logged.replace("28", "2"))


def test_a_recorder_process_that_cannot_create_its_file_fails_cleanly(tmp_path: Path) -> None:
    """Past the command's check (e.g. a folder made read-only meanwhile): the failure is named,
    it is not called a full disk, and close() neither raises nor leaves anything."""
    experiment = load_experiment(GRAPHS / "lead_follow.toml", overrides={"duration_s": 1.0})
    failures: list[str] = []
    recorder = RecorderProcess(
        UNWRITABLE / "hilswarm-test.mcap",
        experiment,
        log_time_ns=1,
        staged=True,
        on_failure=failures.append,
    )
    try:
        with pytest.raises(RecordingError, match="recorder process"):
            recorder.wait_ready(timeout_s=60)
    finally:
        code = recorder.close()
    assert code not in (0, None)
    assert failures, "on_failure was not called"
    assert "disk is full" not in failures[0], failures
    assert "No such file or directory" in failures[0], failures


# -- hilswarm run --out ----------------------------------------------------------------------


RING = str(GRAPHS / "consensus_ring.toml")


@pytest.mark.parametrize(
    ("out", "extra", "reason"),
    [
        ("file.mcap/x.mcap", (), "file.mcap is not a folder"),
        ("sub", ("--force",), "sub: it is a directory"),
        ("sub", (), "sub: it is a directory"),
        (str(UNWRITABLE / "x.mcap"), (), "cannot create files in /proc"),
    ],
)
def test_run_refuses_an_out_it_cannot_write_before_anything_starts(
    tmp_path: Path, out: str, extra: tuple[str, ...], reason: str
) -> None:
    (tmp_path / "file.mcap").write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    code, output = hilswarm("run", RING, "--duration", "1", "--out", out, *extra, cwd=tmp_path)
    assert code == 2, output
    lines = output.strip().splitlines()
    assert len(lines) == 1, output  # nothing started: no agent, no bus, no summary
    assert lines[0].startswith(f"hilswarm run: cannot write the recording to {out}"), output
    assert reason in lines[0], output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.mcap", "sub"]
    assert not any((tmp_path / "sub").iterdir())


def test_run_refuses_an_out_in_a_read_only_folder(tmp_path: Path) -> None:
    folder = tmp_path / "ro"
    wrap = read_only_mount_wrap(folder)
    out = folder / "x.mcap"
    code, output = hilswarm("run", RING, "--duration", "1", "--out", str(out), cwd=tmp_path,
                            wrap=wrap)  # fmt: skip
    assert code == 2, output
    assert output.strip() == (
        f"hilswarm run: cannot write the recording to {out}: cannot create files in {folder} "
        "(Read-only file system)"
    ), output


# -- plot, replay, new, calibrate ------------------------------------------------------------


@pytest.fixture(scope="module")
def run_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real recording of the ring example (the CLI's run, one second)."""
    folder = tmp_path_factory.mktemp("recording")
    code, output = hilswarm("run", RING, "--duration", "1", "--out", "r1.mcap", cwd=folder)
    assert code == 0, output
    return folder / "r1.mcap"


@pytest.fixture
def tickless(tmp_path: Path) -> Path:
    """A recording cut before its first tick: ``/experiment`` only, and no footer."""
    whole = tmp_path / "whole.mcap"
    with Recorder(whole, load_experiment(GRAPHS / "consensus_ring.toml")):
        pass
    cut = tmp_path / "cut.mcap"
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) - 40])  # the footer and the end of the summary
    whole.unlink()
    return cut


def command_folders(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.is_dir())


@pytest.mark.parametrize("command", ["plot", "replay"])
def test_plot_and_replay_name_what_the_input_is(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = tmp_path / "x.toml"
    text.write_text(Path(RING).read_text(encoding="utf-8"), encoding="utf-8")
    assert main([command, str(text)]) == 2
    err = capsys.readouterr().err
    assert f"hilswarm {command}: {text} is not an MCAP file" in err, err
    folder = tmp_path / "somedir"
    folder.mkdir()
    assert main([command, str(folder)]) == 2
    assert f"{folder} is a directory, not an MCAP file" in capsys.readouterr().err
    assert command_folders(tmp_path) == ["somedir"]  # no output folder left


def test_plot_of_a_recording_without_data_warns_once_and_leaves_no_folder(
    tickless: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    with caplog.at_level(logging.WARNING):
        assert main(["plot", str(tickless)]) == 1
    assert f"no plottable data in {tickless}" in capsys.readouterr().out
    warnings = [r.getMessage() for r in caplog.records if "truncated" in r.getMessage()]
    assert len(warnings) == 1, warnings
    assert command_folders(tickless.parent) == []


def test_replay_of_a_recording_without_ticks_says_so(
    tickless: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(tickless)]) == 1
    assert f"hilswarm replay: no ticks to replay in {tickless}" in capsys.readouterr().err
    assert command_folders(tickless.parent) == []


@pytest.mark.parametrize(
    "out",
    [
        ("r1.mcap", "r1.mcap: it is not a folder"),
        ("r1.mcap/p", "is not a folder"),
        (str(UNWRITABLE / "p"), "cannot create files in /proc"),
    ],
)
@pytest.mark.parametrize("command", [("plot", "the plots"), ("replay", "the replay plots")])
def test_plot_and_replay_refuse_an_out_they_cannot_write(
    run_recording: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    command: tuple[str, str],
    out: tuple[str, str],
) -> None:
    (command, what), (out, reason) = command, out
    recording = tmp_path / "r1.mcap"
    recording.write_bytes(run_recording.read_bytes())
    target = out if out.startswith("/") else str(tmp_path / out)
    assert main([command, str(recording), "--out", target]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"hilswarm {command}: cannot write {what} to {target}: "), err
    assert reason in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r1.mcap"]


def test_plot_and_replay_of_a_real_recording_still_write(
    run_recording: Path, tmp_path: Path
) -> None:
    assert main(["plot", str(run_recording), "--out", str(tmp_path / "p" / "q")]) == 0
    assert (tmp_path / "p" / "q" / "outputs.png").is_file()
    assert main(["replay", str(run_recording), "--out", str(tmp_path / "r")]) == 0
    assert sorted(p.name for p in (tmp_path / "r").iterdir())[0].startswith("replay_")


@pytest.mark.parametrize("profile", ["mega", ""])
def test_new_refuses_an_unknown_board_profile(
    profile: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["new", "vehicle", "rover2", "--profile", profile, "--dir", str(tmp_path)]) == 2
    known = ", ".join(PROFILES)
    assert f"unknown board profile {profile!r} (known: {known})" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("folder", "reason"),
    [
        ("file", "file: it is not a folder"),
        ("file/sub", "file is not a folder"),
        (str(UNWRITABLE / "x"), "cannot create files in /proc"),
    ],
)
def test_new_refuses_a_dir_it_cannot_write(
    folder: str, reason: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "file").write_bytes(b"x")
    target = folder if folder.startswith("/") else str(tmp_path / folder)
    assert main(["new", "vehicle", "rover3", "--dir", target]) == 2
    err = capsys.readouterr().err
    assert f"hilswarm new: cannot write the new files to {target}: " in err, err
    assert reason in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.parametrize(
    ("plot", "reason"),
    [("somedir", "it is a directory"), (str(UNWRITABLE / "x.png"), "cannot create files")],
)
def test_calibrate_checks_the_plot_before_writing_anything(
    plot: str, reason: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("pwm,v_left\n-255,-0.2\n0,0\n128,0.1\n255,0.2\n", encoding="utf-8")
    (tmp_path / "somedir").mkdir()
    target = plot if plot.startswith("/") else str(tmp_path / plot)
    output = tmp_path / "cal3.toml"
    args = ["calibrate", str(pairs), "--input", "v_left", "-o", str(output), "--plot", target]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"hilswarm calibrate: cannot write the plot to {target}: " in err and reason in err
    assert not output.exists()

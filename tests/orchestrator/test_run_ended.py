"""``hilswarm stop`` / ``set`` against a run that ends while they reach for it: its registry
entry says it is stopping (or it is gone) and its bus is closed. They say so instead of
blaming the credentials: stop and e-stop got what they asked for (exit 0), set and pause are
too late (exit 2); a run that is still running but cannot be reached stays a failure (1).

In-process, with a registry of the test's own holding an entry of this very process (so it
counts as alive) whose endpoint is a closed loopback port: nothing listens there.
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from hilswarm.orchestrator.cli import main
from hilswarm.orchestrator.run_registry import RunEntry, RunRecord


def _closed_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture
def entry(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> RunRecord:
    runtime = tmp_path / "xdg"
    runtime.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    record = RunRecord(
        RunEntry(
            name="ring",
            run_id="0badc0de",
            endpoints=[f"tcp/127.0.0.1:{_closed_port()}"],
            pid=0,
            mode="lockstep",
            agents={"a0": "running"},
            secure=False,
        )
    )
    record.write()
    return record


@pytest.mark.parametrize(
    ("args", "code", "said"),
    [
        (["stop", "ring"], 0, "ring: ring (run 0badc0de) is stopping already"),
        (["stop", "ring", "--estop"], 0, "ring: ring (run 0badc0de) is stopping already"),
        (["stop", "ring", "--pause"], 2, "ring (run 0badc0de) is stopping: nothing to pause"),
        (["set", "ring", "a0", "gain=1"], 2, "ring (run 0badc0de) is stopping: nothing to set"),
    ],
)
def test_a_stopping_run_is_said_to_be_stopping(
    entry: RunRecord, args: list[str], code: int, said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    entry.entry.state = "stopping"
    entry.write()
    assert main([*args, "--timeout", "2"]) == code
    captured = capsys.readouterr()
    assert said in captured.out + captured.err, captured
    assert "credentials" not in captured.err and "Traceback" not in captured.err


def test_a_running_run_that_cannot_be_reached_is_still_a_failure(
    entry: RunRecord, capsys: pytest.CaptureFixture[str]
) -> None:
    entry.entry.state = "running"
    entry.write()
    assert main(["stop", "ring", "--timeout", "2"]) == 1
    err = capsys.readouterr().err
    assert "stopping" not in err and "Traceback" not in err, err

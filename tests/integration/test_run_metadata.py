"""The run's MCAP metadata record (``hilswarm.run``, docs/recording.md "Run metadata"), read
back with the mcap package's own reader from the recording of a short real run."""

from __future__ import annotations

import json
import re
import subprocess
from importlib import metadata as importlib_metadata
from pathlib import Path

import pytest
from hilswarm.orchestrator.record_content import RECORDED_PACKAGES, RUN_METADATA
from mcap.reader import make_reader
from swarm_harness import REPO, RunProcess, read_recording

pytestmark = pytest.mark.integration

AGENTS = ("leader", "f1", "f2")


def head_revision() -> str:
    """``git rev-parse HEAD`` of the checkout the tests run from ("" outside git)."""
    try:
        done = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "HEAD"],
            capture_output=True, text=True, timeout=10, check=False,
        )  # fmt: skip
    except OSError:  # no git at all
        return ""
    return done.stdout.strip() if done.returncode == 0 else ""


def test_run_metadata_record_holds_the_experiment_code_packages_calibrations_and_seed(
    tmp_path: Path, runs: list[RunProcess]
) -> None:
    text = (REPO / "graphs" / "lead_follow.toml").read_text(encoding="utf-8")
    text = text.replace('mode = "lockstep"', 'mode = "lockstep"\nseed = 4242', 1)
    experiment = tmp_path / "lead_follow.toml"
    experiment.write_text(text, encoding="utf-8")
    run = RunProcess(tmp_path, experiment, "--duration", "1")
    runs.append(run)
    assert run.wait(180) == 0, run.output()

    with run.out.open("rb") as stream:
        records = [record for record in make_reader(stream).iter_metadata()]
    assert [r.name for r in records] == [RUN_METADATA], [r.name for r in records]
    meta = records[0].metadata
    assert all(isinstance(v, str) for v in meta.values()), meta

    assert Path(meta["experiment_file"]).resolve() == experiment.resolve()
    assert meta["experiment_text"] == text
    assert meta["seed"] == "4242"

    head = head_revision()
    if head:  # a git checkout: its HEAD, "+dirty" when it has changes
        assert re.fullmatch(rf"{head}(\+dirty)?", meta["git_revision"]), meta["git_revision"]
    else:
        assert meta["git_revision"] == ""

    packages = json.loads(meta["packages"])
    assert set(packages) == set(RECORDED_PACKAGES), packages
    for name in ("hilswarm", "numpy", "eclipse-zenoh", "mcap"):
        assert packages[name] == importlib_metadata.version(name), name

    # Every Frisbee runs with its vehicle's default calibration: the same object as the
    # /<agent>/calibration message of the recording (without the fields every message has).
    calibrations = json.loads(meta["calibrations"])
    assert set(calibrations) == set(AGENTS), calibrations
    recording = read_recording(run.out)
    for agent in AGENTS:
        (message,) = recording[f"/{agent}/calibration"]
        envelope = {"k", "t", "values", "wall_ns"}
        assert calibrations[agent] == {k: v for k, v in message.items() if k not in envelope}
        assert calibrations[agent]["inputs"], agent


def test_a_run_without_seed_records_an_empty_one(tmp_path: Path, runs: list[RunProcess]) -> None:
    run = RunProcess(tmp_path, REPO / "graphs" / "lead_follow.toml", "--duration", "0.5")
    runs.append(run)
    assert run.wait(180) == 0, run.output()
    with run.out.open("rb") as stream:
        (record,) = list(make_reader(stream).iter_metadata())
    assert record.name == RUN_METADATA
    assert record.metadata["seed"] == ""
    assert record.metadata["experiment_text"] == (REPO / "graphs" / "lead_follow.toml").read_text(
        encoding="utf-8"
    )

"""hilswarm plot: PNG figures from a real recording."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.errors import RecordingError
from hilswarm.orchestrator.cli import main
from hilswarm.orchestrator.experiment import load_experiment
from hilswarm.orchestrator.plotting import load_recording, plot_recording, tick_latencies
from hilswarm.orchestrator.recorder import Recorder

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
T0 = 1_800_000_000_000_000_000


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC), f"{path} is not a PNG"
    return struct.unpack(">II", data[16:24])


@pytest.fixture(scope="module")
def consensus_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A consensus run of the ring example (agents integrated here), recorded with Recorder."""
    experiment = load_experiment(GRAPHS / "consensus_ring.toml")
    path = tmp_path_factory.mktemp("plot") / "ring.mcap"
    x = np.array([spec.initial_state for spec in experiment.agents])
    a = experiment.adjacency.astype(float)
    laplacian = np.diag(a.sum(axis=1)) - a
    with Recorder(path, experiment) as recorder:
        for name in experiment.agent_names:
            recorder.add_topic(f"/{name}/y", fields=["px", "py"])
        for k in range(experiment.n_ticks):
            t, log = k * experiment.dt, T0 + k * 50_000_000
            u = -laplacian @ x
            for i, name in enumerate(experiment.agent_names):
                recorder.write_vector(f"/{name}/y", k=k, t=t, values=x[i], log_time_ns=log)
                recorder.write_vector(f"/{name}/u", k=k, t=t, values=u[i], log_time_ns=log)
            recorder.write_ticks(
                k=k, t=t, log_time_ns=log, timings={"completion_s": 0.001 + 0.0001 * (k % 7)}
            )
            x = x + experiment.dt * u
    return path


def test_load_recording(consensus_recording: Path) -> None:
    data = load_recording(consensus_recording)
    assert sorted(data.outputs) == [f"a{i}" for i in range(6)]
    series = data.outputs["a5"]
    assert series.names == ("px", "py")
    assert series.values.shape == (200, 2)
    assert series.values[0].tolist() == [3.5, -0.5]
    assert np.allclose(series.values[-1], [0.5, 0.0], atol=1e-3)
    assert data.inputs["a0"].names == ("values[0]", "values[1]")
    assert data.experiment is not None and data.experiment["name"] == "consensus_ring"
    k, latency, key = tick_latencies(data.ticks)
    assert key == "completion_s" and latency.shape == k.shape == (200,)


def test_a_recording_split_into_segments_is_read_whole(tmp_path: Path) -> None:
    """run.mcap + run.1.mcap (a restarted recorder): one series, each tick once."""
    experiment = load_experiment(GRAPHS / "consensus_ring.toml")
    path = tmp_path / "run.mcap"
    for segment, ticks in ((path, range(0, 60)), (tmp_path / "run.1.mcap", range(55, 100))):
        with Recorder(segment, experiment) as recorder:  # 55..59 in both: read once
            for k in ticks:
                recorder.write_vector("/a0/y", k=k, t=k * 0.1, values=[k, -k], log_time_ns=T0 + k)
                recorder.write_ticks(k=k, t=k * 0.1, log_time_ns=T0 + k, timings={})
    data = load_recording(path)
    assert data.outputs["a0"].values[:, 0].tolist() == list(range(100))
    assert [tick["k"] for tick in data.ticks] == list(range(100))


def test_plot_writes_every_figure(consensus_recording: Path, tmp_path: Path) -> None:
    written = plot_recording(consensus_recording, tmp_path / "plots")
    assert [p.name for p in written] == ["outputs.png", "inputs.png", "paths.png", "ticks.png"]
    for path in written:
        width, height = png_size(path)
        assert width > 300 and height > 300


def test_plot_skips_what_is_not_recorded(tmp_path: Path) -> None:
    experiment = load_experiment(GRAPHS / "spring_mass_damper.toml")
    path = tmp_path / "smd.mcap"
    with Recorder(path, experiment) as recorder:
        for k in range(10):
            recorder.write_vector(
                "/smd/y", k=k, t=0.1 * k, values=[4 - k, 0, -4 + k, 0], log_time_ns=T0 + k
            )
    written = plot_recording(path, tmp_path / "out", xy=(0, 2))
    assert [p.name for p in written] == ["outputs.png", "paths.png"]  # no u, no ticks


def test_plot_cli(consensus_recording: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "cli"
    assert main(["plot", str(consensus_recording), "--out", str(out), "--agent", "a0"]) == 0
    printed = capsys.readouterr().out.split()
    assert str(out / "paths.png") in printed
    assert main(["plot", str(consensus_recording), "--out", str(out), "--xy", "0"]) == 2
    assert "--xy must be two indices" in capsys.readouterr().err
    assert main(["plot", str(tmp_path / "missing.mcap"), "--out", str(out)]) == 2


def test_bad_xy_raises(consensus_recording: Path, tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="xy must be two entry indices"):
        plot_recording(consensus_recording, tmp_path, xy=(0, -1))

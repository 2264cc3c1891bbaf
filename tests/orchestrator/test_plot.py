"""hilswarm plot: PNG figures from a real recording."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.errors import RecordingError
from hilswarm.orchestrator import plotting
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
    assert "--xy must be two entries of y" in capsys.readouterr().err
    assert main(["plot", str(tmp_path / "missing.mcap"), "--out", str(out)]) == 2


def test_bad_xy_raises(consensus_recording: Path, tmp_path: Path) -> None:
    with pytest.raises(
        RecordingError, match=r"y has no entry -1; valid: indices 0\.\.1 or names px"
    ):
        plot_recording(consensus_recording, tmp_path, xy=(0, -1))


@pytest.fixture(scope="module")
def frisbee_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A lead/follow-like recording with names, units, a heading past ±π, a safe entry, an
    e-stop, the run's stop (every agent safe) and the tick ledger."""
    experiment = load_experiment(GRAPHS / "lead_follow.toml")
    path = tmp_path_factory.mktemp("plot") / "lf.mcap"
    units = {"x": "m", "y": "m", "psi": "rad"}
    with Recorder(path, experiment, log_time_ns=T0) as recorder:
        recorder.write_message(
            "/experiment",
            {"k": 0, "t": 0.0, "values": [], "name": "lf",
             "settings": {"rate_hz": experiment.rate_hz},
             "graph": experiment.graph_dict(),
             "agents": {s.name: {"params": s.params} for s in experiment.agents}},
            log_time_ns=T0,
        )  # fmt: skip
        for name in experiment.agent_names:
            recorder.add_topic(f"/{name}/y", fields=["x", "y", "psi"], units=units)
            recorder.add_topic(
                f"/{name}/u",
                fields=["v_left", "v_right"],
                units={"v_left": "m/s", "v_right": "m/s"},
            )
        for k in range(40):
            t = k * experiment.dt
            psi = 3.0 + 0.05 * k  # crosses +π: wrapped in the file, unwrapped in the plot
            wrapped = (psi + np.pi) % (2 * np.pi) - np.pi
            for name in experiment.agent_names:
                recorder.write_vector(f"/{name}/y", k=k, t=t, values=[t, 0.0, wrapped],
                                      log_time_ns=T0 + k)  # fmt: skip
                recorder.write_vector(f"/{name}/u", k=k, t=t, values=[0.1, 0.1],
                                      log_time_ns=T0 + k)  # fmt: skip
            ledger = {"answer_s": 0.004, "compute_s": 0.001, "actuate_s": 0.0002,
                      "link_s": 0.002, "sense_s": 0.0003, "bus_s": 0.0005, "skipped": 0,
                      "retries": 0}  # fmt: skip
            recorder.write_ticks(
                k=k, t=t, log_time_ns=T0 + k,
                timings={"completion_s": 0.004, "agents": {"leader": ledger, "f1": ledger}},
            )  # fmt: skip
        recorder.write_status("f1", state="safe", k=20, t=1.0, log_time_ns=T0, detail="battery")
        recorder.write_status(
            "orchestrator", state="estop", k=30, t=1.5, log_time_ns=T0, detail="button"
        )
        recorder.write_status(
            "orchestrator", state="stopping", k=39, t=1.95, log_time_ns=T0, detail="e-stop"
        )
        for name in experiment.agent_names:  # the run's orderly end: never marked
            recorder.write_status(
                name, state="safe", k=39, t=1.95, log_time_ns=T0, detail="completed"
            )
    return path


def test_plots_carry_units_unwrap_angles_and_mark_events(frisbee_recording: Path) -> None:
    from hilswarm.orchestrator import plotting

    data = plotting.load_recording(frisbee_recording)
    assert [(e.state, e.agent, e.t) for e in data.events] == [
        ("safe", "f1", 1.0), ("estop", "orchestrator", 1.5),
    ]  # fmt: skip
    outputs = plotting._signals_figure(data, data.outputs, "outputs", True)
    assert [a.get_ylabel() for a in outputs.axes] == ["x [m]", "y [m]", "psi [rad]"]
    assert all(a.get_xlabel() in ("", "experiment time t [s]") for a in outputs.axes)
    heading = outputs.axes[2].lines[0].get_ydata()
    assert np.all(np.abs(np.diff(heading)) < 0.1)  # no jump at ±π
    inputs = plotting._signals_figure(data, data.inputs, "inputs", False)
    assert [a.get_ylabel() for a in inputs.axes] == ["v_left [m/s]", "v_right [m/s]"]
    ticks = plotting._ticks_figure(data, "ticks")
    latency = plotting._latency_figure(data, "ledger")
    for figure in (outputs, inputs, ticks, latency):
        for axis in figure.axes:
            if axis.get_xlabel() != "experiment time t [s]":
                continue
            marks = {
                round(line.get_xdata()[0], 6)
                for line in axis.lines
                if line.get_linestyle() == ":" and len(set(line.get_xdata())) == 1
            }
            assert {1.0, 1.5} <= marks, (figure.texts, axis.get_ylabel())
    deadline = [line for line in ticks.axes[0].lines if line.get_linestyle() == "--"]
    assert deadline and deadline[0].get_ydata()[0] == pytest.approx(1e3 / 20.0)  # 50 ms
    paths = plotting._paths_figure(data, (0, 1), "paths")
    assert paths.axes[0].get_xlabel() == "x [m] (y[0])"
    waypoints = [line for line in paths.axes[0].lines if line.get_marker() == "x"]
    assert len(waypoints) == 1 and len(waypoints[0].get_xdata()) == 4  # the leader's square


def test_unknown_names_exit_2_listing_the_valid_ones(
    frisbee_recording: Path, tmp_path: Path, capsys
) -> None:
    for args, listed in (
        (["--agent", "leadr"], "agents: leader, f1, f2"),
        (["--xy", "0,7"], "valid: indices 0..2 or names x, y, psi"),
        (["--xy", "x,z"], "valid: indices 0..2 or names x, y, psi"),
        (["--field", "sii"], "fields of y and u: x, y, psi, v_left, v_right"),
    ):
        assert main(["plot", str(frisbee_recording), "--out", str(tmp_path), *args]) == 2
        assert listed in capsys.readouterr().err
    written = plot_recording(
        frisbee_recording, tmp_path / "named", xy=("x", "y"), fields=["psi"], latency=True
    )
    assert [p.name for p in written] == ["outputs.png", "paths.png", "ticks.png", "latency.png"]


def test_late_ticks_are_timed_with_the_answers_that_came_after_their_close() -> None:
    """``/orchestrator/late`` completes what a late tick's own message could not say."""
    ticks = [
        {"k": 0, "t": 0.0, "completion_s": 0.004, "send_delay_s": 0.0, "late": [],
         "agents": {"a": {"answer_s": 0.004}, "b": {"answer_s": 0.003}}},
        {"k": 1, "t": 0.1, "completion_s": None, "send_delay_s": 0.001, "late": ["b"],
         "agents": {"a": {"answer_s": 0.003}}},
        {"k": 2, "t": 0.2, "completion_s": None, "send_delay_s": 0.0, "late": ["a", "b"],
         "agents": {}},
        {"k": 3, "t": 0.3, "completion_s": 0.12, "send_delay_s": 0.0, "late": ["b"],
         "agents": {"a": {"answer_s": 0.002}, "b": {"answer_s": 0.12}}},
    ]  # fmt: skip
    late = [
        {"k": 1, "t": 0.1, "agent": "b", "answer_s": 0.13, "compute_s": 0.001},
        {"k": 2, "t": 0.2, "agent": "a", "answer_s": 0.15},
    ]
    completions = plotting.late_tick_completions(ticks, late)
    # tick 1: b's answer 130 ms after the send, 1 ms after schedule; tick 2: b's never came;
    # tick 3 is late but complete: its own completion stands
    assert completions == {1: pytest.approx(0.131), 2: np.inf}
    t_b, parts_b = plotting.tick_ledger(ticks, late)["b"]
    assert t_b.tolist() == [0.0, 0.1, 0.3]  # in time order, the late answer included
    compute = [key for key, _ in plotting.LEDGER_PARTS].index("compute_s")
    assert parts_b[1, compute] == 0.001


def test_a_run_whose_y_has_one_entry_plots_without_a_path_plot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """No --xy and a y of one entry (a battery voltage): every other figure, exit 0; the
    default x-y entries are no error. An --xy given is still checked."""
    experiment = load_experiment(GRAPHS / "consensus_ring.toml")
    path = tmp_path / "scalar.mcap"
    with Recorder(path, experiment) as recorder:
        for k in range(20):
            t, log = k * experiment.dt, T0 + k * 50_000_000
            recorder.write_vector("/a0/y", k=k, t=t, values=[7.4 - 0.01 * k], log_time_ns=log)
            recorder.write_ticks(k=k, t=t, log_time_ns=log, timings={"completion_s": 0.001})
    out = tmp_path / "plots"
    assert main(["plot", str(path), "--out", str(out)]) == 0
    written = capsys.readouterr().out
    assert "outputs.png" in written and "ticks.png" in written and "paths.png" not in written
    assert main(["plot", str(path), "--out", str(out), "--xy", "0,1"]) == 2
    assert "--xy: y has no entry '1'; valid: indices 0..0" in capsys.readouterr().err

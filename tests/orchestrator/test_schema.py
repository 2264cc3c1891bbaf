"""The declarative experiment schema: published JSON Schema in sync, every key's rule, new
tables ([mocap], [gateway]) and run policies, problems as file:key: reason."""

from __future__ import annotations

import json
import textwrap
import tomllib
from pathlib import Path

import pytest
from hilswarm.orchestrator.cli import main
from hilswarm.orchestrator.experiment import load_experiment, parse_experiment
from hilswarm.orchestrator.schema import json_schema, json_schema_text

ROOT = Path(__file__).resolve().parents[2]
GRAPHS = ROOT / "graphs"
SCHEMA_FILE = ROOT / "schema" / "experiment.schema.json"

BASE = """
[experiment]
name = "t"
rate_hz = 10
duration_s = 2
{experiment}
[graph]
agents = ["a", "b"]
adjacency = [[0, 1], [1, 0]]

[defaults]
vehicle = "simulated"
controller = "consensus"
vehicle_params = {{ plant = "integrator" }}

[agents.a]
{agent_a}
[agents.b]
initial_state = [1.0]
{rest}
"""


def write(tmp_path: Path, experiment: str = "", agent_a: str = "", rest: str = "") -> Path:
    path = tmp_path / "exp.toml"
    text = BASE.format(experiment=experiment, agent_a=agent_a, rest=rest)
    path.write_text(textwrap.dedent(text), encoding="utf-8")
    return path


def problems(path: Path) -> dict[str, str]:
    experiment, found = parse_experiment(path)
    assert experiment is None and found
    return {p.key: p.message for p in found}


def test_published_schema_is_generated_from_the_model() -> None:
    assert SCHEMA_FILE.read_text(encoding="utf-8") == json_schema_text(), (
        "schema/experiment.schema.json is out of date: run "
        "`hilswarm check --schema schema/experiment.schema.json`"
    )


def test_check_schema_prints_and_writes_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check", "--schema"]) == 0
    assert capsys.readouterr().out == json_schema_text()
    target = tmp_path / "s.json"
    assert main(["check", "--schema", str(target)]) == 0
    assert json.loads(target.read_text()) == json_schema()
    assert main(["check"]) == 2
    assert "give an experiment file" in capsys.readouterr().err


@pytest.mark.parametrize("path", sorted(GRAPHS.glob("*.toml")), ids=lambda p: p.name)
def test_example_files_validate_against_the_json_schema(path: Path) -> None:
    jsonschema = pytest.importorskip("jsonschema")
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(json_schema())
    jsonschema.validate(data, json_schema(), cls=jsonschema.Draft202012Validator)


def test_json_schema_rejects_what_the_loader_rejects(tmp_path: Path) -> None:
    jsonschema = pytest.importorskip("jsonschema")
    validator = jsonschema.Draft202012Validator(json_schema())
    for experiment in ("rate_hz_ = 1", 'mode = "fast"', "seed = -1", "watchdog_s = 0"):
        path = write(tmp_path, experiment=experiment)
        assert problems(path), experiment
        assert list(validator.iter_errors(tomllib.loads(path.read_text()))), experiment
    path = write(tmp_path, rest="[mocap]\nsystem = 'kinect'\n")
    assert list(validator.iter_errors(tomllib.loads(path.read_text())))


@pytest.mark.parametrize(
    ("experiment", "agent_a", "key", "reason"),
    [
        ("", "initial_state = [true]", "agents.a.initial_state[0]", "True is not a number"),
        ("lockstep_window = true", "", "experiment.lockstep_window", "not an integer"),
        ("seed = true", "", "experiment.seed", "True is not an integer"),
        ("watchdog_s = true", "", "experiment.watchdog_s", "True is not a number"),
        ("max_late_fraction = true", "", "experiment.max_late_fraction", "not a number"),
        ("watchdog_s = inf", "", "experiment.watchdog_s", "not a finite number"),
        ("", "pinout = { drive = { pwm = true } }", "agents.a.pinout.drive.pwm", "not a pin"),
        ("", "params = 3", "agents.a.params", "3 is not a table"),
        ("", 'vehicle = ""', "agents.a.vehicle", "must not be empty"),
        ("", "mocap_body = 3", "agents.a.mocap_body", "3 is not a string"),
    ],
)
def test_types_are_strict(
    tmp_path: Path, experiment: str, agent_a: str, key: str, reason: str
) -> None:
    found = problems(write(tmp_path, experiment=experiment, agent_a=agent_a))
    assert key in found, found
    assert reason in found[key]


def test_rate_hz_true_is_not_a_rate(tmp_path: Path) -> None:
    path = tmp_path / "exp.toml"
    path.write_text(write(tmp_path).read_text().replace("rate_hz = 10", "rate_hz = true"))
    assert problems(path) == {"experiment.rate_hz": "True is not a number"}


def test_run_policies_defaults_and_values(tmp_path: Path) -> None:
    experiment = load_experiment(write(tmp_path))
    assert experiment.on_recording_failure == "stop"
    assert experiment.max_late_fraction == 0.01
    assert experiment.mocap is None and experiment.gateway is None
    assert experiment.agent("a").body == "a" and experiment.agent("a").mocap_body is None
    path = write(
        tmp_path,
        experiment='on_recording_failure = "continue"\nmax_late_fraction = 0.05',
        agent_a='mocap_body = "frisbee-7"',
        rest='[mocap]\nsystem = "sim"',
    )
    path.write_text(path.read_text().replace("duration_s = 2", 'duration_s = 2\nmode = "realtime"'))
    experiment = load_experiment(path)
    assert experiment.on_recording_failure == "continue"
    assert experiment.max_late_fraction == 0.05
    assert experiment.agent("a").body == "frisbee-7"
    assert experiment.agent("b").body == "b"
    found = problems(write(tmp_path, experiment='on_recording_failure = "retry"'))
    assert "'retry' is not one of 'stop', 'continue'" in found["experiment.on_recording_failure"]
    found = problems(write(tmp_path, experiment="max_late_fraction = 1.5"))
    assert "expected max_late_fraction <= 1" in found["experiment.max_late_fraction"]


def test_mocap_and_gateway_tables(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        experiment='mode = "realtime"',
        rest=textwrap.dedent(
            """
            [mocap]
            system = "optitrack"
            host = "192.168.1.10"
            rate_hz = 240
            up_axis = "y"

            [gateway]
            port = "socket://127.0.0.1:9750"
            baud = 57600
            api_mode = 1
            """
        ),
    )
    experiment = load_experiment(path)
    assert experiment.mocap is not None and experiment.mocap.system == "optitrack"
    assert experiment.mocap.host == "192.168.1.10" and experiment.mocap.rate_hz == 240.0
    assert experiment.mocap.up_axis == "y" and experiment.mocap.hold_frames == 10
    assert experiment.gateway is not None and experiment.gateway.api_mode == 1
    assert experiment.gateway.baud == 57600
    sim = load_experiment(
        write(
            tmp_path,
            experiment='mode = "realtime"',
            rest='[mocap]\nsystem = "sim"\n[mocap.sim]\nnoise_std_m = 0.002\n'
            "occlusions = { a = [1.0, 2.0] }",
        )
    )
    assert sim.mocap is not None and sim.mocap.host == "127.0.0.1"
    assert sim.mocap.sim.noise_std_m == 0.002 and sim.mocap.sim.occlusions == {"a": (1.0, 2.0)}

    found = problems(
        write(
            tmp_path,
            rest='[mocap]\nsystem = "kinect"\nrate_hz = 0\ncolour = 1\n[gateway]\napi_mode = 3\n',
        )
    )
    assert "'kinect' is not one of 'vicon', 'optitrack'" in found["mocap.system"]
    assert "0 Hz is out of range; expected rate_hz > 0" in found["mocap.rate_hz"]
    assert found["mocap.colour"].startswith("unknown key; expected one of system, host")
    assert "3 is not one of 1, 2" in found["gateway.api_mode"]
    found = problems(write(tmp_path, rest='[mocap]\nsystem = "vicon"\n'))
    assert found["mocap.host"].startswith("missing")
    assert "realtime" in found["experiment.mode"]  # a mocap system runs on the wall clock
    found = problems(
        write(tmp_path, rest='[mocap]\nsystem = "sim"\n[mocap.sim]\nocclusions = { a = [2, 1] }')
    )
    assert "is not [start_s, end_s]" in found["mocap.sim.occlusions.a"]
    found = problems(write(tmp_path, rest='[gateway]\nport = ""\nbaud = 1000\n'))
    assert found["gateway.port"] == "must not be empty"
    found = problems(write(tmp_path, rest="[gateway]\nbaud = 1000\n"))
    assert "not an XBee rate" in found["gateway"]


def test_overrides_use_the_same_rules(tmp_path: Path) -> None:
    path = write(tmp_path)
    experiment = load_experiment(path, overrides={"on_recording_failure": "continue"})
    assert experiment.on_recording_failure == "continue"
    _, found = parse_experiment(path, overrides={"rate_hz": True, "duration_s": -1.0})
    messages = {p.key: p.message for p in found}
    assert messages["override rate_hz"] == "True is not a number"
    assert messages["override duration_s"] == "-1.0 s is out of range; expected duration_s > 0"

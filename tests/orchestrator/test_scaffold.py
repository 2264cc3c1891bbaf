"""``hilswarm new``: ruff-clean skeletons whose tests fail until filled in, and pass after."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.orchestrator.cli import main
from hilswarm.orchestrator.scaffold import ScaffoldError, plan_device, plan_vehicle, scaffold_names

REPO = Path(__file__).resolve().parents[2]


def pytest_in(directory: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
         "--rootdir", str(directory), str(directory)],
        capture_output=True, text=True, timeout=120, check=False, cwd=directory, env=env,
    )  # fmt: skip


def ruff_clean(directory: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--config", str(REPO / "pyproject.toml"),
         str(directory)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize(
    ("name", "module", "class_name"),
    [
        ("my_rover", "my_rover", "MyRover"),
        ("MyRover", "my_rover", "MyRover"),
        ("HTTPBot", "http_bot", "HttpBot"),
        ("rover2", "rover2", "Rover2"),
    ],
)
def test_names(name, module, class_name):
    names = scaffold_names(name)
    assert (names.module, names.class_name) == (module, class_name)


@pytest.mark.parametrize(
    "name", ["2bot", "my-bot", "class", "json", "my__bot", "bot_", "", "tests"]
)
def test_bad_names_are_refused(name):
    with pytest.raises(ScaffoldError):
        scaffold_names(name)


def test_vehicle_skeleton_fails_until_filled_in_then_passes(tmp_path, capsys):
    assert main(["new", "vehicle", "MyRover", "--dir", str(tmp_path)]) == 0
    assert {p.name for p in tmp_path.iterdir()} == {
        "my_rover.py",
        "test_my_rover.py",
        "my_rover.toml",
    }
    ruff_clean(tmp_path)
    source = (tmp_path / "my_rover.py").read_text()
    assert source.count("raise NotImplementedError(") == 4
    assert "FILL IN MyRover.setup_devices()" in source

    before = pytest_in(tmp_path)
    assert before.returncode == 1, before.stdout
    assert "3 failed" in before.stdout and "NotImplementedError" in before.stdout

    filled = source.split("    def setup_devices(self)")[0] + FILLED_VEHICLE_METHODS
    filled = filled.replace(
        "from hilswarm.agents.link.sim_board import PinPlant\n",
        "from hilswarm.agents.devices.output_pin import OutputPin\n"
        "from hilswarm.agents.link.sim_board import PinPlant\n",
    )
    (tmp_path / "my_rover.py").write_text(filled)
    ruff_clean(tmp_path)
    after = pytest_in(tmp_path)
    assert after.returncode == 0, after.stdout + after.stderr
    assert "3 passed" in after.stdout


FILLED_VEHICLE_METHODS = '''    def setup_devices(self) -> None:
        """One PWM output."""
        self.motor = self.add_device(OutputPin, "motor", mode="pwm")

    def read_outputs(self) -> np.ndarray:
        """The duty on the pin."""
        return np.array([float(self.motor.pins.staged("motor.pin"))])

    def actuate(self, u: np.ndarray) -> None:
        """u [duty] on the pin."""
        self.motor.actuate(int(min(max(u[0], 0), 255)))

    def simulated_hardware(
        self, *, initial_state: Sequence[float] | None, dt: float
    ) -> PinPlant | None:
        """No physics."""
        return None
'''


def test_experiment_file_of_a_skeleton_loads(tmp_path):
    from hilswarm.orchestrator.experiment import load_experiment

    assert main(["new", "vehicle", "rover", "--dir", str(tmp_path)]) == 0
    experiment = load_experiment(tmp_path / "rover.toml")
    assert experiment.agents[0].vehicle == "rover:Rover"


@pytest.mark.parametrize("kind", ["actuator", "sensor"])
def test_device_skeleton_fails_until_filled_in_then_passes(tmp_path, kind):
    assert main(["new", "device", "Buzzer", "--kind", kind, "--dir", str(tmp_path)]) == 0
    ruff_clean(tmp_path)
    before = pytest_in(tmp_path)
    assert before.returncode == 1 and "2 failed" in before.stdout, before.stdout
    source = (tmp_path / "buzzer.py").read_text()
    body = {
        "actuator": ("PinMode.PWM",
                     "value = int(command * 255)\n        self.write(\"pin\", value)"
                     "\n        return value"),
        "sensor": ("PinMode.ANALOG_IN", "return self.read(\"pin\") / 1023 * 5.0"),
    }[kind]  # fmt: skip
    head, _, _ = source.partition("    def role_mode(self, role: str) -> PinMode:")
    method = (
        "actuate(self, command: float) -> int" if kind == "actuator" else "sense(self) -> float"
    )
    filled = (
        head
        + "    def role_mode(self, role: str) -> PinMode:\n"
        + f'        """Mode."""\n        return {body[0]}\n\n'
        + f"    def {method}:\n"
        + f'        """Filled."""\n        {body[1]}\n'
    )
    (tmp_path / "buzzer.py").write_text(filled)
    after = pytest_in(tmp_path)
    assert after.returncode == 0 and "2 passed" in after.stdout, after.stdout + after.stderr


def test_refuses_to_overwrite_anything(tmp_path, capsys):
    (tmp_path / "test_rover.py").write_text("# mine\n")
    assert main(["new", "vehicle", "rover", "--dir", str(tmp_path)]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert not (tmp_path / "rover.py").exists()
    assert (tmp_path / "test_rover.py").read_text() == "# mine\n"


def test_plans_are_pure(tmp_path):
    files = plan_vehicle("rover", tmp_path) + plan_device("lamp", tmp_path)
    assert len(files) == 5
    assert not any(f.path.exists() for f in files)
    with pytest.raises(ScaffoldError, match="kind"):
        plan_device("lamp", tmp_path, kind="motor")


def _hilswarm(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run(
        [sys.executable, "-m", "hilswarm.orchestrator.cli", *args],
        capture_output=True, text=True, timeout=120, check=False, cwd=cwd, env=env,
    )  # fmt: skip


def test_check_finds_the_skeleton_beside_its_experiment_and_says_what_is_unfinished(tmp_path):
    """No PYTHONPATH, another working directory: the experiment's folder is importable."""
    folder = tmp_path / "rovers"
    assert main(["new", "vehicle", "MyRover", "--dir", str(folder)]) == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    unfinished = _hilswarm("check", str(folder / "my_rover.toml"), cwd=elsewhere)
    assert unfinished.returncode == 2, unfinished.stdout + unfinished.stderr
    assert "agents.my_rover.vehicle" in unfinished.stderr + unfinished.stdout
    assert "is not finished: FILL IN MyRover.setup_devices()" in unfinished.stderr
    assert "Traceback" not in unfinished.stderr

    source = (folder / "my_rover.py").read_text()
    filled = source.split("    def setup_devices(self)")[0] + FILLED_VEHICLE_METHODS
    filled = filled.replace(
        "from hilswarm.agents.link.sim_board import PinPlant\n",
        "from hilswarm.agents.devices.output_pin import OutputPin\n"
        "from hilswarm.agents.link.sim_board import PinPlant\n",
    )
    (folder / "my_rover.py").write_text(filled)
    finished = _hilswarm("check", str(folder / "my_rover.toml"), cwd=elsewhere)
    assert finished.returncode == 0, finished.stdout + finished.stderr
    run = _hilswarm(
        "run", str(folder / "my_rover.toml"), "--out", str(tmp_path / "run.mcap"), cwd=elsewhere,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    assert "100/100 ticks" in run.stdout

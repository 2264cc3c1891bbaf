"""``hilswarm calibrate``: measured pairs -> checked calibration file (+ plot), and its JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hilswarm.agents.calibration import Calibration
from hilswarm.orchestrator.calibration_report import calibration_as_json, calibration_topic
from hilswarm.orchestrator.cli import main


def write_pairs(path, duties, speeds, header="pwm,u"):
    lines = [header] + [f"{d},{v}" for d, v in zip(duties, speeds, strict=True)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def curve(duty):
    return math.copysign(0.22 * math.tanh(0.6 * abs(duty) / 255) / math.tanh(0.6), duty)


@pytest.fixture
def pairs(tmp_path):
    rng = np.random.default_rng(7)
    duties, speeds = [], []
    for duty in range(-255, 256, 17):
        for _ in range(3):  # repeated measurements are averaged
            duties.append(duty)
            speeds.append(curve(duty) + rng.normal(0.0, 2e-4))
    return write_pairs(tmp_path / "pairs.csv", duties, speeds)


def test_fits_writes_and_plots(pairs, tmp_path, capsys):
    out, png = tmp_path / "cal.toml", tmp_path / "cal.png"
    args = [
        "calibrate", str(pairs), "--input", "v_left", "--unit", "m/s",
        "--vehicle-id", "fb-7", "--date", "2026-11-21", "-o", str(out), "--plot", str(png),
    ]  # fmt: skip
    assert main(args) == 0
    assert "monotone" in capsys.readouterr().out
    calibration = Calibration.from_file(out)
    assert calibration.vehicle_id == "fb-7" and calibration.date == "2026-11-21"
    assert calibration.names == ("v_left",)
    table = calibration.curve("v_left")
    assert table.unit == "m/s"
    assert table.pwm.tolist() == list(range(-255, 256, 17))
    assert np.all(np.diff(table.u) > 0)
    # The file maps the measured curve both ways within the measurement noise.
    assert calibration.to_u("v_left", 170) == pytest.approx(curve(170), abs=1e-3)
    assert calibration.to_pwm("v_left", curve(-85)) == pytest.approx(-85, abs=2)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_refuses_to_overwrite_and_merges_on_request(pairs, tmp_path, capsys):
    out = tmp_path / "cal.toml"
    base = ["calibrate", str(pairs), "--unit", "m/s", "-o", str(out)]
    assert main([*base, "--input", "v_left"]) == 0
    before = out.read_text()
    assert main([*base, "--input", "v_right"]) == 2
    assert "--merge" in capsys.readouterr().err
    assert out.read_text() == before
    assert main([*base, "--input", "v_right", "--merge"]) == 0
    assert Calibration.from_file(out).names == ("v_left", "v_right")


def test_non_monotone_pairs_are_refused_naming_the_duties(tmp_path, capsys):
    bad = write_pairs(tmp_path / "bad.csv", [-255, 0, 100, 200, 255], [-0.2, 0, 0.1, 0.09, 0.2])
    out = tmp_path / "cal.toml"
    assert main(["calibrate", str(bad), "--input", "v_left", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "pwm 200" in err and "pwm 100" in err and "not strictly increasing" in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("duty,u\n1,2\n", "no 'pwm' column"),
        ("pwm,speed\n1,2\n", "no 'u' or 'v_left' column"),
        ("pwm,u\n1,2\n3,x\n", "data row 3"),
        ("pwm,u\n5,0.1\n5,0.2\n", "two or more distinct duties"),
    ],
)
def test_malformed_pairs_files(tmp_path, capsys, text, match):
    path = tmp_path / "pairs.csv"
    path.write_text(text, encoding="utf-8")
    assert main(["calibrate", str(path), "--input", "v_left", "-o", str(tmp_path / "c.toml")]) == 2
    assert match in capsys.readouterr().err


def test_the_input_name_may_be_the_column_name(tmp_path):
    path = write_pairs(tmp_path / "p.csv", [-255, 0, 255], [-0.2, 0.0, 0.2], header="pwm,v_left")
    assert main(["calibrate", str(path), "--input", "v_left", "-o", str(tmp_path / "c.toml")]) == 0


def test_calibration_as_json_is_plain_json():
    calibration = Calibration(
        {"v_left": ([-0.2, 0.0, 0.2], [-255, 0, 255])},
        units={"v_left": "m/s"},
        vehicle_id="fb-1",
        date="2026-11-21",
        source="x.toml",
    )
    record = json.loads(json.dumps(calibration_as_json(calibration)))
    assert record == {
        "vehicle_id": "fb-1",
        "date": "2026-11-21",
        "source": "x.toml",
        "inputs": [{"name": "v_left", "unit": "m/s", "u": [-0.2, 0.0, 0.2],
                    "pwm": [-255.0, 0.0, 255.0]}],
    }  # fmt: skip
    assert calibration_as_json(None)["inputs"] == []
    assert calibration_topic("leader") == "/leader/calibration"

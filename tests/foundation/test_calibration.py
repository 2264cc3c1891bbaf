"""Calibration: monotone spline u <-> PWM, clipping without extrapolation, the TOML file format."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.calibration import Calibration, CalibrationCurve
from hilswarm.agents.errors import CalibrationError

U = [-0.2, -0.1, 0.0, 0.1, 0.2]
PWM = [-255, -120, 0, 120, 255]

FILE_TEXT = """\
[calibration]
vehicle_id = "frisbee-01"        # which physical vehicle was measured
date = "2026-11-21"
[[calibration.inputs]]
name = "v_left"
unit = "m/s"
u = [-0.2, -0.1, 0.0, 0.1, 0.2]
pwm = [-255, -120, 0, 120, 255]
[[calibration.inputs]]
name = "v_right"
unit = "m/s"
u = [-0.2, 0.0, 0.2]
pwm = [255, 0, -255]             # a motor mounted the other way round
"""


def calibration() -> Calibration:
    return Calibration({"v": (U, PWM)}, units={"v": "m/s"})


def test_table_points_are_reproduced_exactly() -> None:
    cal = calibration()
    for u, pwm in zip(U, PWM, strict=True):
        assert cal.to_pwm("v", u) == pytest.approx(pwm)
        assert cal.to_u("v", pwm) == pytest.approx(u)


def test_linear_table_gives_linear_interpolation() -> None:
    cal = Calibration({"v": ([0.0, 1.0, 2.0], [0, 100, 200])})
    assert cal.to_pwm("v", 0.25) == pytest.approx(25.0)
    assert cal.to_u("v", 150) == pytest.approx(1.5)


def test_interpolant_is_monotone_and_never_overshoots() -> None:
    # a dead band then a steep rise: a cubic spline would overshoot here, PCHIP must not
    u = [0.0, 0.1, 0.2, 0.3, 1.0]
    pwm = [0, 1, 2, 200, 255]
    cal = Calibration({"v": (u, pwm)})
    grid = np.linspace(0.0, 1.0, 2001)
    values = cal.to_pwm("v", grid)
    assert np.all(np.diff(values) >= 0)
    assert values.min() >= 0 and values.max() <= 255


def test_inverse_is_exact_inside_the_table() -> None:
    rng = np.random.default_rng(1234)
    cal = calibration()
    for u in rng.uniform(-0.2, 0.2, size=50):
        assert cal.to_u("v", cal.to_pwm("v", u)) == pytest.approx(u, abs=1e-12)


@pytest.mark.parametrize("falling", [False, True])
def test_inverse_is_the_root_scipy_finds_on_random_tables(falling: bool) -> None:
    """The interval's bracketed Newton search lands on PPoly.solve's root (seeded tables,
    rising and falling, at every integer duty, the knots and the table's ends)."""
    rng = np.random.default_rng(7 + falling)
    for _ in range(20):
        n = int(rng.integers(2, 12))
        u = np.cumsum(rng.uniform(0.01, 0.3, n)) - 0.5
        pwm = np.sort(rng.choice(np.arange(-255, 256), n, replace=False)).astype(float)
        if falling:
            pwm = pwm[::-1]
        curve = CalibrationCurve.build("v", u, pwm)
        slope = curve._spline.derivative()
        lo, hi = curve.pwm_range
        duties = np.concatenate([np.arange(np.ceil(lo), np.floor(hi) + 1), pwm, [lo, hi]])
        for duty in duties:
            roots = curve._spline.solve(duty, extrapolate=False)
            roots = roots[np.isfinite(roots)]
            found = curve.u_at(np.array([duty]))[0]
            assert curve.u_range[0] <= found <= curve.u_range[1]
            # a root to the last bits: pwm within what a few ulps of u and of pwm can reach
            ulps = abs(slope(found)) * np.spacing(abs(found) + 1.0) + np.spacing(256.0)
            assert abs(curve.pwm_at_scalar(found) - duty) <= 4 * ulps
            if roots.size and abs(slope(roots[0])) > 1.0:  # not on a flat spot: the same u
                assert found == pytest.approx(roots[0], rel=1e-12, abs=1e-15)


def test_arrays_in_arrays_out() -> None:
    cal = calibration()
    out = cal.to_pwm("v", np.array([0.0, 0.1]))
    assert isinstance(out, np.ndarray) and out.tolist() == pytest.approx([0, 120])
    assert isinstance(cal.to_pwm("v", 0.1), float)


def test_out_of_range_is_clipped_flagged_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    cal = calibration()
    with caplog.at_level(logging.WARNING, logger="hilswarm.agents.calibration"):
        pwm, clipped = cal.to_pwm_checked("v", 0.5)
        assert (pwm, clipped) == (pytest.approx(255), True)
        assert cal.to_pwm_checked("v", 0.05)[1] is False
        u, clipped = cal.to_u_checked("v", -400)
        assert (u, clipped) == (pytest.approx(-0.2), True)
    assert cal.clip_counts["v"] == 2
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "'v'" in warnings[0].getMessage()  # logged once per input


def test_no_extrapolation_when_clipping_is_off() -> None:
    with pytest.raises(CalibrationError) as info:
        calibration().to_pwm("v", 0.3, clip=False)
    assert "'v'" in str(info.value) and "0.3" in str(info.value)


def test_non_finite_and_unknown_inputs_are_named() -> None:
    cal = calibration()
    with pytest.raises(CalibrationError, match="nan"):
        cal.to_pwm("v", float("nan"))
    with pytest.raises(CalibrationError, match="'w'"):
        cal.to_pwm("w", 0.0)


@pytest.mark.parametrize(
    ("u", "pwm", "culprit"),
    [
        ([0.0, 0.1, 0.1], [0, 1, 2], r"u\[2\] = 0.1"),
        ([0.0, 0.2, 0.1], [0, 1, 2], r"u\[2\]"),
        ([0.0, 0.1], [0, 1, 2], "2 values but pwm has 3"),
        ([0.0], [0], "at least 2"),
        ([0.0, 0.1], [0, 300], r"pwm\[1\] = 300"),
        ([0.0, 0.1, 0.2], [0, 10, 5], "monotone"),
        ([0.0, float("inf")], [0, 1], "not finite"),
        ([0.0, "a"], [0, 1], "list of numbers"),
    ],
)
def test_bad_tables_are_named(u: list, pwm: list, culprit: str) -> None:
    with pytest.raises(CalibrationError, match=culprit) as info:
        Calibration({"v_left": (u, pwm)})
    assert "'v_left'" in str(info.value)


def test_other_construction_errors() -> None:
    with pytest.raises(CalibrationError, match="no inputs"):
        Calibration({})
    with pytest.raises(CalibrationError, match="'w'"):
        Calibration({"v": (U, PWM)}, units={"w": "m"})
    with pytest.raises(CalibrationError, match=r"'v'.*pair"):
        Calibration({"v": U})  # type: ignore[dict-item]
    curve = CalibrationCurve.build("v", U, PWM)
    with pytest.raises(CalibrationError, match=r"'v'.*twice"):
        Calibration([curve, curve])


def test_check_names_against_vehicle_inputs() -> None:
    cal = calibration()
    cal.check_names(("v", "w"))
    with pytest.raises(CalibrationError, match="'v'"):
        cal.check_names(("left", "right"))


# ---------------------------------------------------------------- files
def test_file_format_loads(tmp_path: Path) -> None:
    path = tmp_path / "cal.toml"
    path.write_text(FILE_TEXT)
    cal = Calibration.from_file(path)
    assert cal.names == ("v_left", "v_right")
    assert cal.vehicle_id == "frisbee-01" and cal.date == "2026-11-21"
    assert cal.curve("v_left").unit == "m/s"
    assert cal.to_pwm("v_right", 0.1) == pytest.approx(-127.5)  # decreasing table
    assert cal.to_u("v_right", -127.5) == pytest.approx(0.1)
    assert cal.source == str(path)


def test_save_round_trips(tmp_path: Path) -> None:
    cal = Calibration.from_toml(FILE_TEXT)
    saved = cal.save(tmp_path / "out.toml")
    again = Calibration.from_file(saved)
    assert again.names == cal.names and again.vehicle_id == cal.vehicle_id
    for name in cal.names:
        np.testing.assert_array_equal(again.curve(name).u, cal.curve(name).u)
        np.testing.assert_array_equal(again.curve(name).pwm, cal.curve(name).pwm)
        assert again.curve(name).unit == cal.curve(name).unit


def test_toml_dates_are_accepted(tmp_path: Path) -> None:
    cal = Calibration.from_toml(FILE_TEXT.replace('"2026-11-21"', "2026-11-21"))
    assert cal.date == "2026-11-21"


@pytest.mark.parametrize(
    ("text", "culprits"),
    [
        ("not toml [", ["not valid TOML"]),
        ("[other]\nx = 1\n", ["other"]),
        ("x = 1\n", ["'x'"]),
        ("[calibration]\nvehicle_id = 3\n", ["calibration.vehicle_id", "3"]),
        ("[calibration]\nvehicle = 'a'\ninputs = []\n", ["calibration.vehicle"]),
        ("[calibration]\ninputs = []\n", ["calibration.inputs"]),
        (
            "[calibration]\n[[calibration.inputs]]\nname = 'v'\nu = [0.0, 1.0]\n",
            ["calibration.inputs[0].pwm", "missing"],
        ),
        (
            "[calibration]\n[[calibration.inputs]]\nname = 'v'\nu = [0.0, 1.0]\npwm = [0, 1]\n"
            "[[calibration.inputs]]\nname = 'w'\nu = [0.0, 1.0, 0.5]\npwm = [0, 1, 2]\n",
            ["calibration.inputs[1]", "'w'", "u[2] = 0.5"],
        ),
        (
            "[calibration]\n[[calibration.inputs]]\nname = 'v'\nu = [0.0, 1.0]\npwm = [0, '1']\n",
            ["calibration.inputs[0].pwm", "list of numbers"],
        ),
        (
            "[calibration]\n[[calibration.inputs]]\nname = 'v'\nunits = 'm'\nu = [0, 1]\n"
            "pwm = [0, 1]\n",
            ["calibration.inputs[0].units"],
        ),
    ],
)
def test_file_errors_name_file_key_and_value(
    tmp_path: Path, text: str, culprits: list[str]
) -> None:
    path = tmp_path / "broken.toml"
    path.write_text(text)
    with pytest.raises(CalibrationError) as info:
        Calibration.from_file(path)
    message = str(info.value)
    assert str(path) in message
    for culprit in culprits:
        assert culprit in message


def test_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"nope\.toml"):
        Calibration.from_file(tmp_path / "nope.toml")


def test_remaining_calibration_errors_are_named(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="input name"):
        CalibrationCurve.build("", U, PWM)
    with pytest.raises(CalibrationError, match=r"'v'.*unit"):
        CalibrationCurve.build("v", U, PWM, unit=3)  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match=r"'v'.*pwm.*not finite"):
        calibration().to_u("v", float("inf"))
    with pytest.raises(CalibrationError, match="not a CalibrationCurve"):
        Calibration(["v"])  # type: ignore[list-item]
    with pytest.raises(CalibrationError, match="cannot write"):
        calibration().save(tmp_path / "missing-dir" / "cal.toml")

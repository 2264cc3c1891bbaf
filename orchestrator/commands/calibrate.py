"""``hilswarm calibrate``: fit a calibration table from measured (PWM, u) pairs.

Input: a CSV file with a header row and two columns, ``pwm`` (signed duty, wire units
-255..255) and the measured input value (column ``u`` or the input's own name, e.g.
``v_left``), one measurement per row; repeated duties are averaged. The pairs must describe a
strictly monotone curve (more duty, more u). The command

1. averages repeated duties and sorts by duty,
2. checks that u is strictly increasing with duty (naming the first offending rows if not),
3. builds the monotone spline the vehicles use (:class:`~hilswarm.agents.calibration.Calibration`,
   PCHIP) and checks that its inverse reproduces every measured point,
4. writes the calibration file (``docs/architecture.md`` format), merging into an existing
   file given with ``--merge`` so one file holds every input of a vehicle,
5. optionally plots the measured points and the fitted curve to a PNG.

Both output paths (``-o`` and ``--plot``) are checked writable before anything is written: a
bad ``--plot`` leaves no calibration file behind (exit status 2).

Example::

    hilswarm calibrate left.csv --input v_left --unit m/s --vehicle-id frisbee-01 \\
        -o frisbee-01.toml --plot left.png
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import logging
from collections import defaultdict
from pathlib import Path

import numpy as np
from hilswarm.agents.calibration import Calibration, CalibrationCurve
from hilswarm.agents.errors import CalibrationError
from hilswarm.orchestrator.output_paths import check_output_file
from matplotlib.figure import Figure

HELP = "fit and plot a calibration table from measured pairs"

logger = logging.getLogger(__name__)

#: Largest |to_u(to_pwm(u)) - u| accepted when re-checking the fitted curve (relative to range).
ROUND_TRIP_TOLERANCE = 1e-9


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm calibrate``."""
    parser.add_argument("pairs", type=Path, help="CSV with columns pwm and u (or INPUT)")
    parser.add_argument("--input", required=True, help="vehicle input name, e.g. v_left")
    parser.add_argument("--unit", default="", help="unit of u, e.g. m/s")
    parser.add_argument("--vehicle-id", default="", help="which physical vehicle was measured")
    parser.add_argument("--date", default=None, help="measurement date (default: today)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="calibration TOML")
    parser.add_argument(
        "--merge",
        action="store_true",
        help="add/replace this input in an existing output file instead of refusing it",
    )
    parser.add_argument("--plot", type=Path, default=None, help="write a PNG of the fit")


def read_pairs(path: Path, input_name: str) -> tuple[np.ndarray, np.ndarray]:
    """Read ``(pwm, u)`` columns from a CSV file (header row required).

    Raises:
        CalibrationError: unreadable file, missing columns, non-numeric cells (row named),
            fewer than two distinct duties.
    """
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            rows = list(csv.reader(handle))
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read pairs file: {exc}") from None
    rows = [row for row in rows if row and not row[0].lstrip().startswith("#")]
    if not rows:
        raise CalibrationError(f"{path}: empty file; expected a header row 'pwm,u'")
    header = [cell.strip() for cell in rows[0]]
    if "pwm" not in header:
        raise CalibrationError(f"{path}: header {header} has no 'pwm' column")
    value_column = next((name for name in ("u", input_name) if name in header), None)
    if value_column is None:
        raise CalibrationError(
            f"{path}: header {header} has no 'u' or {input_name!r} column for the measured input"
        )
    pwm_index, u_index = header.index("pwm"), header.index(value_column)
    pwm, u = [], []
    for line, row in enumerate(rows[1:], start=2):
        try:
            pwm.append(float(row[pwm_index]))
            u.append(float(row[u_index]))
        except (IndexError, ValueError):
            raise CalibrationError(
                f"{path}: data row {line}: expected numbers in columns 'pwm' and "
                f"{value_column!r}, got {row}"
            ) from None
    if not np.all(np.isfinite(pwm)) or not np.all(np.isfinite(u)):
        raise CalibrationError(f"{path}: non-finite numbers in the pairs")
    return np.array(pwm), np.array(u)


def fit_table(pwm: np.ndarray, u: np.ndarray, *, source: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Average repeated duties, sort by duty and check monotonicity.

    Returns:
        ``(u_table, pwm_table)``, u strictly increasing.

    Raises:
        CalibrationError: fewer than two distinct duties, or u not strictly increasing with
            duty (the message names the two duties where it is not).
    """
    groups: dict[float, list[float]] = defaultdict(list)
    for duty, value in zip(pwm.tolist(), u.tolist(), strict=True):
        groups[duty] += [value]
    duties = np.array(sorted(groups))
    if duties.size < 2:
        raise CalibrationError(f"{source}: need measurements at two or more distinct duties")
    means = np.array([np.mean(groups[d]) for d in duties.tolist()])
    steps = np.diff(means)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0])
        raise CalibrationError(
            f"{source}: the measured curve is not strictly increasing: u = {means[i + 1]:.6g} at "
            f"pwm {duties[i + 1]:g} is not above u = {means[i]:.6g} at pwm {duties[i]:g}; "
            "measure again or drop the dead band (a calibration must be invertible)"
        )
    return means, duties


def check_curve(curve: CalibrationCurve) -> float:
    """Largest round-trip error ``|u(pwm(u)) - u|`` over a dense grid (must be ~0).

    Raises:
        CalibrationError: the fitted curve is not monotone (the round trip fails).
    """
    grid = np.linspace(*curve.u_range, 2001)
    pwm = curve.pwm_at(grid)
    if np.any(np.diff(pwm) * np.sign(curve.pwm[-1] - curve.pwm[0]) < 0):
        raise CalibrationError(f"input {curve.name!r}: the fitted spline is not monotone")
    error = float(np.max(np.abs(curve.u_at(pwm) - grid)))
    span = curve.u_range[1] - curve.u_range[0]
    if error > ROUND_TRIP_TOLERANCE * max(span, 1.0):
        raise CalibrationError(
            f"input {curve.name!r}: the fitted spline does not invert (error {error:g})"
        )
    return error


def merged_calibration(
    curve: CalibrationCurve, output: Path, *, merge: bool, vehicle_id: str, date: str
) -> Calibration:
    """The calibration to write: ``curve`` alone, or replacing/adding it in ``output``."""
    curves = [curve]
    if output.exists():
        if not merge:
            raise CalibrationError(
                f"{output}: exists; pass --merge to add input {curve.name!r} to it, or choose "
                "another -o file"
            )
        existing = Calibration.from_file(output)
        if existing.vehicle_id and vehicle_id and existing.vehicle_id != vehicle_id:
            raise CalibrationError(
                f"{output}: belongs to vehicle {existing.vehicle_id!r}, not {vehicle_id!r}"
            )
        vehicle_id = vehicle_id or existing.vehicle_id
        curves = [existing.curve(n) for n in existing.names if n != curve.name] + curves
    return Calibration(curves, vehicle_id=vehicle_id, date=date, source=str(output))


def plot_fit(
    curve: CalibrationCurve, pwm: np.ndarray, u: np.ndarray, path: Path, *, title: str
) -> None:
    """PNG: measured pairs (points) and the fitted curve (line), u against duty."""
    grid = np.linspace(*curve.u_range, 400)
    fig = Figure(figsize=(6.0, 4.0), dpi=120)
    ax = fig.add_subplot()
    ax.plot(curve.pwm_at(grid), grid, "-", label="fitted spline (PCHIP)")
    ax.plot(pwm, u, "o", ms=4, label="measured")
    ax.set_xlabel("signed PWM duty [wire units]")
    ax.set_ylabel(f"{curve.name} [{curve.unit or '-'}]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)


def run(args: argparse.Namespace) -> int:
    """Fit, check, write and plot; returns the exit status."""
    pwm, u = read_pairs(args.pairs, args.input)
    u_table, pwm_table = fit_table(pwm, u, source=str(args.pairs))
    curve = CalibrationCurve.build(
        args.input, u_table, pwm_table, unit=args.unit, where=str(args.pairs)
    )
    error = check_curve(curve)
    date = args.date or dt.date.today().isoformat()
    check_output_file(args.output, what="the calibration")  # both before anything is written
    if args.plot is not None:
        check_output_file(args.plot, what="the plot")
    calibration = merged_calibration(
        curve, args.output, merge=args.merge, vehicle_id=args.vehicle_id, date=date
    )
    calibration.save(args.output)
    print(
        f"{args.output}: input {args.input!r}: {u_table.size} points, "
        f"u {u_table[0]:.6g}..{u_table[-1]:.6g} {args.unit}, "
        f"pwm {pwm_table[0]:g}..{pwm_table[-1]:g} (monotone; round-trip error {error:.1e})"
    )
    if args.plot is not None:
        plot_fit(curve, pwm, u, args.plot, title=f"{args.vehicle_id or 'vehicle'}: {args.input}")
        print(f"{args.plot}: plot written")
    return 0

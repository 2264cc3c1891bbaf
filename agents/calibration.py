"""Calibration curves: control input u <-> signed PWM duty, by monotone spline (thesis A.2.6).

Each control input ``u_i`` of a vehicle (a speed [m/s], a thrust [N], ...) is related to the
signed PWM duty an actuator gets (wire units, -255..255, sign = direction) by a measured table.
:class:`Calibration` interpolates the table both ways.

Why :class:`scipy.interpolate.PchipInterpolator` and not ``CubicSpline``: a measured actuator
curve is monotone (more duty, more thrust), and the inverse PWM -> u only exists if the
interpolant is monotone too. PCHIP (piecewise cubic Hermite) preserves the monotonicity of the
data and never overshoots between measurements, so a dead band or a saturating end of the table
does not turn into a wiggle that maps one PWM to two values of u. ``CubicSpline`` is smoother
(C2 instead of C1) but overshoots near sharp bends, exactly where motor tables have them. The
inverse is the exact inverse of the same curve (root of the PCHIP polynomial), so
``to_u(to_pwm(u)) == u`` inside the table.

Nothing is ever extrapolated: a value outside the table is clipped to the table's end (logged
once per input at WARNING, counted in :attr:`Calibration.clip_counts`, and reported by the
``*_checked`` methods), or refused with ``clip=False``.

The file format (TOML, see ``docs/architecture.md``)::

    [calibration]
    vehicle_id = "frisbee-01"
    date = "2026-11-21"
    [[calibration.inputs]]
    name = "v_left"
    unit = "m/s"
    u = [-0.2, -0.1, 0.0, 0.1, 0.2]     # strictly increasing
    pwm = [-255, -120, 0, 120, 255]     # wire units, strictly monotone
"""

from __future__ import annotations

import bisect
import datetime as _dt
import logging
import math
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, overload

import numpy as np
from hilswarm.agents.errors import CalibrationError
from hilswarm.agents.link.board import PWM_MAX
from numpy.typing import ArrayLike
from scipy.interpolate import PchipInterpolator

__all__ = ["Calibration", "CalibrationCurve"]

logger = logging.getLogger(__name__)

_TOP_KEYS = {"vehicle_id", "date", "inputs"}
_INPUT_KEYS = {"name", "unit", "u", "pwm"}


def _strictly_monotone(values: np.ndarray) -> int:
    """+1 strictly increasing, -1 strictly decreasing, 0 otherwise."""
    steps = np.diff(values)
    if np.all(steps > 0):
        return 1
    if np.all(steps < 0):
        return -1
    return 0


@dataclass(frozen=True)
class CalibrationCurve:
    """One input's table and its monotone interpolant.

    Attributes:
        name: the vehicle input name (one of ``Vehicle.input_names``).
        unit: unit of ``u`` (free text, e.g. ``"m/s"``).
        u: control input values, strictly increasing (unit ``unit``).
        pwm: signed PWM duty at each ``u`` (wire units, -255..255), strictly monotone.
    """

    name: str
    unit: str
    u: np.ndarray
    pwm: np.ndarray
    _spline: PchipInterpolator = field(repr=False, compare=False)
    #: Scalar fast path, built once: knots, per-interval coefficients (highest power first),
    #: both ranges as floats, and the inverse at integer PWM values as they are asked for.
    _knots: list[float] = field(init=False, repr=False, compare=False)
    _coefficients: list[tuple[float, ...]] = field(init=False, repr=False, compare=False)
    _u_bounds: tuple[float, float] = field(init=False, repr=False, compare=False)
    _pwm_bounds: tuple[float, float] = field(init=False, repr=False, compare=False)
    _inverse_cache: dict[float, float] = field(init=False, repr=False, compare=False)
    #: For the inverse: the PWM at the knots made increasing (negated for a falling table),
    #: and that sign (+1 rising, -1 falling).
    _pwm_rising: list[float] = field(init=False, repr=False, compare=False)
    _direction: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        spline = self._spline
        set_field = object.__setattr__  # frozen dataclass: derived fields are set once here
        set_field(self, "_knots", [float(v) for v in spline.x])
        set_field(self, "_coefficients", [tuple(float(c) for c in col) for col in spline.c.T])
        set_field(self, "_u_bounds", (float(self.u[0]), float(self.u[-1])))
        set_field(self, "_pwm_bounds", (float(self.pwm.min()), float(self.pwm.max())))
        set_field(self, "_inverse_cache", {})
        direction = 1.0 if self.pwm[-1] > self.pwm[0] else -1.0
        set_field(self, "_direction", direction)
        set_field(self, "_pwm_rising", [direction * float(v) for v in self.pwm])

    @classmethod
    def build(
        cls, name: str, u: ArrayLike, pwm: ArrayLike, *, unit: str = "", where: str = ""
    ) -> CalibrationCurve:
        """Validate the table and build the curve.

        Raises:
            CalibrationError: naming ``where`` (file/key), the input and the bad value.
        """
        at = f"{where}: " if where else ""
        if not isinstance(name, str) or not name:
            raise CalibrationError(f"{at}input name must be a non-empty string, got {name!r}")
        if not isinstance(unit, str):
            raise CalibrationError(f"{at}input {name!r}: unit must be a string, got {unit!r}")
        arrays = []
        for key, raw in (("u", u), ("pwm", pwm)):
            try:
                values = np.asarray(raw, dtype=np.float64)
            except (TypeError, ValueError):
                raise CalibrationError(
                    f"{at}input {name!r}: {key} must be a list of numbers, got {raw!r}"
                ) from None
            if values.ndim != 1 or values.size < 2:
                raise CalibrationError(
                    f"{at}input {name!r}: {key} needs at least 2 numbers in a flat list, "
                    f"got {raw!r}"
                )
            bad = np.flatnonzero(~np.isfinite(values))
            if bad.size:
                raise CalibrationError(
                    f"{at}input {name!r}: {key}[{bad[0]}] = {values[bad[0]]} is not finite"
                )
            arrays.append(values)
        u_arr, pwm_arr = arrays
        if u_arr.size != pwm_arr.size:
            raise CalibrationError(
                f"{at}input {name!r}: u has {u_arr.size} values but pwm has {pwm_arr.size}"
            )
        if _strictly_monotone(u_arr) != 1:
            i = int(np.flatnonzero(np.diff(u_arr) <= 0)[0])
            raise CalibrationError(
                f"{at}input {name!r}: u must be strictly increasing, but u[{i + 1}] = "
                f"{u_arr[i + 1]} follows u[{i}] = {u_arr[i]}"
            )
        out = np.flatnonzero(np.abs(pwm_arr) > PWM_MAX)
        if out.size:
            raise CalibrationError(
                f"{at}input {name!r}: pwm[{out[0]}] = {pwm_arr[out[0]]} is outside "
                f"-{PWM_MAX}..{PWM_MAX}"
            )
        if _strictly_monotone(pwm_arr) == 0:
            raise CalibrationError(
                f"{at}input {name!r}: pwm must be strictly monotone (increasing or decreasing) "
                f"so that PWM -> u is invertible, got {pwm_arr.tolist()}"
            )
        u_arr.flags.writeable = False
        pwm_arr.flags.writeable = False
        return cls(name, unit, u_arr, pwm_arr, PchipInterpolator(u_arr, pwm_arr))

    @property
    def u_range(self) -> tuple[float, float]:
        """Smallest and largest u of the table."""
        return self._u_bounds

    @property
    def pwm_range(self) -> tuple[float, float]:
        """Smallest and largest PWM of the table (wire units)."""
        return self._pwm_bounds

    def pwm_at(self, u: np.ndarray) -> np.ndarray:
        """PWM at ``u`` values already inside :attr:`u_range`."""
        return np.asarray(self._spline(u), dtype=np.float64)

    def pwm_at_scalar(self, u: float) -> float:
        """PWM at one ``u`` inside :attr:`u_range`, bit for bit what :meth:`pwm_at` gives.

        Plain float arithmetic in scipy's own order (interval with ``x[i] <= u < x[i+1]``,
        the last one closed; ``sum c_j s^j`` from the constant term up), about 20 times
        cheaper than a call into the interpolator for a single value.
        """
        knots = self._knots
        i = _interval(knots, u)
        s = u - knots[i]
        c3, c2, c1, c0 = self._coefficients[i]
        return 0.0 + c0 + c1 * s + c2 * (s * s) + c3 * (s * s * s)

    def u_at(self, pwm: np.ndarray) -> np.ndarray:
        """u at ``pwm`` values already inside :attr:`pwm_range` (exact inverse of pwm_at)."""
        result = np.empty(pwm.shape, dtype=np.float64)
        flat_in, flat_out = pwm.reshape(-1), result.reshape(-1)
        for i, value in enumerate(flat_in):
            flat_out[i] = self._inverse(float(value))
        return result

    def u_at_scalar(self, pwm: float) -> float:
        """u at one ``pwm`` inside :attr:`pwm_range` (same value as :meth:`u_at`).

        The inverse at integer PWM values (what boards are driven with) is remembered, so
        the root finding runs once per duty value.
        """
        cached = self._inverse_cache.get(pwm)
        if cached is not None:
            return cached
        u = self._inverse(pwm)
        if pwm.is_integer():
            self._inverse_cache[pwm] = u
        return u

    def prepare_inverse(self) -> None:
        """Compute the inverse at every integer PWM of the table now (~5 µs per value).

        Afterwards :meth:`u_at_scalar` of an integer duty is a lookup on every call, so a
        control tick never pays for a root search (an agent calls this before tick 0).
        """
        low, high = self._pwm_bounds
        for duty in range(math.ceil(low), math.floor(high) + 1):
            self.u_at_scalar(float(duty))

    def _inverse(self, value: float) -> float:
        """The u in the table's range with ``pwm_at(u) == value`` (to the last bit or so).

        PCHIP keeps the table's monotonicity, so the root lies in the one interval whose end
        values bracket ``value``: Newton's method on that interval's cubic, kept inside a
        shrinking bracket (a bisection step whenever Newton would leave it), from the linear
        interpolation's guess. About 5 µs, where ``PPoly.solve`` searched every interval
        for roots (~65 µs): the agent computes the inverse at every duty before its first
        tick (:meth:`prepare_inverse`), and that was most of an agent's start-up.
        """
        rising = self._pwm_rising
        direction = self._direction
        target = direction * value
        i = _interval(rising, target)
        knot = self._knots[i]
        width = self._knots[i + 1] - knot
        c3, c2, c1, c0 = self._coefficients[i]
        low, high = 0.0, width
        rise = rising[i + 1] - rising[i]
        s = min(max(width * (target - rising[i]) / rise, 0.0), width)
        for _ in range(_INVERSE_STEPS):
            # pwm_at_scalar's own arithmetic, so that its value at the root is the closest
            g = direction * ((0.0 + c0 + c1 * s + c2 * (s * s) + c3 * (s * s * s)) - value)
            if g == 0.0:
                break
            if g > 0.0:
                high = s
            else:
                low = s
            slope = direction * ((3.0 * c3 * s + 2.0 * c2) * s + c1)
            step = s - g / slope if slope > 0.0 else low - 1.0
            if not low < step < high:
                step = 0.5 * (low + high)
            if step == s or step in (low, high):
                break
            s = step
        return knot + s


def _interval(knots: list[float], value: float) -> int:
    """Index i of the interval ``knots[i] <= value < knots[i+1]`` (increasing knots; the last
    interval closed, values outside the knots in the end intervals), as scipy's PPoly picks it."""
    i = bisect.bisect_right(knots, value) - 1
    last = len(knots) - 2
    if i > last:
        return last
    return max(i, 0)


#: Bound of the inverse's iterations: Newton converges in ~5; bisection alone would need ~60
#: to reach the last bit of a double, so the bound never cuts a converging search short.
_INVERSE_STEPS = 80


class Calibration:
    """Spline calibration u <-> signed PWM for several inputs.

    Args:
        curves: input name -> ``(u, pwm)`` arrays, or an iterable of :class:`CalibrationCurve`.
        units: optional input name -> unit of u, for the mapping form.
        vehicle_id: which physical vehicle was measured.
        date: when it was measured (ISO date string).
        source: where the tables came from (a file path), used in messages.

    Raises:
        CalibrationError: a malformed table, duplicate or empty input list.
    """

    def __init__(
        self,
        curves: Mapping[str, tuple[ArrayLike, ArrayLike]] | Iterable[CalibrationCurve],
        *,
        units: Mapping[str, str] | None = None,
        vehicle_id: str = "",
        date: str = "",
        source: str = "",
    ) -> None:
        self.vehicle_id = vehicle_id
        self.date = date
        self.source = source
        built: dict[str, CalibrationCurve] = {}
        if isinstance(curves, Mapping):
            units = dict(units or {})
            unknown_units = [name for name in units if name not in curves]
            if unknown_units:
                raise CalibrationError(f"units given for unknown input(s) {unknown_units}")
            items: list[CalibrationCurve] = []
            for name, table in curves.items():
                try:
                    u, pwm = table
                except (TypeError, ValueError):
                    raise CalibrationError(
                        f"input {name!r}: expected a (u, pwm) pair of arrays, got {table!r}"
                    ) from None
                items.append(
                    CalibrationCurve.build(name, u, pwm, unit=units.get(name, ""), where=source)
                )
        else:
            items = list(curves)
        for curve in items:
            if not isinstance(curve, CalibrationCurve):
                raise CalibrationError(f"not a CalibrationCurve: {curve!r}")
            if curve.name in built:
                raise CalibrationError(
                    f"{source or 'calibration'}: input {curve.name!r} is calibrated twice"
                )
            built[curve.name] = curve
        if not built:
            raise CalibrationError(f"{source or 'calibration'}: no inputs calibrated")
        self._curves = built
        self.clip_counts: dict[str, int] = dict.fromkeys(built, 0)

    # ------------------------------------------------------------------ lookups
    @property
    def names(self) -> tuple[str, ...]:
        """Calibrated input names, in table order."""
        return tuple(self._curves)

    def __contains__(self, name: object) -> bool:
        return name in self._curves

    def curve(self, name: str) -> CalibrationCurve:
        """The table of input ``name``.

        Raises:
            CalibrationError: input not calibrated.
        """
        try:
            return self._curves[name]
        except (KeyError, TypeError):
            raise CalibrationError(
                f"{self.source or 'calibration'}: no curve for input {name!r}; "
                f"calibrated inputs: {list(self._curves)}"
            ) from None

    def prepare_inverse(self) -> None:
        """Precompute ``to_u`` at every integer PWM of every curve (see
        :meth:`CalibrationCurve.prepare_inverse`): before a run, not during its ticks."""
        for curve in self._curves.values():
            curve.prepare_inverse()

    def check_names(self, input_names: Sequence[str]) -> None:
        """Raise :class:`CalibrationError` if a curve names an input not in ``input_names``."""
        unknown = [name for name in self._curves if name not in input_names]
        if unknown:
            raise CalibrationError(
                f"{self.source or 'calibration'}: curve(s) for unknown input(s) {unknown}; "
                f"the vehicle's inputs are {list(input_names)}"
            )

    # ------------------------------------------------------------------ conversions
    def _clip(
        self, name: str, values: np.ndarray, bounds: tuple[float, float], *, what: str, clip: bool
    ) -> tuple[np.ndarray, bool]:
        lo, hi = bounds
        if not np.all(np.isfinite(values)):
            raise CalibrationError(f"input {name!r}: {what} {values.tolist()} is not finite")
        outside = (values < lo) | (values > hi)
        if not outside.any():
            return values, False
        bad = values[outside]
        if not clip:
            raise CalibrationError(
                f"{self.source or 'calibration'}: input {name!r}: {what} {bad.tolist()} outside "
                f"the calibrated range {lo}..{hi} (no extrapolation)"
            )
        if self.clip_counts[name] == 0:
            logger.warning(
                "calibration of %r: %s %s outside the table range %g..%g, clipped "
                "(further clips of this input are logged at DEBUG)",
                name,
                what,
                bad.tolist(),
                lo,
                hi,
            )
        else:
            logger.debug("calibration of %r: %s %s clipped", name, what, bad.tolist())
        self.clip_counts[name] += int(outside.sum())
        return np.clip(values, lo, hi), True

    def to_pwm_checked(
        self, name: str, u: ArrayLike, *, clip: bool = True
    ) -> tuple[float | np.ndarray, bool]:
        """``(pwm, clipped)``: the signed PWM [wire units, float] for ``u`` and whether any
        value was clipped to the table range.

        Raises:
            CalibrationError: unknown input, non-finite u, or out of range with ``clip=False``.
        """
        curve = self.curve(name)
        if isinstance(u, float | int) and not isinstance(u, bool):
            value = float(u)
            lo, hi = curve._u_bounds
            if lo <= value <= hi:  # the common case: one value inside the table (not NaN)
                return curve.pwm_at_scalar(value), False
        values = np.asarray(u, dtype=np.float64)
        inside, clipped = self._clip(name, values, curve.u_range, what="u", clip=clip)
        if inside.ndim == 0:
            return curve.pwm_at_scalar(float(inside)), clipped
        return curve.pwm_at(inside), clipped

    def to_u_checked(
        self, name: str, pwm: ArrayLike, *, clip: bool = True
    ) -> tuple[float | np.ndarray, bool]:
        """``(u, clipped)``: the input for a signed PWM [wire units] and whether it was clipped.

        Raises:
            CalibrationError: unknown input, non-finite PWM, or out of range with ``clip=False``.
        """
        curve = self.curve(name)
        if isinstance(pwm, float | int) and not isinstance(pwm, bool):
            value = float(pwm)
            lo, hi = curve._pwm_bounds
            if lo <= value <= hi:  # the common case: one duty inside the table (not NaN)
                return curve.u_at_scalar(value), False
        values = np.asarray(pwm, dtype=np.float64)
        inside, clipped = self._clip(name, values, curve.pwm_range, what="pwm", clip=clip)
        if inside.ndim == 0:
            return curve.u_at_scalar(float(inside)), clipped
        return curve.u_at(inside), clipped

    @overload
    def to_pwm(self, name: str, u: float, *, clip: bool = ...) -> float: ...
    @overload
    def to_pwm(self, name: str, u: ArrayLike, *, clip: bool = ...) -> float | np.ndarray: ...
    def to_pwm(self, name: str, u: ArrayLike, *, clip: bool = True) -> float | np.ndarray:
        """Signed PWM duty [wire units, float] for input ``name`` at ``u`` (clipped, logged)."""
        return self.to_pwm_checked(name, u, clip=clip)[0]

    @overload
    def to_u(self, name: str, pwm: float, *, clip: bool = ...) -> float: ...
    @overload
    def to_u(self, name: str, pwm: ArrayLike, *, clip: bool = ...) -> float | np.ndarray: ...
    def to_u(self, name: str, pwm: ArrayLike, *, clip: bool = True) -> float | np.ndarray:
        """Input value ``u`` of ``name`` for a signed PWM duty (inverse of :meth:`to_pwm`)."""
        return self.to_u_checked(name, pwm, clip=clip)[0]

    # ------------------------------------------------------------------ files
    @classmethod
    def from_file(cls, path: str | Path) -> Calibration:
        """Load the TOML format of the module docstring.

        Raises:
            CalibrationError: unreadable file, bad TOML, missing/unknown keys, bad tables; the
                message names the file and the key (``calibration.inputs[1].u``).
        """
        file = Path(path)
        try:
            text = file.read_text(encoding="utf-8")
        except OSError as exc:
            raise CalibrationError(f"{file}: cannot read calibration file: {exc}") from None
        return cls.from_toml(text, source=str(file))

    @classmethod
    def from_toml(cls, text: str, *, source: str = "<string>") -> Calibration:
        """Parse calibration TOML text (see :meth:`from_file`)."""
        try:
            document = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise CalibrationError(f"{source}: not valid TOML: {exc}") from None
        extra = [key for key in document if key != "calibration"]
        if extra:
            raise CalibrationError(f"{source}: unknown top-level key(s) {extra}")
        table = document.get("calibration")
        if not isinstance(table, dict):
            raise CalibrationError(f"{source}: missing [calibration] table")
        unknown = sorted(set(table) - _TOP_KEYS)
        if unknown:
            raise CalibrationError(
                f"{source}: unknown key(s) calibration.{unknown[0]} (known: {sorted(_TOP_KEYS)})"
            )
        vehicle_id = table.get("vehicle_id", "")
        if not isinstance(vehicle_id, str):
            raise CalibrationError(
                f"{source}: calibration.vehicle_id must be a string, got {vehicle_id!r}"
            )
        date = table.get("date", "")
        if isinstance(date, _dt.date):
            date = date.isoformat()
        if not isinstance(date, str):
            raise CalibrationError(
                f"{source}: calibration.date must be a date or string, got {date!r}"
            )
        inputs = table.get("inputs")
        if not isinstance(inputs, list) or not inputs:
            raise CalibrationError(
                f"{source}: calibration.inputs must be a non-empty array of tables "
                "([[calibration.inputs]])"
            )
        curves = []
        for index, entry in enumerate(inputs):
            key = f"calibration.inputs[{index}]"
            if not isinstance(entry, dict):
                raise CalibrationError(f"{source}: {key} must be a table, got {entry!r}")
            unknown = sorted(set(entry) - _INPUT_KEYS)
            if unknown:
                raise CalibrationError(
                    f"{source}: unknown key {key}.{unknown[0]} (known: {sorted(_INPUT_KEYS)})"
                )
            for required in ("name", "u", "pwm"):
                if required not in entry:
                    raise CalibrationError(f"{source}: {key}.{required} is missing")
            for list_key in ("u", "pwm"):
                values = entry[list_key]
                if not isinstance(values, list) or not all(
                    isinstance(v, int | float) and not isinstance(v, bool) for v in values
                ):
                    raise CalibrationError(
                        f"{source}: {key}.{list_key} must be a list of numbers, got {values!r}"
                    )
            curves.append(
                CalibrationCurve.build(
                    entry["name"],
                    entry["u"],
                    entry["pwm"],
                    unit=entry.get("unit", ""),
                    where=f"{source}: {key}",
                )
            )
        return cls(curves, vehicle_id=vehicle_id, date=date, source=source)

    def to_toml(self) -> str:
        """The calibration in the file format (round-trips through :meth:`from_toml`)."""
        lines = [
            "[calibration]",
            f"vehicle_id = {_toml_string(self.vehicle_id)}",
            f"date = {_toml_string(self.date)}",
        ]
        for curve in self._curves.values():
            lines += [
                "",
                "[[calibration.inputs]]",
                f"name = {_toml_string(curve.name)}",
                f"unit = {_toml_string(curve.unit)}",
                f"u = [{', '.join(_toml_number(v) for v in curve.u)}]",
                f"pwm = [{', '.join(_toml_number(v) for v in curve.pwm)}]",
            ]
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> Path:
        """Write the calibration file to ``path`` (TOML) and return the path."""
        file = Path(path)
        try:
            file.write_text(self.to_toml(), encoding="utf-8")
        except OSError as exc:
            raise CalibrationError(f"{file}: cannot write calibration file: {exc}") from None
        return file

    def __repr__(self) -> str:
        return f"Calibration({list(self._curves)}, vehicle_id={self.vehicle_id!r})"


def _toml_string(text: str) -> str:
    escaped = text.replace("\\", "\\\\").replace('"', '\\"')
    return f'"{escaped}"'


def _toml_number(value: Any) -> str:
    number = float(value)
    if number.is_integer() and abs(number) < 2**53:
        return str(int(number))
    return repr(number) if math.isfinite(number) else "nan"

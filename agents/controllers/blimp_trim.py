"""Trim, linearisation, LQR and gain scheduling for the Blimpduino (thesis §4.4.1-§4.4.2).

Pipeline, for every point of a grid of (airspeed V_D, heading ψ_D, thrust angle μ_D):

1. **Trim** — minimise ``J = QᵀQ`` (``scipy.optimize.least_squares``) over the reduced state
   ``s = [u, v, w, r, x, y, z, ψ]`` and input ``[T_l, T_r, μ]`` where the residual vector Q
   holds the thesis' desired flight conditions: no acceleration (u̇, v̇, ẇ, ṙ), no angular
   velocity (r), symmetric thrust (T_l - T_r), forward speed (u - |u|), airspeed (V_D - V),
   heading (ψ_D - ψ), thrust angle (μ_D - μ), and the position (0, 0, z_trim) the thesis trims
   around (altitude 1 m: z = -1 in the NED world frame). Combinations with no equilibrium
   (e.g. flying forward with the thrust pointing up) keep J > 0 and are flagged infeasible.
2. **Linearise** — A = ∂f/∂s, B = ∂f/∂u by central differences (eq. 4.21).
3. **LQR** — per flight mode, on the part of the state that mode controls (the "state
   adjustment" of §4.4.3): ``K = R⁻¹ Bᵀ P`` with P from ``scipy.linalg.solve_continuous_are``
   (eq. 4.24). At zero airspeed the full 8-state system is not stabilisable (no side force,
   so the cross-track position cannot be controlled), which is why each mode uses a
   sub-state, selected by an orthonormal projection ``z = Π s``:

   ========  ===========================  ================================  ===============
   mode      trim points                  sub-state z                       inputs
   ========  ===========================  ================================  ===============
   vertical  V = 0, μ = -π/2              w, z                              T_l, T_r
   hover     V = 0, μ = 0                 u, r, along-heading position, ψ   T_l, T_r
   forward   V > 0, μ = 0                 u, v, r, cross-track position, ψ  T_l, T_r
   ========  ===========================  ================================  ===============

   The gain stored per trim point is ``K Π`` (2 x 8, on the reduced state error); the thrust
   angle is set by the mode (thrust along body x or z, §4.4.3), never by the LQR.
4. **Gain scheduling** — :meth:`GainSchedule.gain` interpolates ``K Π`` and the trim input
   linearly in airspeed and periodically in heading between grid points.

Cost: with the default grid (5 airspeeds x 12 headings x 2 thrust angles = 120 trims) building
the schedule takes about 1-2 s on one core; it is built on first use and cached per
(parameters, grid, weights) in memory for the life of the process (:func:`gain_schedule`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from hilswarm.agents.errors import ControllerError
from hilswarm.agents.sim.blimp import BlimpPlant, wrap_angle
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS, BlimpParams
from numpy.typing import ArrayLike
from scipy.linalg import solve_continuous_are
from scipy.optimize import least_squares

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_GRID",
    "DEFAULT_WEIGHTS",
    "FlightMode",
    "GainSchedule",
    "ModeWeights",
    "ScheduleGrid",
    "TrimPoint",
    "central_jacobians",
    "find_trim",
    "gain_schedule",
    "lqr",
    "mode_projection",
    "riccati_residual",
    "trim_residuals",
]

#: Index of each reduced state in ``s = [u, v, w, r, x, y, z, ψ]``.
U, V, W, R, X, Y, Z, PSI = range(8)
#: Altitude the thesis trims around: 1 m, i.e. z = -1 in the NED world frame.
TRIM_Z = -1.0
#: A trim with J below this is an equilibrium.
FEASIBLE_J = 1e-10


class FlightMode(StrEnum):
    """Flight modes of §4.4.3 that have their own LQR sub-state (see module docstring)."""

    VERTICAL = "vertical"
    HOVER = "hover"
    FORWARD = "forward"


#: Thrust angle [rad] each mode holds (thrust along body -z, i.e. up, or body x).
MODE_THRUST_ANGLE: dict[FlightMode, float] = {
    FlightMode.VERTICAL: -math.pi / 2,
    FlightMode.HOVER: 0.0,
    FlightMode.FORWARD: 0.0,
}


@dataclass(frozen=True)
class ScheduleGrid:
    """The trim grid.

    Attributes:
        airspeeds: V_D [m/s], increasing, first entry 0 (hover), >= 2 entries.
        headings: number of headings ψ_D, evenly spaced over [-π, π) (>= 4).
        thrust_angles: μ_D [rad]; must contain -π/2 (vertical) and 0 (hover/forward).
    """

    airspeeds: tuple[float, ...] = (0.0, 0.05, 0.1, 0.2, 0.3)
    headings: int = 12
    thrust_angles: tuple[float, ...] = (-math.pi / 2, 0.0)

    def __post_init__(self) -> None:
        speeds = np.asarray(self.airspeeds, dtype=float)
        if speeds.ndim != 1 or speeds.size < 2 or speeds[0] != 0 or np.any(np.diff(speeds) <= 0):
            raise ControllerError(
                f"ScheduleGrid.airspeeds must start at 0 and increase (>= 2 entries) [m/s], "
                f"got {self.airspeeds}"
            )
        if (
            isinstance(self.headings, bool)
            or not isinstance(self.headings, int)
            or self.headings < 4
        ):
            raise ControllerError(
                f"ScheduleGrid.headings must be an int >= 4, got {self.headings!r}"
            )
        for needed in MODE_THRUST_ANGLE.values():
            if not any(math.isclose(a, needed, abs_tol=1e-12) for a in self.thrust_angles):
                raise ControllerError(
                    f"ScheduleGrid.thrust_angles must contain {needed} rad, "
                    f"got {self.thrust_angles}"
                )

    @property
    def heading_values(self) -> np.ndarray:
        """ψ_D grid [rad]: -π, -π + 2π/n, ..."""
        return -math.pi + 2.0 * math.pi * np.arange(self.headings) / self.headings


#: Default grid (120 trim points).
DEFAULT_GRID = ScheduleGrid()


@dataclass(frozen=True)
class ModeWeights:
    """LQR weights by Bryson's rule: Q_ii = 1 / (largest acceptable deviation)².

    Attributes:
        vertical: largest deviations of (w [m/s], z [m]).
        hover: of (u [m/s], r [rad/s], along-heading position [m], ψ [rad]).
        forward: of (u [m/s], v [m/s], r [rad/s], cross-track position [m], ψ [rad]).
        thrust_n: largest acceptable thrust deviation [N] (R = 1/thrust_n² per thruster).
    """

    vertical: tuple[float, ...] = (0.2, 0.15)
    hover: tuple[float, ...] = (0.1, 0.3, 0.3, 0.15)
    forward: tuple[float, ...] = (0.1, 1.0, 0.3, 0.02, 0.5)
    thrust_n: float = 0.03

    def of(self, mode: FlightMode) -> tuple[float, ...]:
        """Largest deviations of ``mode``'s sub-state."""
        return {
            FlightMode.VERTICAL: self.vertical,
            FlightMode.HOVER: self.hover,
            FlightMode.FORWARD: self.forward,
        }[mode]


#: Default weights.
DEFAULT_WEIGHTS = ModeWeights()


# --- trim ----------------------------------------------------------------------------------


def trim_residuals(
    plant: BlimpPlant,
    decision: np.ndarray,
    airspeed: float,
    heading: float,
    thrust_angle: float,
    *,
    trim_z: float = TRIM_Z,
) -> np.ndarray:
    """The thesis' trim objective vector Q(s, u) (§4.4.1); J = QᵀQ.

    ``decision = [s (8), T_l, T_r, μ]``. Accelerations are in [m/s²] and [rad/s²], the rest
    in their own units; thrust terms are scaled by 1/thrust_limit so all entries are O(1).
    """
    s, u = decision[:8], decision[8:]
    rate = plant.reduced_dynamics(s, u)
    limit = plant.params.thrust_limit_n
    speed = math.sqrt(s[U] ** 2 + s[V] ** 2 + s[W] ** 2)
    return np.array(
        [
            rate[U],
            rate[V],
            rate[W],
            rate[R],
            s[R],
            (u[0] - u[1]) / limit,
            s[U] - abs(s[U]),
            airspeed - speed,
            wrap_angle(heading - s[PSI]),
            thrust_angle - u[2],
            s[X],
            s[Y],
            s[Z] - trim_z,
        ]
    )


@dataclass(frozen=True)
class TrimPoint:
    """One trim point and its linearisation.

    Attributes:
        airspeed, heading, thrust_angle: the requested (V_D [m/s], ψ_D [rad], μ_D [rad]).
        state: trimmed reduced state s* = [u, v, w, r, x, y, z, ψ].
        inputs: trimmed input u* = [T_l, T_r, μ] [N, N, rad].
        cost: J = QᵀQ at the optimum.
        feasible: J < FEASIBLE_J (a true equilibrium).
        A, B: Jacobians ∂f/∂s (8x8) and ∂f/∂u (8x3) at (s*, u*).
    """

    airspeed: float
    heading: float
    thrust_angle: float
    state: np.ndarray
    inputs: np.ndarray
    cost: float
    feasible: bool
    A: np.ndarray
    B: np.ndarray


def central_jacobians(
    f: Callable[[np.ndarray, np.ndarray], np.ndarray],
    s: ArrayLike,
    u: ArrayLike,
    *,
    step: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """``(∂f/∂s, ∂f/∂u)`` at (s, u) by central differences with relative step ``step``."""
    s0 = np.asarray(s, dtype=float)
    u0 = np.asarray(u, dtype=float)
    n = f(s0, u0).shape[0]

    def jac(point: np.ndarray, call: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        out = np.empty((n, point.size))
        for i in range(point.size):
            h = step * max(1.0, abs(point[i]))
            plus, minus = point.copy(), point.copy()
            plus[i] += h
            minus[i] -= h
            out[:, i] = (call(plus) - call(minus)) / (2.0 * h)
        return out

    return jac(s0, lambda x: f(x, u0)), jac(u0, lambda v: f(s0, v))


def find_trim(
    plant: BlimpPlant,
    airspeed: float,
    heading: float,
    thrust_angle: float,
    *,
    trim_z: float = TRIM_Z,
) -> TrimPoint:
    """Trim the reduced model at (V_D, ψ_D, μ_D) and linearise it there.

    Raises:
        ControllerError: the optimiser failed outright.
    """
    p = plant.params
    limit = p.thrust_limit_n
    # Initial guess: straight flight at V_D, each thruster carrying half the drag.
    drag = p.damping_linear[0] * airspeed + p.damping_quadratic[0] * airspeed**2
    along = math.cos(thrust_angle)
    thrust = drag / (2.0 * along) if abs(along) > 0.1 else 0.0
    thrust = min(max(thrust, -0.99 * limit), 0.99 * limit)
    guess = np.array(
        [airspeed, 0, 0, 0, 0, 0, trim_z, heading, thrust, thrust, thrust_angle], dtype=float
    )
    lower = np.full(11, -np.inf)
    upper = np.full(11, np.inf)
    lower[8:10], upper[8:10] = -limit, limit
    result = least_squares(
        lambda z: trim_residuals(plant, z, airspeed, heading, thrust_angle, trim_z=trim_z),
        guess,
        bounds=(lower, upper),
        xtol=1e-14,
        ftol=1e-14,
        gtol=1e-14,
        max_nfev=2000,
    )
    if result.status < 0:
        raise ControllerError(
            f"trim at V={airspeed} m/s, ψ={heading} rad, μ={thrust_angle} rad failed: "
            f"{result.message}"
        )
    state, inputs = result.x[:8].copy(), result.x[8:].copy()
    cost = float(2.0 * result.cost)  # least_squares reports ½ QᵀQ
    a, b = central_jacobians(plant.reduced_dynamics, state, inputs)
    return TrimPoint(
        airspeed=float(airspeed),
        heading=float(heading),
        thrust_angle=float(thrust_angle),
        state=state,
        inputs=inputs,
        cost=cost,
        feasible=cost < FEASIBLE_J,
        A=a,
        B=b,
    )


# --- LQR -----------------------------------------------------------------------------------


def lqr(
    a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Infinite-horizon continuous LQR (MATLAB ``lqr``): returns ``(K, P)``, ``K = R⁻¹ Bᵀ P``.

    Raises:
        ControllerError: the Riccati equation has no stabilising solution.
    """
    try:
        p = solve_continuous_are(a, b, q, r)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise ControllerError(f"LQR: no stabilising Riccati solution ({exc})") from None
    k = np.linalg.solve(r, b.T @ p)
    return k, p


def riccati_residual(
    a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray, p: np.ndarray
) -> np.ndarray:
    """``AᵀP + PA + Q - P B R⁻¹ Bᵀ P`` (zero for the LQR solution, eq. 4.24)."""
    return a.T @ p + p @ a + q - p @ b @ np.linalg.solve(r, b.T @ p)


def mode_projection(mode: FlightMode, heading: float) -> np.ndarray:
    """Orthonormal rows Π mapping the reduced state error to ``mode``'s sub-state.

    Along-heading position = cos ψ x + sin ψ y; cross-track = -sin ψ x + cos ψ y.
    """
    c, s = math.cos(heading), math.sin(heading)

    def unit(index: int) -> np.ndarray:
        row = np.zeros(8)
        row[index] = 1.0
        return row

    along = np.zeros(8)
    along[[X, Y]] = c, s
    cross = np.zeros(8)
    cross[[X, Y]] = -s, c
    rows = {
        FlightMode.VERTICAL: [unit(W), unit(Z)],
        FlightMode.HOVER: [unit(U), unit(R), along, unit(PSI)],
        FlightMode.FORWARD: [unit(U), unit(V), unit(R), cross, unit(PSI)],
    }[mode]
    return np.array(rows)


@dataclass(frozen=True)
class ModeGain:
    """The LQR of one mode at one trim point.

    Attributes:
        projection: Π (n_sub x 8).
        a_sub, b_sub: Π A Πᵀ and Π B[:, :2].
        q, r: weights.
        k_sub: LQR gain on the sub-state (2 x n_sub).
        p: Riccati solution.
        gain: K Π (2 x 8), applied to the reduced state error s - s_ref.
    """

    projection: np.ndarray
    a_sub: np.ndarray
    b_sub: np.ndarray
    q: np.ndarray
    r: np.ndarray
    k_sub: np.ndarray
    p: np.ndarray
    gain: np.ndarray


def mode_gain(trim: TrimPoint, mode: FlightMode, weights: ModeWeights) -> ModeGain:
    """LQR of ``mode`` on the linearisation at ``trim`` (see module docstring)."""
    projection = mode_projection(mode, trim.heading)
    a_sub = projection @ trim.A @ projection.T
    b_sub = projection @ trim.B[:, :2]
    q = np.diag(1.0 / np.square(np.asarray(weights.of(mode), dtype=float)))
    r = np.eye(2) / weights.thrust_n**2
    k_sub, p = lqr(a_sub, b_sub, q, r)
    return ModeGain(projection, a_sub, b_sub, q, r, k_sub, p, k_sub @ projection)


# --- the schedule --------------------------------------------------------------------------


@dataclass
class GainSchedule:
    """Trim points and per-mode LQR gains over a :class:`ScheduleGrid`, with interpolation.

    Attributes:
        params: the blimp parameters.
        grid: the grid.
        weights: the LQR weights.
        trims: ``trims[i_speed][i_heading][i_angle]`` -> :class:`TrimPoint`.
        gains: ``gains[mode][i_speed][i_heading]`` -> :class:`ModeGain` (``None`` where the
            mode does not apply: vertical/hover only at V = 0, forward only at V > 0).
        build_seconds: wall time it took to build [s].
    """

    params: BlimpParams
    grid: ScheduleGrid
    weights: ModeWeights
    trims: list[list[list[TrimPoint]]] = field(default_factory=list)
    gains: dict[FlightMode, list[list[ModeGain | None]]] = field(default_factory=dict)
    build_seconds: float = 0.0

    @classmethod
    def build(
        cls,
        params: BlimpParams = DEFAULT_BLIMP_PARAMS,
        grid: ScheduleGrid = DEFAULT_GRID,
        weights: ModeWeights = DEFAULT_WEIGHTS,
    ) -> GainSchedule:
        """Trim, linearise and compute every gain (takes ~10 ms per trim point)."""
        started = time.perf_counter()
        plant = BlimpPlant(params)
        schedule = cls(params=params, grid=grid, weights=weights)
        headings = grid.heading_values
        schedule.trims = [
            [[find_trim(plant, v, psi, mu) for mu in grid.thrust_angles] for psi in headings]
            for v in grid.airspeeds
        ]
        for mode in FlightMode:
            angle_index = schedule._angle_index(MODE_THRUST_ANGLE[mode])
            table: list[list[ModeGain | None]] = []
            for i, speed in enumerate(grid.airspeeds):
                applies = (speed == 0) == (mode is not FlightMode.FORWARD)
                row: list[ModeGain | None] = []
                for j in range(len(headings)):
                    trim = schedule.trims[i][j][angle_index]
                    if applies and not trim.feasible:
                        raise ControllerError(
                            f"no equilibrium for mode {mode} at V={speed} m/s, "
                            f"ψ={trim.heading:.3f} rad (J={trim.cost:.3g})"
                        )
                    row.append(mode_gain(trim, mode, weights) if applies else None)
                table.append(row)
            schedule.gains[mode] = table
        schedule.build_seconds = time.perf_counter() - started
        logger.info(
            "blimp gain schedule: %d trim points in %.2f s",
            len(grid.airspeeds) * len(headings) * len(grid.thrust_angles),
            schedule.build_seconds,
        )
        return schedule

    def _angle_index(self, angle: float) -> int:
        for index, value in enumerate(self.grid.thrust_angles):
            if math.isclose(value, angle, abs_tol=1e-12):
                return index
        raise ControllerError(
            f"thrust angle {angle} rad is not on the grid {self.grid.thrust_angles}"
        )

    def _heading_weights(self, heading: float) -> tuple[int, int, float]:
        n = self.grid.headings
        position = (wrap_angle(heading) + math.pi) / (2.0 * math.pi) * n
        lower = math.floor(position) % n
        fraction = position - math.floor(position)
        return lower, (lower + 1) % n, fraction

    def _speed_weights(self, mode: FlightMode, airspeed: float) -> tuple[int, int, float]:
        speeds = self.grid.airspeeds
        if mode is not FlightMode.FORWARD:
            return 0, 0, 0.0
        low_index, high_index = 1, len(speeds) - 1
        v = min(max(airspeed, speeds[low_index]), speeds[high_index])
        i = int(np.searchsorted(speeds, v, side="right")) - 1
        i = min(max(i, low_index), high_index - 1) if high_index > low_index else low_index
        if high_index == low_index:
            return low_index, low_index, 0.0
        fraction = (v - speeds[i]) / (speeds[i + 1] - speeds[i])
        return i, i + 1, fraction

    def _blend(
        self,
        mode: FlightMode,
        airspeed: float,
        heading: float,
        pick: Callable[[int, int], np.ndarray],
    ) -> np.ndarray:
        i0, i1, fv = self._speed_weights(mode, airspeed)
        j0, j1, fh = self._heading_weights(heading)
        return (
            (1 - fv) * (1 - fh) * pick(i0, j0)
            + (1 - fv) * fh * pick(i0, j1)
            + fv * (1 - fh) * pick(i1, j0)
            + fv * fh * pick(i1, j1)
        )

    def gain(self, mode: FlightMode, airspeed: float, heading: float) -> np.ndarray:
        """Interpolated thrust gain K Π (2 x 8) for ``mode`` at (V [m/s], ψ [rad]).

        Airspeed is clamped to the mode's grid range (forward: the smallest V > 0 to the
        largest); heading interpolation is periodic.
        """
        table = self.gains[mode]

        def pick(i: int, j: int) -> np.ndarray:
            entry = table[i][j]
            if entry is None:  # pragma: no cover - guarded by _speed_weights
                raise ControllerError(f"no {mode} gain at grid point ({i}, {j})")
            return entry.gain

        return self._blend(mode, airspeed, heading, pick)

    def trim_input(self, mode: FlightMode, airspeed: float, heading: float) -> np.ndarray:
        """Interpolated trim input u* = [T_l, T_r, μ] for ``mode`` at (V, ψ)."""
        k = self._angle_index(MODE_THRUST_ANGLE[mode])
        return self._blend(mode, airspeed, heading, lambda i, j: self.trims[i][j][k].inputs)

    def trim_points(self) -> list[TrimPoint]:
        """All trim points, flattened."""
        return [t for row in self.trims for cell in row for t in cell]


_CACHE: dict[tuple[BlimpParams, ScheduleGrid, ModeWeights], GainSchedule] = {}


def gain_schedule(
    params: BlimpParams = DEFAULT_BLIMP_PARAMS,
    grid: ScheduleGrid = DEFAULT_GRID,
    weights: ModeWeights = DEFAULT_WEIGHTS,
) -> GainSchedule:
    """The schedule for (params, grid, weights), built on first use and cached in memory."""
    key = (params, grid, weights)
    schedule = _CACHE.get(key)
    if schedule is None:
        schedule = GainSchedule.build(params, grid, weights)
        _CACHE[key] = schedule
    return schedule

"""Continuous-time plant models and fixed-step integrators.

A :class:`ContinuousPlant` is described python-control style by its sizes and two functions:

* ``dynamics(t, x, u) -> dx/dt`` — state derivative at time ``t`` [s], per second;
* ``output(t, x, u) -> y`` — the measured output.

The plant itself has no time step. The **dt contract** of :meth:`ContinuousPlant.advance` is
the one of a sampled-data loop: the input ``u`` is held constant (zero-order hold) over
``[t, t + dt]`` and the state is integrated over that interval with ``substeps`` equal fixed
steps of Euler (the thesis' ``ode1``) or classic RK4 (``ode4``). A SIL run with Euler and
one substep per control period is, tick for tick, what a SHIL run computes.

Also here: :class:`PoseSource` (anything with a world pose) and, re-exported from
``link.sim_board``, the :class:`PinPlant` protocol (a plant behind a simulated *board*: pin
outputs in wire units in, analog voltages out).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
from hilswarm.agents.errors import PlantError
from hilswarm.agents.link.sim_board import PinPlant
from numpy.typing import ArrayLike

#: Fixed-step methods understood by :func:`integrate` and :meth:`ContinuousPlant.advance`.
METHODS = ("euler", "rk4")

__all__ = [
    "METHODS",
    "ContinuousPlant",
    "LinearPlant",
    "PinPlant",
    "PoseSource",
    "euler_step",
    "integrate",
    "rk4_step",
    "wrap_angle",
]

Rate = Callable[[float, np.ndarray], np.ndarray]


def euler_step(rate: Rate, t: float, x: np.ndarray, h: float) -> np.ndarray:
    """One explicit Euler step: ``x + h * rate(t, x)`` (local error O(h^2), global O(h))."""
    return x + h * rate(t, x)


def rk4_step(rate: Rate, t: float, x: np.ndarray, h: float) -> np.ndarray:
    """One classic fourth-order Runge-Kutta step (local error O(h^5), global O(h^4))."""
    k1 = rate(t, x)
    k2 = rate(t + h / 2, x + h / 2 * k1)
    k3 = rate(t + h / 2, x + h / 2 * k2)
    k4 = rate(t + h, x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


_STEPS: dict[str, Callable[[Rate, float, np.ndarray, float], np.ndarray]] = {
    "euler": euler_step,
    "rk4": rk4_step,
}


def wrap_angle(angle: float) -> float:
    """Wrap an angle [rad] to [-π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def check_method(method: str, substeps: int) -> None:
    """Raise :class:`PlantError` unless ``method`` is known and ``substeps`` an int >= 1."""
    if method not in _STEPS:
        raise PlantError(f"integration method must be one of {METHODS}, got {method!r}")
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise PlantError(f"substeps must be an int >= 1, got {substeps!r}")


def integrate(
    rate: Rate,
    t: float,
    x: ArrayLike,
    dt: float,
    *,
    method: str = "euler",
    substeps: int = 1,
) -> np.ndarray:
    """Advance ``dx/dt = rate(t, x)`` from time ``t`` [s] over ``dt`` [s].

    Uses ``substeps`` equal steps of size ``dt / substeps`` of ``method`` (``"euler"`` or
    ``"rk4"``).

    Raises:
        PlantError: unknown method, bad ``substeps`` or negative/non-finite ``dt``.
    """
    check_method(method, substeps)
    finite = math.isfinite(dt) if isinstance(dt, float | int) else bool(np.isfinite(dt))
    if not finite or dt < 0:
        raise PlantError(f"dt must be a finite interval >= 0 [s], got {dt!r}")
    step = _STEPS[method]
    h = dt / substeps
    state = np.array(x, dtype=np.float64)
    for i in range(substeps):
        state = step(rate, t + i * h, state, h)
    return state


class ContinuousPlant(ABC):
    """A continuous-time plant ``dx/dt = dynamics(t, x, u)``, ``y = output(t, x, u)``.

    Subclasses set the instance attributes :attr:`n_states`, :attr:`n_inputs`,
    :attr:`n_outputs` (call :meth:`_set_sizes`) and implement :meth:`dynamics`; the default
    :meth:`output` is the full state. Names default to ``x0..``, ``u0..``, ``y0..``.
    """

    n_states: int
    n_inputs: int
    n_outputs: int
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]

    def _set_sizes(
        self,
        n_states: int,
        n_inputs: int,
        n_outputs: int,
        *,
        state_names: Sequence[str] | None = None,
        input_names: Sequence[str] | None = None,
        output_names: Sequence[str] | None = None,
    ) -> None:
        """Set sizes and names (names must match the sizes)."""
        plant = type(self).__name__
        for label, size in (
            ("n_states", n_states),
            ("n_inputs", n_inputs),
            ("n_outputs", n_outputs),
        ):
            if isinstance(size, bool) or not isinstance(size, int) or size < 0:
                raise PlantError(f"{plant}: {label} must be an int >= 0, got {size!r}")
        self.n_states, self.n_inputs, self.n_outputs = n_states, n_inputs, n_outputs
        for attr, names, size, prefix in (
            ("state_names", state_names, n_states, "x"),
            ("input_names", input_names, n_inputs, "u"),
            ("output_names", output_names, n_outputs, "y"),
        ):
            chosen = (
                tuple(names) if names is not None else tuple(f"{prefix}{i}" for i in range(size))
            )
            if len(chosen) != size:
                raise PlantError(f"{plant}: {attr} must have {size} names, got {chosen}")
            setattr(self, attr, chosen)

    @abstractmethod
    def dynamics(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``dx/dt`` at time ``t`` [s] for state ``x`` and input ``u``."""

    def output(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The output ``y`` (default: the whole state)."""
        if self.n_outputs != self.n_states:
            raise PlantError(
                f"{type(self).__name__}: the default output is the state, but n_outputs="
                f"{self.n_outputs} != n_states={self.n_states}; override output()"
            )
        return np.array(x, dtype=np.float64)

    def check_state(self, x: ArrayLike) -> np.ndarray:
        """``x`` as a float vector of ``n_states`` entries, or :class:`PlantError`."""
        return self._vector("state", x, self.n_states)

    def check_input(self, u: ArrayLike) -> np.ndarray:
        """``u`` as a float vector of ``n_inputs`` entries, or :class:`PlantError`."""
        return self._vector("input", u, self.n_inputs)

    def _vector(self, what: str, value: ArrayLike, size: int) -> np.ndarray:
        try:
            vector = np.array(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise PlantError(f"{type(self).__name__}: {what} is not numeric: {exc}") from None
        if vector.shape != (size,):
            raise PlantError(
                f"{type(self).__name__}: {what} must have {size} entries, got {vector.shape[0]}"
            )
        return vector

    def advance(
        self,
        t: float,
        x: ArrayLike,
        u: ArrayLike,
        dt: float,
        *,
        method: str = "euler",
        substeps: int = 1,
    ) -> np.ndarray:
        """The state at ``t + dt`` from ``x`` at ``t``, with ``u`` held constant over ``dt``.

        Args:
            t: start time [s].
            x: state at ``t``.
            u: input, constant over the interval (zero-order hold).
            dt: interval [s] (one control period in a sampled-data loop).
            method: ``"euler"`` or ``"rk4"``.
            substeps: fixed steps per interval.

        Raises:
            PlantError: wrong sizes, method or ``dt``.
        """
        state = self.check_state(x)
        held = self.check_input(u)

        def rate(time: float, z: np.ndarray) -> np.ndarray:
            return np.asarray(self.dynamics(time, z, held), dtype=np.float64)

        return integrate(rate, t, state, dt, method=method, substeps=substeps)


def _matrix(plant: str, name: str, value: Any, flat: str = "row") -> np.ndarray:
    """A finite 2-D matrix; a scalar is 1x1, a flat list one row or one column (``flat``)."""
    try:
        matrix = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PlantError(f"{plant}: {name} must be a numeric matrix: {exc}") from None
    if matrix.ndim == 0:
        matrix = matrix.reshape(1, 1)
    elif matrix.ndim == 1:
        matrix = matrix.reshape(1, -1) if flat == "row" else matrix.reshape(-1, 1)
    if matrix.ndim != 2:
        raise PlantError(f"{plant}: {name} must be a 2-D matrix, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise PlantError(f"{plant}: {name} has non-finite entries")
    return matrix


class LinearPlant(ContinuousPlant):
    """``dx/dt = A x + B u``, ``y = C x + D u`` (TOML-like lists accepted).

    Args:
        A: n x n state matrix [1/s].
        B: n x m input matrix (a flat list is one column: a single input).
        C: p x n output matrix (default identity: ``y = x``; a flat list is one row).
        D: p x m feed-through (default zeros).
        state_names, input_names, output_names: optional names.

    Raises:
        PlantError: inconsistent shapes or non-finite entries.
    """

    def __init__(
        self,
        A: ArrayLike,
        B: ArrayLike,
        C: ArrayLike | None = None,
        D: ArrayLike | None = None,
        *,
        state_names: Sequence[str] | None = None,
        input_names: Sequence[str] | None = None,
        output_names: Sequence[str] | None = None,
    ) -> None:
        plant = type(self).__name__
        a = _matrix(plant, "A", A)
        n = a.shape[0]
        if a.shape != (n, n):
            raise PlantError(f"{plant}: A must be square, got shape {a.shape}")
        b = _matrix(plant, "B", B, flat="column")
        if b.shape[0] != n:
            raise PlantError(f"{plant}: B must have {n} rows (one per state), got {b.shape}")
        m = b.shape[1]
        c = np.eye(n) if C is None else _matrix(plant, "C", C)
        if c.shape[1] != n:
            raise PlantError(f"{plant}: C must have {n} columns, got shape {c.shape}")
        p = c.shape[0]
        d = np.zeros((p, m)) if D is None else _matrix(plant, "D", D)
        if d.shape != (p, m):
            raise PlantError(f"{plant}: D must have shape {(p, m)}, got {d.shape}")
        self.A, self.B, self.C, self.D = a, b, c, d
        self._set_sizes(
            n, m, p, state_names=state_names, input_names=input_names, output_names=output_names
        )

    def dynamics(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.A @ x + self.B @ u

    def output(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.C @ x + self.D @ u


@runtime_checkable
class PoseSource(Protocol):
    """Anything that knows a rigid-body pose.

    ``pose()`` returns ``[x, y, z, roll, pitch, yaw]``: position [m, world frame] and
    orientation [rad, roll-pitch-yaw of the body in the world frame].
    """

    def pose(self) -> np.ndarray: ...

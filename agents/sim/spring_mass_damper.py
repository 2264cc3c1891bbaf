"""The two-dimensional spring-mass-damper of thesis §3.2.2 (eqs. 3.1-3.3).

A mass ``m`` [kg] moves in a plane; a spring ``k1`` [N/m] and a damper ``c1`` [N s/m] act
along world x, ``k2`` and ``c2`` along world y, and the control forces ``F1``, ``F2`` [N] push
along x and y::

    m x'' = F1 - k1 x - c1 x'
    m y'' = F2 - k2 y - c2 y'                                   (3.1)

State ``z = [x, x', y, y']`` (position [m, world frame], velocity [m/s]), input
``u = [F1, F2]`` [N], output ``y = z`` (full state, as the thesis' full-state feedback needs).
With ``k1 = k2 = m = 1`` and ``c1 = c2 = 0`` the state matrix is eq. 3.3 with eigenvalues
``{±i, ±i}``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import ClassVar

import numpy as np
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.plant import LinearPlant
from numpy.typing import ArrayLike

STATE_NAMES = ("x", "xdot", "y", "ydot")
INPUT_NAMES = ("F1", "F2")


def _parameter(name: str, value: float, *, positive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise PlantError(f"SpringMassDamper: {name} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise PlantError(f"SpringMassDamper: {name} must be > 0, got {value!r}")
    if not positive and value < 0:
        raise PlantError(f"SpringMassDamper: {name} must be >= 0, got {value!r}")
    return float(value)


class SpringMassDamper(LinearPlant):
    """Thesis eqs. 3.1-3.2 as a :class:`LinearPlant` (defaults: eq. 3.3).

    Args:
        m: mass [kg] (> 0).
        k1: spring stiffness along x [N/m] (>= 0).
        k2: spring stiffness along y [N/m] (>= 0).
        c1: damping along x [N s/m] (>= 0).
        c2: damping along y [N s/m] (>= 0).

    Raises:
        PlantError: a parameter is not a finite number in its range.
    """

    #: Units of the inputs and outputs (recorded in the MCAP schemas, shown on plot axes).
    input_units: ClassVar[Mapping[str, str]] = {"F1": "N", "F2": "N"}
    output_units: ClassVar[Mapping[str, str]] = {"x": "m", "xdot": "m/s", "y": "m", "ydot": "m/s"}

    def __init__(
        self,
        m: float = 1.0,
        k1: float = 1.0,
        k2: float = 1.0,
        c1: float = 0.0,
        c2: float = 0.0,
    ) -> None:
        self.m = _parameter("m", m, positive=True)
        self.k1 = _parameter("k1", k1, positive=False)
        self.k2 = _parameter("k2", k2, positive=False)
        self.c1 = _parameter("c1", c1, positive=False)
        self.c2 = _parameter("c2", c2, positive=False)
        a = np.array(
            [
                [0.0, 1.0, 0.0, 0.0],
                [-self.k1 / self.m, -self.c1 / self.m, 0.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
                [0.0, 0.0, -self.k2 / self.m, -self.c2 / self.m],
            ]
        )
        b = np.array([[0.0, 0.0], [1.0 / self.m, 0.0], [0.0, 0.0], [0.0, 1.0 / self.m]])
        super().__init__(
            a, b, state_names=STATE_NAMES, input_names=INPUT_NAMES, output_names=STATE_NAMES
        )

    def energy(self, z: ArrayLike) -> float:
        """Mechanical energy [J] of state ``z``: kinetic plus spring potential."""
        x, xdot, y, ydot = self.check_state(z)
        kinetic = 0.5 * self.m * (xdot**2 + ydot**2)
        potential = 0.5 * self.k1 * x**2 + 0.5 * self.k2 * y**2
        return float(kinetic + potential)

"""The single integrator ``x' = u`` in ``n_dims`` dimensions (used by the consensus demo).

State and output ``x`` (e.g. a position [m, world frame]), input ``u`` its rate (e.g. a
velocity [m/s]); ``n_states = n_inputs = n_outputs = n_dims``.
"""

from __future__ import annotations

import numpy as np
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.plant import ContinuousPlant


class Integrator(ContinuousPlant):
    """``dx/dt = u``, ``y = x``, in ``n_dims`` dimensions.

    Args:
        n_dims: number of dimensions (>= 1).

    Raises:
        PlantError: ``n_dims`` is not an int >= 1.
    """

    def __init__(self, n_dims: int = 1) -> None:
        if isinstance(n_dims, bool) or not isinstance(n_dims, int) or n_dims < 1:
            raise PlantError(f"Integrator: n_dims must be an int >= 1, got {n_dims!r}")
        self.n_dims = n_dims
        self._set_sizes(n_dims, n_dims, n_dims)

    def dynamics(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.array(u, dtype=np.float64)

    def output(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.array(x, dtype=np.float64)

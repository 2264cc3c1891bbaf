"""Linear consensus of single-integrator agents.

Each agent ``i`` is a single integrator ``x_i' = u_i`` (vehicle ``"simulated"`` with plant
``"integrator"``, output ``y_i = x_i``) and applies the classic consensus protocol

    u_i = -gain * sum_j a_ij (y_i - y_j)

over the neighbours ``j`` it receives (``A[i][j] = 1`` in the experiment's graph), with
``a_ij = 1`` unless the ``weights`` parameter gives another weight. A neighbour whose output is
missing this tick (``None``) is left out of the sum. ``u_{k+1}`` is computed from ``y_k`` and
the neighbours' ``y_k``; ``y`` may be a vector (every component agrees independently), and ``u``
has the size of ``y``.

With an undirected (symmetric) connected graph the states converge to the average of the
initial states; with a directed graph that has a spanning tree, to a weighted average. With the
integrator advanced by Euler steps of ``dt``, convergence needs ``gain * dt * d_max < 1``
(``d_max`` the largest in-degree, weighted), which :meth:`LinearConsensus.step` does not check
because it does not know ``dt`` until the first tick; ``hilswarm check`` reports it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from hilswarm.agents.control import Controller, TickInput, all_finite
from hilswarm.agents.errors import ControllerError


class LinearConsensus(Controller):
    """``u_i = -gain * sum_j a_ij (y_i - y_j)`` over the neighbours with data.

    Parameters:
        gain: consensus gain [1/s] (> 0): the rate at which disagreement decays.
        weights: optional table neighbour name -> ``a_ij`` (>= 0); neighbours not listed
            weigh 1.
        u_max: optional bound on every entry of ``|u|`` [units of y per s] (> 0), or ``None``.
    """

    n_states: ClassVar[int] = 0
    default_params: ClassVar[Mapping[str, Any]] = {"gain": 1.0, "weights": None, "u_max": None}

    def validate_params(self, params: Mapping[str, Any]) -> dict[str, Any]:
        merged = super().validate_params(params)
        merged["gain"] = _positive_number(merged["gain"], "gain")
        if merged["u_max"] is not None:
            merged["u_max"] = _positive_number(merged["u_max"], "u_max")
        weights = merged["weights"]
        if weights is None:
            merged["weights"] = {}
        elif not isinstance(weights, Mapping):
            raise ControllerError(
                f"consensus param 'weights' must be a table name -> weight, got {weights!r}"
            )
        else:
            checked = {}
            for name, weight in weights.items():
                if (
                    isinstance(weight, bool)
                    or not isinstance(weight, int | float)
                    or not math.isfinite(weight)
                    or weight < 0
                ):
                    raise ControllerError(
                        f"consensus param 'weights.{name}' must be a number >= 0, got {weight!r}"
                    )
                checked[str(name)] = float(weight)
            merged["weights"] = checked
        return merged

    def step(
        self, tick: TickInput, x_hat: np.ndarray, params: Mapping[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        own = np.asarray(tick.y, dtype=np.float64).reshape(-1)
        disagreement = np.zeros_like(own)
        weights: Mapping[str, float] = params["weights"]
        for name, other in tick.neighbours.items():
            if other is None:
                continue
            value = np.asarray(other, dtype=np.float64).reshape(-1)
            if value.shape != own.shape:
                raise ControllerError(
                    f"consensus: neighbour {name!r} sent y of shape {value.shape}, this agent's "
                    f"y has shape {own.shape}; consensus needs outputs of the same size"
                )
            if not all_finite(value):
                continue
            disagreement += weights.get(name, 1.0) * (own - value)
        u_next = -params["gain"] * disagreement
        if params["u_max"] is not None:
            u_next = np.clip(u_next, -params["u_max"], params["u_max"])
        return u_next, x_hat


def _positive_number(value: Any, key: str) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value <= 0
    ):
        raise ControllerError(f"consensus param {key!r} must be a number > 0, got {value!r}")
    return float(value)

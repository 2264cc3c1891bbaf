"""Thesis chapter 3 (§3.2): spring-mass-damper with full-state feedback, SIL versus SHIL.

The maths shared by ``scripts/reproduce_chapter3.py`` and the tests:

* :func:`place_gains` — pole placement (``scipy.signal.place_poles``) for the plant of eq. 3.3
  and the poles ``{-2 ± 0.1i, -2 ± 0.1i}``; gives eq. 3.4, ``K = [[3.01, 4, 0, 0],
  [0, 0, 3.01, 4]]``. Each pole has multiplicity 2, which pole placement can only reach
  because the plant has 2 independent inputs (rank B = 2).
* :func:`sil_fixed_step` — software-in-the-loop: the closed loop ``z' = A z + B (-K z)``
  integrated with fixed-step Euler (the thesis' ``ode1``) or RK4 (``ode4``), one step per
  control period.
* :func:`sil_adaptive` — the same closed loop with adaptive Dormand-Prince (``solve_ivp``
  RK45, the ``ode45`` analogue), sampled at the tick times.
* :func:`shil` — simulated hardware-in-the-loop: a :class:`ControlModel` running a
  :class:`StateFeedback` controller and a :class:`SimulatedVehicle` running the plant exchange
  ``u`` and ``y`` once per tick through the Vehicle interface.

The control period defaults to ``DEFAULT_DT = 0.1 s``, the ``TimeToSim`` default (1/10 s) of
the thesis' SimulinkVehicle. SHIL with an Euler plant equals SIL-Euler at every tick (same
arithmetic: the controller computes ``u_{k+1} = -K z_k`` and the vehicle takes one Euler step
with it); SIL-RK45 differs by the discretisation error of that step, O(dt).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from hilswarm.agents.control import ControlModel, StateFeedback
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.plant import ContinuousPlant, integrate
from hilswarm.agents.sim.simulated_vehicle import SimulatedVehicle
from hilswarm.agents.sim.spring_mass_damper import SpringMassDamper
from numpy.typing import ArrayLike
from scipy.integrate import solve_ivp
from scipy.signal import place_poles

#: Closed-loop poles of §3.2.2 (each of multiplicity 2).
THESIS_POLES = (-2 + 0.1j, -2 - 0.1j, -2 + 0.1j, -2 - 0.1j)
#: Gain of eq. 3.4.
THESIS_GAIN = np.array([[3.01, 4.0, 0.0, 0.0], [0.0, 0.0, 3.01, 4.0]])
#: Initial condition of §3.2.3: z0 = [x, x', y, y'] = [4 m, 0 m/s, -4 m, 0 m/s].
THESIS_Z0 = (4.0, 0.0, -4.0, 0.0)
#: Control period [s]: the SimulinkVehicle's TimeToSim default (1/10 s).
DEFAULT_DT = 0.1
#: Simulated duration [s]: the closed loop (time constant 0.5 s) has settled well before.
DEFAULT_DURATION_S = 6.0


@dataclass(frozen=True)
class Trajectory:
    """States at the tick times.

    Attributes:
        label: what produced it (``"SIL-Euler"``, ``"SIL-RK45"``, ``"SHIL"``).
        t: tick times [s], shape ``(n + 1,)``.
        z: states ``[x, x', y, y']`` [m, m/s] at those times, shape ``(n + 1, 4)``.
        u: inputs ``[F1, F2]`` [N] applied during each tick, shape ``(n, 2)``; for the
            adaptive run the continuous feedback ``-K z`` at the tick times.
    """

    label: str
    t: np.ndarray
    z: np.ndarray
    u: np.ndarray


def place_gains(
    plant: SpringMassDamper | None = None, poles: Sequence[complex] = THESIS_POLES
) -> np.ndarray:
    """Full-state feedback gain ``K`` (``u = -K z``) placing the closed-loop ``poles``.

    Uses ``scipy.signal.place_poles`` (Yang-Tits method, which handles complex and repeated
    poles up to the rank of ``B``).
    """
    model = plant if plant is not None else SpringMassDamper()
    return np.asarray(place_poles(model.A, model.B, np.asarray(poles)).gain_matrix)


def tick_count(duration_s: float, dt: float) -> int:
    """Number of ticks covering ``duration_s`` [s] with period ``dt`` [s] (rounded)."""
    if not dt > 0 or not duration_s > 0:
        raise PlantError(f"duration_s and dt must be > 0 [s], got {duration_s!r}, {dt!r}")
    return round(duration_s / dt)


def sil_fixed_step(
    gain: ArrayLike,
    *,
    plant: ContinuousPlant | None = None,
    z0: ArrayLike = THESIS_Z0,
    dt: float = DEFAULT_DT,
    n_ticks: int,
    method: str = "euler",
) -> Trajectory:
    """Closed loop ``z' = f(z, -K z)`` with one fixed step of ``method`` per period ``dt``."""
    model = plant if plant is not None else SpringMassDamper()
    k_matrix = np.asarray(gain, dtype=np.float64)
    z = np.empty((n_ticks + 1, model.n_states))
    u = np.empty((n_ticks, model.n_inputs))
    z[0] = model.check_state(z0)
    for k in range(n_ticks):

        def closed_loop(t: float, state: np.ndarray) -> np.ndarray:
            return model.dynamics(t, state, -k_matrix @ state)

        u[k] = -k_matrix @ z[k]
        z[k + 1] = integrate(closed_loop, k * dt, z[k], dt, method=method)
    label = "SIL-Euler" if method == "euler" else f"SIL-{method.upper()}"
    return Trajectory(label, dt * np.arange(n_ticks + 1), z, u)


def sil_adaptive(
    gain: ArrayLike,
    *,
    plant: ContinuousPlant | None = None,
    z0: ArrayLike = THESIS_Z0,
    dt: float = DEFAULT_DT,
    n_ticks: int,
    rtol: float = 1e-6,
    atol: float = 1e-9,
) -> Trajectory:
    """Closed loop with adaptive RK45 (Dormand-Prince, like ``ode45``), sampled every ``dt``."""
    model = plant if plant is not None else SpringMassDamper()
    k_matrix = np.asarray(gain, dtype=np.float64)
    times = dt * np.arange(n_ticks + 1)

    def closed_loop(t: float, state: np.ndarray) -> np.ndarray:
        return model.dynamics(t, state, -k_matrix @ state)

    solution = solve_ivp(
        closed_loop,
        (0.0, float(times[-1])),
        model.check_state(z0),
        method="RK45",
        t_eval=times,
        rtol=rtol,
        atol=atol,
    )
    if not solution.success:
        raise PlantError(f"solve_ivp failed: {solution.message}")
    z = solution.y.T
    return Trajectory("SIL-RK45", times, z, -(z[:-1] @ k_matrix.T))


def shil(
    gain: ArrayLike,
    *,
    z0: ArrayLike = THESIS_Z0,
    dt: float = DEFAULT_DT,
    n_ticks: int,
    integrator: str = "euler",
    plant_params: dict[str, float] | None = None,
) -> Trajectory:
    """Simulated HIL: ControlModel(StateFeedback) and SimulatedVehicle(spring-mass-damper).

    Each tick ``k`` (the agent's order): ``y_k = vehicle.sense(k, t_k)``;
    ``u_{k+1} = model.step(vehicle.u, y_k)``; ``vehicle.apply(u_{k+1})`` (the plant advances
    one period ``dt``); ``vehicle.exchange()`` (no board: nothing to do).
    """
    vehicle = SimulatedVehicle(
        name="smd",
        params={
            "plant": "spring_mass_damper",
            "plant_params": dict(plant_params or {}),
            "integrator": integrator,
        },
        initial_state=[float(v) for v in np.asarray(z0, dtype=np.float64)],
        dt=dt,
    )
    model = ControlModel(
        StateFeedback(),
        dt=dt,
        n_inputs=vehicle.n_inputs,
        n_outputs=vehicle.n_outputs,
        params={"K": np.asarray(gain, dtype=np.float64).tolist()},
    )
    z = np.empty((n_ticks + 1, vehicle.n_outputs))
    u = np.empty((n_ticks, vehicle.n_inputs))
    for k in range(n_ticks):
        t = k * dt
        z[k] = vehicle.sense(k, t)
        u[k] = model.step(vehicle.u, z[k], t=t)
        vehicle.apply(u[k])
        vehicle.exchange()
    z[n_ticks] = vehicle.sense(n_ticks, n_ticks * dt)
    return Trajectory("SHIL", dt * np.arange(n_ticks + 1), z, u)


def max_abs_difference(a: Trajectory, b: Trajectory) -> float:
    """Largest ``|a.z - b.z|`` over all ticks and states [m or m/s]."""
    if a.z.shape != b.z.shape:
        raise PlantError(f"trajectories differ in shape: {a.z.shape} vs {b.z.shape}")
    return float(np.max(np.abs(a.z - b.z)))

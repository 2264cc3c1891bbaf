"""Simulated motion capture: the pose of a simulated body, with seeded Gaussian noise.

Stands in for the thesis' Vicon system. :class:`SimulatedMocap` wraps any object with a
``pose()`` method (a :class:`~hilswarm.agents.sim.plant.PinPlant`, a plant wrapper, ...) and
implements the :class:`~hilswarm.agents.sim.plant.PoseSource` protocol itself:
``pose() -> [x, y, z (m, world frame), roll, pitch, yaw (rad)]``.

Noise is drawn from a ``numpy`` generator seeded at construction, so two instances with the
same seed and the same sequence of calls give the same samples. Optional rate limiting models a
camera system slower than the control loop: with ``rate_hz`` set and the caller's time ``t``
[s] passed to :meth:`SimulatedMocap.pose`, a new sample is taken only once ``1 / rate_hz`` has
passed since the last one; in between the last sample is repeated. Time is always passed in.
"""

from __future__ import annotations

import math

import numpy as np
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.plant import PoseSource

POSE_SIZE = 6
_FLOAT64 = np.dtype(np.float64)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles [rad] wrapped into ``[-pi, pi)``."""
    return (np.asarray(angle) + math.pi) % (2 * math.pi) - math.pi


def _non_negative(name: str, value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise PlantError(f"SimulatedMocap: {name} must be a finite number, got {value!r}")
    if value < 0:
        raise PlantError(f"SimulatedMocap: {name} must be >= 0, got {value!r}")
    return float(value)


class SimulatedMocap:
    """A noisy, optionally rate-limited pose measurement of ``source``.

    Args:
        source: anything with ``pose() -> [x, y, z, roll, pitch, yaw]`` (m, world; rad).
        noise_std_m: standard deviation of the position noise [m] (each axis).
        noise_std_rad: standard deviation of the attitude noise [rad] (each angle); noisy
            angles are wrapped into ``[-pi, pi)``.
        seed: seed of the noise generator (same seed, same samples).
        rate_hz: camera rate [Hz]; ``None`` takes a new sample on every call.

    Raises:
        PlantError: ``source`` has no ``pose()``, or a bad noise level or rate.
    """

    def __init__(
        self,
        source: PoseSource,
        *,
        noise_std_m: float = 0.0,
        noise_std_rad: float = 0.0,
        seed: int | None = 0,
        rate_hz: float | None = None,
    ) -> None:
        if not callable(getattr(source, "pose", None)):
            raise PlantError(f"SimulatedMocap: source {type(source).__name__} has no pose() method")
        self.source = source
        self.noise_std_m = _non_negative("noise_std_m", noise_std_m)
        self.noise_std_rad = _non_negative("noise_std_rad", noise_std_rad)
        if rate_hz is not None and _non_negative("rate_hz", rate_hz) == 0:
            raise PlantError("SimulatedMocap: rate_hz must be > 0 (or None for every call)")
        self.rate_hz = None if rate_hz is None else float(rate_hz)
        self._rng = np.random.default_rng(seed)
        self._last: np.ndarray | None = None
        self._last_t: float | None = None
        #: Frame of the poses: the source's (``pose_frame``; the blimp plant's is ``"ned"``).
        self.frame: str = getattr(source, "pose_frame", "world")

    def _true_pose(self) -> np.ndarray:
        pose = self.source.pose()
        if type(pose) is np.ndarray and pose.dtype == _FLOAT64 and pose.shape == (POSE_SIZE,):
            return pose
        pose = np.asarray(pose, dtype=np.float64).reshape(-1)
        if pose.shape != (POSE_SIZE,):
            raise PlantError(
                f"SimulatedMocap: {type(self.source).__name__}.pose() must return "
                f"{POSE_SIZE} numbers [x, y, z, roll, pitch, yaw], got shape {pose.shape}"
            )
        return pose

    def _sample(self) -> np.ndarray:
        pose = self._true_pose()
        if not (self.noise_std_m or self.noise_std_rad):
            return pose + 0.0  # a new array, exactly the values pose + zero noise has
        noise = np.concatenate(
            [
                self._rng.normal(0.0, self.noise_std_m, 3) if self.noise_std_m else np.zeros(3),
                self._rng.normal(0.0, self.noise_std_rad, 3) if self.noise_std_rad else np.zeros(3),
            ]
        )
        measured = pose + noise
        if self.noise_std_rad:
            measured[3:] = wrap_angle(measured[3:])
        return measured

    def pose(self, t: float | None = None) -> np.ndarray:
        """The measured pose ``[x, y, z (m, world), roll, pitch, yaw (rad)]``.

        Args:
            t: the caller's time [s]; used only with ``rate_hz`` to decide whether a new
                camera frame is due (a call without ``t`` always takes a new sample).
        """
        if self.rate_hz is None:  # a new frame on every call: return it, keep a copy
            last = self._sample()
            self._last, self._last_t = last.copy(), t
            return last
        last = self._last
        if last is None or self._frame_due(t):
            last = self._sample()
            self._last, self._last_t = last, t
        return last.copy()

    def _frame_due(self, t: float | None) -> bool:
        if self.rate_hz is None or t is None or self._last_t is None:
            return True
        return t - self._last_t >= 1.0 / self.rate_hz - 1e-12

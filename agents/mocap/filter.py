"""Per-body filtering of mocap poses: backward-difference velocity and a constant-velocity
Kalman filter for position and heading.

The thesis notes that Vicon heading is noisy and suggests a Kalman filter; this is it. Each of
``x, y, z`` [m] and the **unwrapped** heading ``yaw`` [rad] has its own constant-velocity model
(state ``[p, v]``, white-noise acceleration of spectral density ``q``)::

    F = [[1, dt], [0, 1]]    Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]    H = [1, 0]    R = r

The four axes are independent, so the filter runs on them as arrays at once (no matrices
inverted: the gain of a scalar measurement is a division). The **innovation** ``z - H x^-`` of
every update is kept (recorded per tick) — it shows whether ``q`` and ``r`` fit. Roll and
pitch pass through unfiltered. ``dt`` comes from the frames' own timestamps [s].

An occluded frame (no measurement) does not update anything: the filter holds its last
estimate (no extrapolation: a held pose must not drift while nobody sees the body). After
``reset_after_s`` without a measurement the next one restarts the filter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from hilswarm.agents.mocap.frames import wrap

#: Filtered axes: x, y, z [m] and yaw [rad, unwrapped].
AXES = 4


@dataclass(frozen=True)
class FilterTuning:
    """Noise levels of :class:`PoseFilter`.

    Attributes:
        position_std_m: measurement noise of each position axis [m] (``r = std^2``).
        yaw_std_rad: measurement noise of the heading [rad].
        accel_psd: white-noise acceleration density of x, y, z [m^2 s^-3].
        yaw_accel_psd: white-noise angular acceleration density of yaw [rad^2 s^-3].
        reset_after_s: a gap without measurements longer than this restarts the filter [s].
    """

    position_std_m: float = 0.002
    yaw_std_rad: float = 0.02
    accel_psd: float = 1.0
    yaw_accel_psd: float = 10.0
    reset_after_s: float = 0.5


class PoseFilter:
    """One body's filter (see the module docstring).

    Args:
        tuning: noise levels.
    """

    def __init__(self, tuning: FilterTuning | None = None) -> None:
        self.tuning = tuning or FilterTuning()
        t = self.tuning
        self._r = np.array([t.position_std_m**2] * 3 + [t.yaw_std_rad**2])
        self._q = np.array([t.accel_psd] * 3 + [t.yaw_accel_psd])
        self._p = np.zeros(AXES)  # position estimates (yaw unwrapped)
        self._v = np.zeros(AXES)  # velocity estimates
        self._pp = np.zeros(AXES)  # covariance entries P00, P01, P11 per axis
        self._pv = np.zeros(AXES)
        self._vv = np.zeros(AXES)
        self._t: float | None = None  # time of the last measurement [s]
        self._last_raw: np.ndarray | None = None  # last measurement (yaw unwrapped)
        self._attitude = np.zeros(2)  # roll, pitch of the last measurement [rad]
        #: Innovation of the last update ``[x, y, z (m), yaw (rad)]`` (NaN before/without one).
        self.innovation = np.full(AXES, np.nan)
        #: Backward-difference velocity of the raw measurements ``[vx, vy, vz (m/s), yaw rate
        #: (rad/s)]`` (NaN until two measurements).
        self.velocity = np.full(AXES, np.nan)

    @property
    def started(self) -> bool:
        """True once a measurement was taken (and not reset since)."""
        return self._t is not None

    def update(self, t: float, pose: np.ndarray | None) -> np.ndarray:
        """Take the frame of time ``t`` [s]: a measured pose, or ``None`` when occluded.

        Returns the estimate ``[x, y, z, roll, pitch, yaw]`` (world frame; yaw wrapped), NaN
        while the filter has never seen the body.
        """
        if pose is None:
            self.innovation = np.full(AXES, np.nan)
            return self.estimate()
        pose = np.asarray(pose, dtype=np.float64)
        measured = np.array([pose[0], pose[1], pose[2], pose[5]])
        if self._t is not None and t - self._t > self.tuning.reset_after_s:
            self._t = None  # too long unseen: start again from this measurement
        if self._t is None:
            self._start(t, measured, pose)
            return self.estimate()
        dt = t - self._t
        if not dt > 0.0:  # a repeated or reordered frame: nothing new to learn
            return self.estimate()
        last = measured if self._last_raw is None else self._last_raw  # set with self._t
        measured[3] = last[3] + wrap(measured[3] - last[3])  # unwrap the heading
        self.velocity = (measured - last) / dt
        self._predict(dt)
        innovation = measured - self._p
        s = self._pp + self._r
        k0, k1 = self._pp / s, self._pv / s
        self._p = self._p + k0 * innovation
        self._v = self._v + k1 * innovation
        pp, pv, vv = self._pp, self._pv, self._vv
        self._pp, self._pv, self._vv = (1 - k0) * pp, (1 - k0) * pv, vv - k1 * pv
        self.innovation = innovation
        self._t, self._last_raw = t, measured
        self._attitude = pose[3:5].copy()
        return self.estimate()

    def _start(self, t: float, measured: np.ndarray, pose: np.ndarray) -> None:
        self._p, self._v = measured.copy(), np.zeros(AXES)
        self._pp, self._pv, self._vv = self._r.copy(), np.zeros(AXES), np.full(AXES, 1.0)
        self._t, self._last_raw = t, measured
        self._attitude = pose[3:5].copy()
        self.innovation = np.zeros(AXES)
        self.velocity = np.full(AXES, np.nan)

    def _predict(self, dt: float) -> None:
        q = self._q
        pp, pv, vv = self._pp, self._pv, self._vv
        self._p = self._p + dt * self._v
        self._pp = pp + 2 * dt * pv + dt * dt * vv + q * dt**3 / 3
        self._pv = pv + dt * vv + q * dt**2 / 2
        self._vv = vv + q * dt

    def estimate(self) -> np.ndarray:
        """``[x, y, z, roll, pitch, yaw]`` [m, rad; world frame, yaw wrapped]; NaN if unstarted."""
        if self._t is None:
            return np.full(6, np.nan)
        p = self._p
        return np.array([p[0], p[1], p[2], self._attitude[0], self._attitude[1], wrap(p[3])])

    @property
    def rate(self) -> np.ndarray:
        """Filtered velocity ``[vx, vy, vz (m/s), yaw rate (rad/s)]``."""
        return self._v.copy() if self._t is not None else np.full(AXES, math.nan)

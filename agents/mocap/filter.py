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


class FilterBank:
    """The filters of ``n`` bodies, run as arrays at once (see the module docstring).

    One frame updates every body with one set of array operations (no Python loop per body):
    at 16 bodies and 240 Hz that is the difference between keeping up and not.

    Args:
        n: number of bodies.
        tuning: noise levels (the same for every body).
    """

    def __init__(self, n: int, tuning: FilterTuning | None = None) -> None:
        self.n = int(n)
        self.tuning = tuning or FilterTuning()
        t = self.tuning
        self._r = np.array([t.position_std_m**2] * 3 + [t.yaw_std_rad**2])
        self._q = np.array([t.accel_psd] * 3 + [t.yaw_accel_psd])
        shape = (self.n, AXES)
        self._p = np.zeros(shape)  # position estimates (yaw unwrapped)
        self._v = np.zeros(shape)  # velocity estimates
        self._pp = np.zeros(shape)  # covariance entries P00, P01, P11 per body and axis
        self._pv = np.zeros(shape)
        self._vv = np.zeros(shape)
        self._t = np.full(self.n, np.nan)  # time of each body's last measurement [s]
        self._last_raw = np.zeros(shape)  # last measurement (yaw unwrapped)
        self._attitude = np.zeros((self.n, 2))  # roll, pitch of the last measurement [rad]
        #: Innovation of this frame's update ``[x, y, z (m), yaw (rad)]`` per body (NaN: none).
        self.innovation = np.full(shape, np.nan)
        #: Backward-difference velocity of the raw measurements ``[vx, vy, vz (m/s), yaw rate
        #: (rad/s)]`` per body (NaN until two measurements).
        self.velocity = np.full(shape, np.nan)

    def update(self, t: float, poses: np.ndarray) -> np.ndarray:
        """Take the frame of time ``t`` [s]: ``poses`` ``(n, 6)``, a NaN row for a body unseen.

        Returns the estimates ``(n, 6)`` ``[x, y, z, roll, pitch, yaw]`` (world frame; yaw
        wrapped), NaN rows for bodies never seen.
        """
        poses = np.asarray(poses, dtype=np.float64).reshape(self.n, 6)
        seen = np.isfinite(poses).all(axis=1)
        measured = poses[:, (0, 1, 2, 5)]
        age = t - self._t  # NaN for bodies not started
        with np.errstate(invalid="ignore"):
            running = seen & (age <= self.tuning.reset_after_s)  # too long unseen: restart
            start = seen & ~running
            step = running & (age > 0.0)  # a repeated or reordered frame: nothing new
        self.innovation[:] = np.nan
        if start.any():
            self._start(start, t, measured, poses)
        if step.all():
            self._step(slice(None), t, measured, poses, age)
        elif step.any():
            self._step(step, t, measured, poses, age)
        return self.estimate()

    def _start(self, rows: np.ndarray, t: float, measured: np.ndarray, poses: np.ndarray) -> None:
        self._p[rows] = measured[rows]
        self._v[rows] = 0.0
        self._pp[rows], self._pv[rows], self._vv[rows] = self._r, 0.0, 1.0
        self._t[rows] = t
        self._last_raw[rows] = measured[rows]
        self._attitude[rows] = poses[rows, 3:5]
        self.innovation[rows] = 0.0
        self.velocity[rows] = np.nan

    def _step(
        self,
        rows: np.ndarray | slice,
        t: float,
        measured: np.ndarray,
        poses: np.ndarray,
        age: np.ndarray,
    ) -> None:
        z = measured[rows]
        last = self._last_raw[rows]
        z[:, 3] = last[:, 3] + wrap_array(z[:, 3] - last[:, 3])  # unwrap the heading
        dt = age[rows][:, None]
        self.velocity[rows] = (z - last) / dt
        q = self._q
        pp, pv, vv = self._pp[rows], self._pv[rows], self._vv[rows]
        p = self._p[rows] + dt * self._v[rows]  # predict
        pp = pp + 2 * dt * pv + dt * dt * vv + q * dt**3 / 3
        pv = pv + dt * vv + q * dt**2 / 2
        vv = vv + q * dt
        innovation = z - p  # update
        s = pp + self._r
        k0, k1 = pp / s, pv / s
        self._p[rows] = p + k0 * innovation
        self._v[rows] = self._v[rows] + k1 * innovation
        self._pp[rows], self._pv[rows], self._vv[rows] = (1 - k0) * pp, (1 - k0) * pv, vv - k1 * pv
        self.innovation[rows] = innovation
        self._t[rows] = t
        self._last_raw[rows] = z
        self._attitude[rows] = poses[rows, 3:5]

    def estimate(self) -> np.ndarray:
        """Estimates ``(n, 6)`` [m, rad; world frame, yaw wrapped]; NaN rows if never seen."""
        p = self._p
        out = np.column_stack([p[:, :3], self._attitude, wrap_array(p[:, 3])])
        out[np.isnan(self._t)] = np.nan
        return out

    @property
    def rate(self) -> np.ndarray:
        """Filtered velocities ``(n, 4)`` ``[vx, vy, vz (m/s), yaw rate (rad/s)]``."""
        out = self._v.copy()
        out[np.isnan(self._t)] = np.nan
        return out


def wrap_array(angles: np.ndarray) -> np.ndarray:
    """Angles [rad] wrapped into ``[-pi, pi)`` (element-wise)."""
    return (angles + math.pi) % (2.0 * math.pi) - math.pi


class PoseFilter:
    """One body's filter: a :class:`FilterBank` of one, with per-body shapes.

    Args:
        tuning: noise levels.
    """

    def __init__(self, tuning: FilterTuning | None = None) -> None:
        self._bank = FilterBank(1, tuning)
        self.tuning = self._bank.tuning

    @property
    def started(self) -> bool:
        """True once a measurement was taken (and not reset since)."""
        return bool(np.isfinite(self._bank._t[0]))

    def update(self, t: float, pose: np.ndarray | None) -> np.ndarray:
        """Take the frame of time ``t`` [s]: a measured pose, or ``None`` when occluded.

        Returns the estimate ``[x, y, z, roll, pitch, yaw]`` (world frame; yaw wrapped), NaN
        while the filter has never seen the body.
        """
        row = np.full((1, 6), np.nan) if pose is None else np.asarray(pose, dtype=np.float64)
        return self._bank.update(t, row.reshape(1, 6))[0]

    def estimate(self) -> np.ndarray:
        """``[x, y, z, roll, pitch, yaw]`` [m, rad; world frame, yaw wrapped]; NaN if unseen."""
        return self._bank.estimate()[0]

    @property
    def innovation(self) -> np.ndarray:
        """Innovation of the last update ``[x, y, z (m), yaw (rad)]`` (NaN without one)."""
        return self._bank.innovation[0].copy()

    @property
    def velocity(self) -> np.ndarray:
        """Backward-difference velocity ``[vx, vy, vz (m/s), yaw rate (rad/s)]``."""
        return self._bank.velocity[0].copy()

    @property
    def rate(self) -> np.ndarray:
        """Filtered velocity ``[vx, vy, vz (m/s), yaw rate (rad/s)]``."""
        return self._bank.rate[0]

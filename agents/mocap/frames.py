"""The project's world frame and each mocap system's axis convention mapped into it.

**World frame** (the whole project): right-handed, **z up**, x and y horizontal; metres and
radians. A pose is ``[x, y, z, roll, pitch, yaw]``: position [m] and the body's Z-Y-X Euler
angles [rad] (``R = Rz(yaw) Ry(pitch) Rx(roll)``, body -> world); ``yaw`` is the heading, from
world x towards world y, wrapped into ``[-pi, pi)``.

**NED frame** (the Blimpduino's, :mod:`hilswarm.agents.sim.blimp`): derived from the world
frame by a rotation of pi about world x: north = world x, east = -world y, down = -world z.
:func:`world_to_ned` maps a world pose into it (roll stays, pitch and yaw change sign); the map
is its own inverse.

**Systems** (:data:`CONVENTIONS`): what each one streams, before mapping:

=========  ========  =======  =====================================================
system     up axis   units    notes
=========  ========  =======  =====================================================
qualisys   z         mm       QTM's default global frame; qtm-rt gives raw mm
vicon      z         m        libmotioncapture converts Vicon's mm to m
optitrack  y         m        Motive's default streaming up axis is Y
vrpn       z         m        VRPN trackers report metres; servers usually z-up
sim        z         mm       the built-in simulator speaks the Qualisys protocol
=========  ========  =======  =====================================================

A y-up system (OptiTrack's default) is mapped by a rotation of +pi/2 about x:
``world = (x, -z, y)``. ``up_axis`` in ``[mocap]`` overrides a system's default (e.g. a
Motive set to stream z-up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from hilswarm.agents.errors import HilswarmError

POSE_SIZE = 6


class FrameError(HilswarmError, ValueError):
    """An unknown system or axis convention."""


@dataclass(frozen=True)
class Convention:
    """How one system streams positions and rotations.

    Attributes:
        up_axis: ``"z"`` or ``"y"``: the system's vertical axis (both right-handed).
        metres_per_unit: position unit of the stream [m per unit] (1e-3 for mm).
    """

    up_axis: str
    metres_per_unit: float

    def __post_init__(self) -> None:
        if self.up_axis not in _TO_WORLD:
            raise FrameError(f"up_axis must be one of {sorted(_TO_WORLD)}, got {self.up_axis!r}")

    @property
    def rotation(self) -> np.ndarray:
        """``C`` (3 x 3): system-frame vector -> world-frame vector."""
        return _TO_WORLD[self.up_axis]

    def to_world(self, position: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position [system units] and attitude ``R_sys`` (body -> system) to the world frame.

        Returns ``(p_world [m], R_world)`` with ``p_world = C p s`` and ``R_world = C R_sys
        C^T``: the body frame a system defines (a body at rest has the identity attitude, its
        "up" along the system's up axis) is turned the same way, so a body at rest is level
        in the world frame too (roll = pitch = 0) whatever the system's up axis.
        """
        position = np.asarray(position, dtype=np.float64) * self.metres_per_unit
        if self.up_axis == "z":  # already the world's axes: no product (per frame and body)
            return position, np.asarray(rotation, dtype=np.float64)
        c = self.rotation
        return c @ position, c @ np.asarray(rotation, dtype=np.float64) @ c.T

    def poses(self, positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """World poses ``(n, 6)`` of ``n`` bodies: positions ``(n, 3)`` [system units] and
        attitudes ``(n, 3, 3)`` (body -> system), as :meth:`to_world` and :func:`pose_from` do
        for one (array operations, no loop per body; NaN rows stay NaN)."""
        p = np.asarray(positions, dtype=np.float64) * self.metres_per_unit
        r = np.asarray(rotations, dtype=np.float64)
        if self.up_axis != "z":
            c = self.rotation
            p = p @ c.T
            r = c @ r @ c.T
        pitch = np.arcsin(np.clip(-r[:, 2, 0], -1.0, 1.0))
        roll = np.arctan2(r[:, 2, 1], r[:, 2, 2])
        yaw = (np.arctan2(r[:, 1, 0], r[:, 0, 0]) + math.pi) % (2.0 * math.pi) - math.pi
        return np.column_stack([p, roll, pitch, yaw])


_TO_WORLD: dict[str, np.ndarray] = {
    "z": np.eye(3),
    # y up: rotation of +pi/2 about x takes the system's y (up) to world z, its z to -world y.
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
}
for _matrix in _TO_WORLD.values():
    _matrix.setflags(write=False)

#: Each system's default convention (see the module docstring).
CONVENTIONS: dict[str, Convention] = {
    "qualisys": Convention("z", 1e-3),
    "vicon": Convention("z", 1.0),
    "optitrack": Convention("y", 1.0),
    "vrpn": Convention("z", 1.0),
    "sim": Convention("z", 1e-3),
}
SYSTEMS: tuple[str, ...] = tuple(CONVENTIONS)


def convention(system: str, up_axis: str | None = None) -> Convention:
    """The convention of ``system``, with its up axis overridden when ``up_axis`` is given."""
    try:
        base = CONVENTIONS[system]
    except KeyError:
        raise FrameError(
            f"unknown mocap system {system!r}; expected one of {', '.join(SYSTEMS)}"
        ) from None
    return base if up_axis is None else Convention(up_axis, base.metres_per_unit)


def wrap(angle: float) -> float:
    """An angle [rad] wrapped into ``[-pi, pi)``."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def euler_zyx(rotation: np.ndarray) -> tuple[float, float, float]:
    """``(roll, pitch, yaw)`` [rad] of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (yaw wrapped)."""
    r = np.asarray(rotation, dtype=np.float64)
    pitch = math.asin(max(-1.0, min(1.0, -float(r[2, 0]))))
    roll = math.atan2(float(r[2, 1]), float(r[2, 2]))
    yaw = math.atan2(float(r[1, 0]), float(r[0, 0]))
    return roll, pitch, wrap(yaw)


def rotation_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` (body -> world) for angles [rad]."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def rotations_zyx(angles: np.ndarray) -> np.ndarray:
    """:func:`rotation_zyx` of every row of ``angles`` ``(n, 3)`` ``[roll, pitch, yaw]``
    [rad]: the matrices ``(n, 3, 3)`` (body -> world), as array operations."""
    angles = np.asarray(angles, dtype=np.float64).reshape(-1, 3)
    cos, sin = np.cos(angles), np.sin(angles)
    cr, cp, cy = cos[:, 0], cos[:, 1], cos[:, 2]
    sr, sp, sy = sin[:, 0], sin[:, 1], sin[:, 2]
    out = np.empty((angles.shape[0], 3, 3))
    out[:, 0, 0] = cy * cp
    out[:, 0, 1] = cy * sp * sr - sy * cr
    out[:, 0, 2] = cy * sp * cr + sy * sr
    out[:, 1, 0] = sy * cp
    out[:, 1, 1] = sy * sp * sr + cy * cr
    out[:, 1, 2] = sy * sp * cr - cy * sr
    out[:, 2, 0] = -sp
    out[:, 2, 1] = cp * sr
    out[:, 2, 2] = cp * cr
    return out


def quaternion_to_rotation(w: float, x: float, y: float, z: float) -> np.ndarray:
    """Rotation matrix of the unit quaternion ``w + xi + yj + zk`` (normalised here)."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n or not math.isfinite(n):
        return np.full((3, 3), np.nan)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def yaw_quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of the quaternion of ``Rz(yaw) Ry(pitch) Rx(roll)`` (angles [rad])."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def pose_from(position_m: np.ndarray, rotation_world: np.ndarray) -> np.ndarray:
    """``[x, y, z, roll, pitch, yaw]`` (world frame) of a position [m] and attitude matrix."""
    roll, pitch, yaw = euler_zyx(rotation_world)
    return np.array([*np.asarray(position_m, dtype=np.float64).tolist(), roll, pitch, yaw])


def world_to_ned(pose: np.ndarray) -> np.ndarray:
    """A world pose ``[x, y, z, roll, pitch, yaw]`` in the NED frame (its own inverse).

    NED = world rotated by pi about x: ``(x, -y, -z)``; the body frame turns the same way
    (x forward, y right, z down), so ``R_ned = Cx R Cx``: roll stays, pitch and yaw change
    sign (yaw wrapped into ``[-pi, pi)``).
    """
    x, y, z, roll, pitch, yaw = np.asarray(pose, dtype=np.float64).tolist()
    return np.array([x, -y, -z, roll, -pitch, wrap(-yaw)])

"""Frame mapping: a known pose in each system's convention lands at the right world pose."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.mocap.frames import (
    CONVENTIONS,
    FrameError,
    convention,
    euler_zyx,
    pose_from,
    quaternion_to_rotation,
    rotation_zyx,
    rotations_zyx,
    world_to_ned,
    yaw_quaternion,
)

# A body 1 m along world x, 2 m along world y, 0.5 m up, heading 30 deg (towards world y).
WORLD = np.array([1.0, 2.0, 0.5, 0.0, 0.0, math.radians(30.0)])
RX90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # y-up -> z-up


def system_view(system: str) -> tuple[np.ndarray, np.ndarray]:
    """How ``system`` streams WORLD, written out by hand from its convention."""
    yaw = WORLD[5]
    if system in ("qualisys", "sim"):  # z up, millimetres
        return np.array([1000.0, 2000.0, 500.0]), rotation_zyx(0.0, 0.0, yaw)
    if system in ("vicon", "vrpn"):  # z up, metres
        return np.array([1.0, 2.0, 0.5]), rotation_zyx(0.0, 0.0, yaw)
    # OptiTrack, y up: its x = world x, its y = world z (up), its z = -world y; a body at rest
    # has the identity attitude (its own y up), so a heading is R_sys = C^T R_world C.
    r_world = rotation_zyx(0.0, 0.0, yaw)
    return np.array([1.0, 0.5, -2.0]), RX90.T @ r_world @ RX90


@pytest.mark.parametrize("system", sorted(CONVENTIONS))
def test_known_pose_of_each_system_lands_at_the_world_pose(system: str) -> None:
    position, rotation = system_view(system)
    p, r = convention(system).to_world(position, rotation)
    np.testing.assert_allclose(pose_from(p, r), WORLD, atol=1e-12)


def test_a_body_at_rest_in_a_y_up_system_is_level_in_the_world() -> None:
    _, r = convention("optitrack").to_world(np.zeros(3), np.eye(3))
    np.testing.assert_allclose(euler_zyx(r), (0.0, 0.0, 0.0), atol=1e-15)


def test_optitrack_set_to_z_up_is_mapped_as_such() -> None:
    position, rotation = np.array([1.0, 2.0, 0.5]), rotation_zyx(0.0, 0.0, WORLD[5])
    p, r = convention("optitrack", up_axis="z").to_world(position, rotation)
    np.testing.assert_allclose(pose_from(p, r), WORLD, atol=1e-12)


def test_every_convention_is_a_proper_rotation() -> None:
    for system, conv in CONVENTIONS.items():
        assert np.linalg.det(conv.rotation) == pytest.approx(1.0), system
        np.testing.assert_allclose(conv.rotation @ conv.rotation.T, np.eye(3), atol=1e-15)


def test_unknown_system_and_axis_are_refused() -> None:
    with pytest.raises(FrameError, match="unknown mocap system"):
        convention("phasespace")
    with pytest.raises(FrameError, match="up_axis"):
        convention("vicon", up_axis="x")


def test_rotations_of_many_bodies_at_once_are_each_bodys_rotation() -> None:
    angles = np.random.default_rng(4).uniform(-math.pi, math.pi, size=(50, 3))
    many = rotations_zyx(angles)
    assert many.shape == (50, 3, 3)
    for row, matrix in zip(angles, many, strict=True):
        np.testing.assert_allclose(matrix, rotation_zyx(*row), atol=1e-15)
    assert rotations_zyx(np.empty((0, 3))).shape == (0, 3, 3)


def test_euler_and_quaternion_round_trip() -> None:
    rng = np.random.default_rng(3)
    for _ in range(100):
        roll, pitch, yaw = rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), rng.uniform(-3.1, 3.1)
        r = rotation_zyx(roll, pitch, yaw)
        np.testing.assert_allclose(euler_zyx(r), (roll, pitch, yaw), atol=1e-9)
        qx, qy, qz, qw = yaw_quaternion(roll, pitch, yaw)
        np.testing.assert_allclose(quaternion_to_rotation(qw, qx, qy, qz), r, atol=1e-12)


def test_ned_is_the_world_turned_about_x_and_its_own_inverse() -> None:
    ned = world_to_ned(WORLD)
    # North = world x, east = -world y, down = -world z; heading from north towards east.
    np.testing.assert_allclose(ned, [1.0, -2.0, -0.5, 0.0, 0.0, -WORLD[5]], atol=1e-15)
    np.testing.assert_allclose(world_to_ned(ned), WORLD, atol=1e-15)
    # The same as the rotation: R_ned = Cx R Cx for a tilted body too.
    cx = np.diag([1.0, -1.0, -1.0])
    pose = np.array([0.1, 0.2, 0.3, 0.2, -0.3, 2.0])
    expected = euler_zyx(cx @ rotation_zyx(*pose[3:]) @ cx)
    np.testing.assert_allclose(world_to_ned(pose)[3:], expected, atol=1e-12)

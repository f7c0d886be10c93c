"""Pose conventions (evgs.data.poses) against independent references: OpenCV's Rodrigues, scipy's
Euler angles, and hand-derived matrices."""

import cv2
import numpy as np
import pytest
from evgs.data.poses import (
    check_rotations,
    euler_to_rotmat,
    rodrigues_to_rotmat,
    rows_to_pose,
    to_c2w,
    to_opencv_axes,
)
from evgs.geometry import invert_pose, make_pose, quat_to_rotmat
from scipy.spatial.transform import Rotation


def test_rodrigues_matches_opencv():
    rng = np.random.default_rng(0)
    rvecs = np.concatenate([rng.normal(size=(20, 3)), [[0, 0, 0], [1e-10, 0, 0], [0, np.pi, 0]]])
    R = rodrigues_to_rotmat(rvecs)
    for r, m in zip(rvecs, R, strict=True):
        np.testing.assert_allclose(m, cv2.Rodrigues(r)[0], atol=1e-12)
    # 90° about x maps y to z.
    np.testing.assert_allclose(
        rodrigues_to_rotmat(np.array([np.pi / 2, 0, 0])) @ [0, 1, 0], [0, 0, 1], atol=1e-12
    )


@pytest.mark.parametrize("order", ["xyz", "zyx", "xzy", "XYZ", "ZYX", "ZXZ"])
def test_euler_matches_scipy(order):
    rng = np.random.default_rng(1)
    angles = rng.uniform(-np.pi, np.pi, size=(30, 3))
    np.testing.assert_allclose(
        euler_to_rotmat(angles, order), Rotation.from_euler(order, angles).as_matrix(), atol=1e-12
    )


def test_euler_aerospace_convention():
    roll, pitch, yaw = 0.1, -0.4, 1.2
    c, s = np.cos, np.sin
    Rx = np.array([[1, 0, 0], [0, c(roll), -s(roll)], [0, s(roll), c(roll)]])
    Ry = np.array([[c(pitch), 0, s(pitch)], [0, 1, 0], [-s(pitch), 0, c(pitch)]])
    Rz = np.array([[c(yaw), -s(yaw), 0], [s(yaw), c(yaw), 0], [0, 0, 1]])
    np.testing.assert_allclose(euler_to_rotmat(np.array([roll, pitch, yaw]), "xyz"), Rz @ Ry @ Rx, atol=1e-12)
    np.testing.assert_allclose(euler_to_rotmat(np.array([yaw, pitch, roll]), "ZYX"), Rz @ Ry @ Rx, atol=1e-12)


@pytest.mark.parametrize("order", ["xy", "xYz", "abc"])
def test_euler_bad_order(order):
    with pytest.raises(ValueError, match="Euler order"):
        euler_to_rotmat(np.zeros(3), order)


def test_rows_to_pose_12_and_16():
    rng = np.random.default_rng(2)
    T = make_pose(quat_to_rotmat(rng.normal(size=(5, 4))), rng.normal(size=(5, 3)))
    rows12 = np.concatenate([T[:, :3, :3].reshape(5, 9), T[:, :3, 3]], axis=1)
    np.testing.assert_allclose(rows_to_pose(np.round(rows12, 6), "f"), T, atol=1e-5)
    np.testing.assert_allclose(rows_to_pose(T.reshape(5, 16), "f"), T, atol=1e-12)


def test_rows_to_pose_rejects_non_rotation_naming_line():
    rows = np.tile(np.r_[np.eye(3).ravel(), 1, 2, 3], (3, 1))
    rows[1, 0] = 2.0
    with pytest.raises(ValueError, match=r"poses.txt: line 6: not a rotation"):
        rows_to_pose(rows, "poses.txt", first_line=5)
    reflect = np.diag([1.0, 1.0, -1.0])
    with pytest.raises(ValueError, match="not a rotation"):
        check_rotations(reflect, "x")
    m = np.eye(4).ravel()
    m[12] = 1.0
    with pytest.raises(ValueError, match="last matrix row"):
        rows_to_pose(m[None], "traj.txt")


def test_directions_and_axes():
    rng = np.random.default_rng(3)
    T = make_pose(quat_to_rotmat(rng.normal(size=(4, 4))), rng.normal(size=(4, 3)))
    np.testing.assert_allclose(to_c2w(T, "c2w"), T)
    np.testing.assert_allclose(to_c2w(invert_pose(T), "w2c"), T, atol=1e-12)
    with pytest.raises(ValueError, match="pose direction"):
        to_c2w(T, "up")
    # An OpenGL camera looking down its −z sees a point in front where an OpenCV camera looks along +z.
    gl = to_opencv_axes(T, "opengl")
    point_gl_cam = np.array([0.1, 0.2, -3.0])  # in front of the OpenGL camera, up and right
    world = (T[0] @ np.r_[point_gl_cam, 1])[:3]
    cv_cam = (invert_pose(gl[0]) @ np.r_[world, 1])[:3]
    np.testing.assert_allclose(cv_cam, [0.1, -0.2, 3.0], atol=1e-12)

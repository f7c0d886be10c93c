"""Every pose convention the data sets use, converted explicitly to evgs's own in one tested place.

evgs's convention (see ``evgs.geometry``): 4×4 camera-to-world ``T_wc``, OpenCV camera axes (x right,
y down, z forward). Data sets differ in

- direction: camera-to-world (``"c2w"``, the camera's pose in the world) or world-to-camera (``"w2c"``,
  the world/target's pose in the camera, as pose-estimation data sets usually give);
- rotation parameterisation: Rodrigues axis-angle vectors, Euler angles in some axis order, a row-major
  3×3 (``r1..r9``) or 4×4 matrix, quaternions (TUM order is handled by ``evgs.data.tum``);
- camera axes: OpenCV or OpenGL/Blender (x right, y up, z backward).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from evgs.geometry import invert_pose, make_pose

Direction = Literal["c2w", "w2c"]
Axes = Literal["opencv", "opengl"]

DIRECTIONS: tuple[str, ...] = ("c2w", "w2c")
AXES: tuple[str, ...] = ("opencv", "opengl")

# Largest tolerated deviation of a stored rotation matrix from orthonormality (text files round).
ORTHONORMAL_TOL = 1e-3


def _axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """(…,) angles → (…, 3, 3) right-handed rotations about the named axis (``x``, ``y`` or ``z``)."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(angle), np.zeros_like(angle)
    rows = {
        "x": [o, z, z, z, c, -s, z, s, c],
        "y": [c, z, s, z, o, z, -s, z, c],
        "z": [c, -s, z, s, c, z, z, z, o],
    }[axis]
    return np.stack(rows, axis=-1).reshape(angle.shape + (3, 3))


def euler_to_rotmat(angles: np.ndarray, order: str) -> np.ndarray:
    """(…, 3) Euler angles (rad) → (…, 3, 3) rotations.

    ``angles[..., i]`` is the rotation about axis ``order[i]``. Lower-case ``order`` (e.g. ``"xyz"``) means
    extrinsic rotations about the fixed axes, applied in that order: ``R = R_z · R_y · R_x``. Upper-case
    (e.g. ``"ZYX"``) means intrinsic rotations about the moving axes: ``R = R_Z · R_Y · R_X``. So extrinsic
    ``"xyz"`` with (roll, pitch, yaw) is the aerospace 3-2-1 body-to-world attitude ``Rz(ψ) Ry(θ) Rx(φ)``,
    the same matrix as intrinsic ``"ZYX"`` with (yaw, pitch, roll). (scipy's ``Rotation.from_euler`` uses
    the same letter-case rule.)
    """
    a = np.asarray(angles, np.float64)
    if a.shape[-1] != 3:
        raise ValueError(f"Euler angles need 3 values, got shape {a.shape}")
    if len(order) != 3 or not (order.islower() or order.isupper()) or set(order.lower()) - set("xyz"):
        raise ValueError(f"Euler order {order!r}: expected 3 letters of x/y/z, all lower or all upper case")
    mats = [_axis_rotation(ax, a[..., i]) for i, ax in enumerate(order.lower())]
    if order.islower():
        return mats[2] @ mats[1] @ mats[0]
    return mats[0] @ mats[1] @ mats[2]


def rodrigues_to_rotmat(rvec: np.ndarray) -> np.ndarray:
    """(…, 3) axis-angle vectors (axis · angle in rad, as OpenCV's ``Rodrigues``) → (…, 3, 3)."""
    r = np.asarray(rvec, np.float64)
    theta = np.linalg.norm(r, axis=-1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    # sin θ/θ and (1 − cos θ)/θ² with their Taylor limits near zero.
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    k = _skew(r)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = np.moveaxis(v, -1, 0)
    o = np.zeros_like(x)
    return np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(v.shape[:-1] + (3, 3))


def check_rotations(rot: np.ndarray, source: str, first_line: int | None = None) -> np.ndarray:
    """Project near-orthonormal (…, 3, 3) matrices (rounded text) onto SO(3); raise naming ``source``
    (and the line, counted from ``first_line``) of the first that is not a rotation (non-finite,
    det ≤ 0, or further than ``ORTHONORMAL_TOL``)."""
    m = np.asarray(rot, np.float64).reshape(-1, 3, 3)
    u, _, vt = np.linalg.svd(np.nan_to_num(m))
    proj = u @ vt
    err = np.abs(m @ np.swapaxes(m, 1, 2) - np.eye(3)).max(axis=(1, 2))
    bad = ~np.isfinite(m).all(axis=(1, 2)) | (np.linalg.det(m) <= 0) | ~(err <= ORTHONORMAL_TOL)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(
            f"{source}: {'' if first_line is None else f'line {first_line + i}: '}not a rotation matrix "
            f"(|R·Rᵀ − I| = {err[i]:.2g}, det = {np.linalg.det(m[i]):.3g})"
        )
    return proj.reshape(np.shape(rot))


def rows_to_pose(rows: np.ndarray, source: str, first_line: int = 1) -> np.ndarray:
    """(N, 12) ``r1..r9 tx ty tz`` (row-major rotation, then translation) or (N, 16) row-major 4×4
    matrices → (N, 4, 4), rotations checked and re-orthonormalised."""
    a = np.asarray(rows, np.float64)
    if a.ndim != 2 or a.shape[1] not in (12, 16):
        raise ValueError(f"{source}: expected 12 (r1..r9 tx ty tz) or 16 (4×4) values per pose")
    if a.shape[1] == 12:
        rot, t = a[:, :9].reshape(-1, 3, 3), a[:, 9:12]
    else:
        m = a.reshape(-1, 4, 4)
        bottom = np.abs(m[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
        if np.any(~(bottom <= 1e-6)):
            i = int(np.argmax(~(bottom <= 1e-6)))
            raise ValueError(f"{source}: line {first_line + i}: last matrix row must be 0 0 0 1")
        rot, t = m[:, :3, :3], m[:, :3, 3]
    return make_pose(check_rotations(rot, source, first_line), t)


def to_c2w(T: np.ndarray, direction: Direction) -> np.ndarray:
    """Poses given in ``direction`` → camera-to-world."""
    if direction == "c2w":
        return np.asarray(T, np.float64)
    if direction == "w2c":
        return invert_pose(np.asarray(T, np.float64))
    raise ValueError(f"pose direction {direction!r}: expected one of {', '.join(DIRECTIONS)}")


# OpenGL/Blender camera (x right, y up, z backward) → OpenCV: flip y and z of the camera frame.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def to_opencv_axes(T_wc: np.ndarray, axes: Axes) -> np.ndarray:
    """Camera-to-world poses of a camera with ``axes`` → the same poses with OpenCV camera axes."""
    if axes == "opencv":
        return np.asarray(T_wc, np.float64)
    if axes == "opengl":
        return np.asarray(T_wc, np.float64) @ _GL_TO_CV
    raise ValueError(f"camera axes {axes!r}: expected one of {', '.join(AXES)}")

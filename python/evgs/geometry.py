"""Rigid-body conventions in one place (numpy, float64).

Poses are 4×4 camera-to-world matrices ``T_wc`` unless a name says otherwise; camera axes are OpenCV
(x right, y down, z forward). Quaternions are in TUM order ``(qx, qy, qz, qw)``.
"""

from __future__ import annotations

import numpy as np


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(…, 4) quaternions ``(qx, qy, qz, qw)`` (normalised here) → (…, 3, 3) rotation matrices."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    r = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )  # fmt: skip
    return r.reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """(…, 3, 3) rotation matrices → (…, 4) unit quaternions ``(qx, qy, qz, qw)`` with ``qw ≥ 0``.

    Shepperd's method: picks the numerically largest of the four candidate denominators.
    """
    r = np.asarray(r, np.float64)
    m = r.reshape(-1, 3, 3)
    q = np.empty((m.shape[0], 4))
    tr = np.trace(m, axis1=1, axis2=2)
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    choice = np.argmax(np.concatenate([tr[:, None], diag], axis=1), axis=1)
    for i in range(m.shape[0]):
        a = m[i]
        c = choice[i]
        if c == 0:
            s = 2.0 * np.sqrt(1.0 + tr[i])
            q[i] = [
                (a[2, 1] - a[1, 2]) / s,
                (a[0, 2] - a[2, 0]) / s,
                (a[1, 0] - a[0, 1]) / s,
                s / 4,
            ]
        elif c == 1:
            s = 2.0 * np.sqrt(1.0 + a[0, 0] - a[1, 1] - a[2, 2])
            q[i] = [
                s / 4,
                (a[0, 1] + a[1, 0]) / s,
                (a[0, 2] + a[2, 0]) / s,
                (a[2, 1] - a[1, 2]) / s,
            ]
        elif c == 2:
            s = 2.0 * np.sqrt(1.0 + a[1, 1] - a[0, 0] - a[2, 2])
            q[i] = [
                (a[0, 1] + a[1, 0]) / s,
                s / 4,
                (a[1, 2] + a[2, 1]) / s,
                (a[0, 2] - a[2, 0]) / s,
            ]
        else:
            s = 2.0 * np.sqrt(1.0 + a[2, 2] - a[0, 0] - a[1, 1])
            q[i] = [
                (a[0, 2] + a[2, 0]) / s,
                (a[1, 2] + a[2, 1]) / s,
                s / 4,
                (a[1, 0] - a[0, 1]) / s,
            ]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(r.shape[:-2] + (4,))


def make_pose(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack (…, 3, 3) rotations and (…, 3) translations into (…, 4, 4) homogeneous matrices."""
    r = np.asarray(r, np.float64)
    t = np.asarray(t, np.float64)
    out = np.zeros(r.shape[:-2] + (4, 4))
    out[..., :3, :3] = r
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of (…, 4, 4) rigid transforms."""
    r = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(r, -np.einsum("...ij,...j->...i", r, T[..., :3, 3]))

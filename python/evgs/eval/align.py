"""Trajectory alignment for evaluation only (paper §4): Umeyama Sim(3)/SE(3) and first-pose rotation.

The SLAM estimate lives in its own world frame with an unobservable scale, so positions are compared
after the least-squares similarity (Umeyama 1991) and orientations after the first-pose rotation
alignment of eq. 13–14.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evgs.geometry import make_pose


@dataclass(frozen=True)
class Sim3:
    """``x ↦ s · R · x + t`` (maps estimate coordinates to ground-truth coordinates)."""

    R: np.ndarray
    t: np.ndarray
    s: float

    def apply_points(self, p: np.ndarray) -> np.ndarray:
        """(…, 3) points → transformed points."""
        return self.s * np.asarray(p, np.float64) @ self.R.T + self.t

    def apply_poses(self, T: np.ndarray) -> np.ndarray:
        """(…, 4, 4) camera-to-world poses → poses in the target frame (translations scaled, rotations
        pre-multiplied by ``R``; the camera axes themselves stay orthonormal)."""
        return make_pose(self.R @ T[..., :3, :3], self.apply_points(T[..., :3, 3]))

    def inverse(self) -> Sim3:
        r_inv = self.R.T
        return Sim3(r_inv, -(r_inv @ self.t) / self.s, 1.0 / self.s)

    def matrix(self) -> np.ndarray:
        """The 4×4 homogeneous matrix ``[[sR, t], [0, 1]]``."""
        return make_pose(self.s * self.R, self.t)


def umeyama(src: np.ndarray, dst: np.ndarray, *, with_scale: bool = True) -> Sim3:
    """Least-squares ``dst ≈ s R src + t`` for (N, 3) corresponding points (Umeyama 1991, eq. 34–43).

    The SVD of the cross-covariance can yield an orthogonal matrix with det −1 (noisy or coplanar data);
    flipping the sign of the smallest singular direction gives the best *proper* rotation.
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama: expected two equal (N, 3) arrays, got {src.shape} and {dst.shape}")
    n = src.shape[0]
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    var_s = float(np.sum(xs * xs)) / n
    cov = xd.T @ xs / n
    u, d, vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(np.float64).eps * max(d[0], 1.0)) < 2:
        raise ValueError(f"umeyama: degenerate point sets ({n} points, rank < 2): alignment is undefined")
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    R = (u * sign) @ vt
    s = float(np.sum(d * sign)) / var_s if with_scale else 1.0
    return Sim3(R, mu_d - s * R @ mu_s, s)


def first_pose_rotation(R_gt_first: np.ndarray, R_est_first: np.ndarray) -> np.ndarray:
    """Eq. 13: ``R_align = R_gt,1 · R_est,1⁻¹``."""
    return R_gt_first @ R_est_first.T


def align_first_pose(T_gt: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """Eq. 14: ``T_est-aligned,i = T_align · T_est,i`` with the pure rotation of eq. 13."""
    R_align = first_pose_rotation(T_gt[0, :3, :3], T_est[0, :3, :3])
    return make_pose(R_align, np.zeros(3)) @ T_est

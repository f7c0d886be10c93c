"""Timestamp association: the ground truth is interpolated at the estimate's timestamps.

Estimates are produced at frame (chunk-boundary) times, which rarely coincide with ground-truth samples;
interpolating the (denser) ground truth avoids the nearest-neighbour time error of plain matching.
Estimates outside the ground-truth time span cannot be interpolated: they are dropped and counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from evgs.geometry import make_pose


@dataclass(frozen=True)
class Association:
    t: np.ndarray  # (N,) seconds, the kept estimate timestamps
    T_gt: np.ndarray  # (N, 4, 4) ground truth interpolated at ``t``
    T_est: np.ndarray  # (N, 4, 4)
    est_index: np.ndarray  # (N,) indices into the original estimate
    dropped: int  # estimates outside the ground-truth span


def interpolate_poses(t_src: np.ndarray, T_src: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Poses at ``t_query`` (inside ``[t_src[0], t_src[-1]]``): linear translation, geodesic (slerp)
    rotation between the bracketing samples. Exact sample times return the sample unchanged."""
    t_src = np.asarray(t_src, np.float64)
    t_query = np.asarray(t_query, np.float64)
    if np.any(np.diff(t_src) <= 0):
        raise ValueError("interpolate_poses: source timestamps must be strictly increasing")
    if np.any((t_query < t_src[0]) | (t_query > t_src[-1])):
        raise ValueError("interpolate_poses: query time outside the source time span")
    idx = np.searchsorted(t_src, t_query, side="left")  # first sample at or after the query
    exact = t_src[idx] == t_query
    out = np.empty((len(t_query), 4, 4))
    out[exact] = T_src[idx[exact]]
    hi = idx[~exact]  # ≥ 1 here: the query is inside the span and not equal to t_src[0]
    if hi.size == 0:
        return out
    lo = hi - 1
    a = (t_query[~exact] - t_src[lo]) / (t_src[hi] - t_src[lo])
    R0 = T_src[lo, :3, :3]
    rel = Rotation.from_matrix(np.swapaxes(R0, 1, 2) @ T_src[hi, :3, :3]).as_rotvec()
    R = R0 @ Rotation.from_rotvec(rel * a[:, None]).as_matrix()
    p = (1 - a)[:, None] * T_src[lo, :3, 3] + a[:, None] * T_src[hi, :3, 3]
    out[~exact] = make_pose(R, p)
    return out


def associate(
    t_est: np.ndarray, T_est: np.ndarray, t_gt: np.ndarray, T_gt: np.ndarray, *, tol: float = 1e-6
) -> Association:
    """Pair every estimate with the ground truth interpolated at its timestamp (seconds).

    ``tol`` (seconds) lets estimates within rounding distance of the ground-truth span snap onto its
    ends rather than being dropped.
    """
    t_est = np.asarray(t_est, np.float64)
    t_gt = np.asarray(t_gt, np.float64)
    t_q = t_est.copy()
    t_q[np.abs(t_q - t_gt[0]) <= tol] = t_gt[0]
    t_q[np.abs(t_q - t_gt[-1]) <= tol] = t_gt[-1]
    keep = np.flatnonzero((t_q >= t_gt[0]) & (t_q <= t_gt[-1]))
    if len(keep) == 0:
        raise ValueError(
            f"no estimated pose lies inside the ground-truth time span [{t_gt[0]:.6f}, {t_gt[-1]:.6f}] s"
        )
    return Association(
        t=t_est[keep],
        T_gt=interpolate_poses(t_gt, T_gt, t_q[keep]),
        T_est=np.asarray(T_est, np.float64)[keep],
        est_index=keep,
        dropped=len(t_est) - len(keep),
    )

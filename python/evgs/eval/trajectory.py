"""Trajectory metrics (paper §4): ATE after Sim(3) alignment (eq. 15), per-axis RMSE, orientation error
after first-pose alignment (eq. 16–17), drift, yaw/pitch/roll RMSE and the relative pose error (RPE);
beyond the paper, the orientation error under the ATE's own Sim(3) (the gaze error).

The paper's orientation error aligns the first poses' rotations, so a camera that looks a constant angle
beside where its path says it should (an orbit whose cameras look beside the target's centre, the
bas-relief trade of docs/ablations.md §33, §36) reads 0 there; under the Sim(3) that aligns the
positions it reads that angle at every frame.

Conventions (chosen to agree with evo's ``evo_ape tum GT EST -as`` and ``evo_rpe tum GT EST -as``):
- positions compared after the Umeyama Sim(3) estimate → ground truth; errors in ground-truth units;
- the gaze error of a frame: the angle of ``R_gt,iᵀ R R_est,i`` with ``R`` the Sim(3)'s rotation (evo's
  ``evo_ape … -as -r angle_deg``);
- RPE of a pair (i, j): ``E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)`` with Q = ground truth, P = Sim(3)-aligned
  estimate; pairs are consecutive, every ``delta`` frames or every ``delta`` metres of (aligned)
  estimated path;
- Euler angles are intrinsic Z-Y-X (``R = Rz(yaw) Ry(pitch) Rx(roll)``) of camera-to-world rotations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from evgs.eval.align import Sim3, align_first_pose, umeyama
from evgs.geometry import invert_pose

GAZE_MIN_SPREAD = 3.0


def gaze_errors_deg(T_gt: np.ndarray, R_sim: np.ndarray, ate_rmse: float) -> np.ndarray:
    """(N,) orientation errors of the Sim(3)-aligned rotations ``R_sim``, or NaN where the ground-truth
    positions' RMS spread across their main axis is below ``GAZE_MIN_SPREAD`` × ``ate_rmse``."""
    p = T_gt[:, :3, 3] - T_gt[:, :3, 3].mean(0)
    spread = np.linalg.svd(p, compute_uv=False) / np.sqrt(len(p))
    if np.hypot(spread[1], spread[2]) < GAZE_MIN_SPREAD * ate_rmse:
        return np.full(len(T_gt), np.nan)
    return orientation_errors_deg(T_gt[:, :3, :3], R_sim)


def rmse(x: np.ndarray, axis: int | None = None) -> np.ndarray | float:
    return np.sqrt(np.mean(np.square(x), axis=axis))


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """(…, 3, 3) → angle in radians of each rotation, eq. 17.

    ``acos((tr R − 1) / 2)`` loses half the digits near 0 and π; the equivalent
    ``atan2(‖vee(R − Rᵀ)‖ / 2, (tr R − 1) / 2)`` is accurate over the whole range.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation_angle: expected (…, 3, 3) rotations, got {R.shape}")
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(np.linalg.norm(v, axis=-1) / 2.0, c)


def euler_ypr_deg(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) → (N, 3) intrinsic Z-Y-X angles (yaw, pitch, roll) in degrees."""
    return Rotation.from_matrix(R).as_euler("ZYX", degrees=True)


def wrap_deg(a: np.ndarray) -> np.ndarray:
    """Angles to (−180°, 180°]."""
    return 180.0 - np.mod(180.0 - a, 360.0)


def orientation_errors_deg(R_gt: np.ndarray, R_est_aligned: np.ndarray) -> np.ndarray:
    """Eq. 16–17: angle of ``R_gt,iᵀ R_est-aligned,i`` per frame, degrees."""
    return np.degrees(rotation_angle(np.swapaxes(R_gt, -1, -2) @ R_est_aligned))


@dataclass(frozen=True)
class RPE:
    delta: float
    unit: str  # "frames" or "m"
    pairs: np.ndarray  # (M, 2) index pairs (i, j)
    trans: np.ndarray  # (M,) translation error, ground-truth units
    rot_deg: np.ndarray  # (M,) rotation error, degrees


def rpe_pairs(positions: np.ndarray, delta: float, unit: str) -> np.ndarray:
    """Consecutive index pairs ``delta`` frames apart, or each time the travelled path reaches ``delta``."""
    n = len(positions)
    if unit == "frames":
        step = int(delta)
        if step < 1 or step != delta:
            raise ValueError(f"RPE delta in frames must be a positive integer, got {delta}")
        ids = np.arange(0, n, step)
    elif unit == "m":
        if delta <= 0:
            raise ValueError(f"RPE delta in metres must be positive, got {delta}")
        # Walk the path, restarting the accumulated length at every selected pose (sequential by nature).
        steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        ids_list = [0]
        acc = 0.0
        for i, step_len in enumerate(steps, start=1):
            acc += float(step_len)
            if acc >= delta:
                ids_list.append(i)
                acc = 0.0
        ids = np.asarray(ids_list)
    else:
        raise ValueError(f"RPE unit must be 'frames' or 'm', got {unit!r}")
    return np.stack([ids[:-1], ids[1:]], axis=1).reshape(-1, 2)


def rpe(T_gt: np.ndarray, T_est: np.ndarray, delta: float = 1, unit: str = "frames") -> RPE:
    """Relative pose error between (already aligned) estimate and ground truth; pairs follow the
    estimate's path (evo's default)."""
    pairs = rpe_pairs(T_est[:, :3, 3], delta, unit)
    i, j = pairs[:, 0], pairs[:, 1]
    rel_gt = invert_pose(T_gt[i]) @ T_gt[j]
    rel_est = invert_pose(T_est[i]) @ T_est[j]
    E = invert_pose(rel_gt) @ rel_est
    return RPE(
        float(delta),
        unit,
        pairs,
        np.linalg.norm(E[:, :3, 3], axis=1),
        np.degrees(rotation_angle(E[:, :3, :3])),
    )


@dataclass(frozen=True)
class TrajectoryMetrics:
    sim3: Sim3  # estimate → ground truth
    p_gt: np.ndarray  # (N, 3)
    p_est: np.ndarray  # (N, 3) Sim(3)-aligned estimate
    ate_errors: np.ndarray  # (N,) ‖p_gt − p_est‖
    ate_rmse: float  # eq. 15
    axis_rmse: np.ndarray  # (3,) x, y, z
    ypr_gt_deg: np.ndarray  # (N, 3) yaw, pitch, roll
    ypr_est_deg: np.ndarray  # (N, 3) of the first-pose-aligned estimate
    ypr_rmse_deg: np.ndarray  # (3,) wrapped differences
    orientation_error_deg: np.ndarray  # (N,) eq. 16–17
    drift_deg: float  # orientation error at the last frame
    gaze_error_deg: np.ndarray  # (N,) orientation error under the Sim(3) (evo's APE angle_deg), or NaN
    rpe_frame: RPE  # consecutive frames
    rpe_metre: RPE  # every ``rpe_delta_m`` of path

    def summary(self) -> dict[str, float]:
        """Flat scalar metrics (for tables, JSON and CSV)."""
        return {
            "ate_rmse": float(self.ate_rmse),
            "ate_x": float(self.axis_rmse[0]),
            "ate_y": float(self.axis_rmse[1]),
            "ate_z": float(self.axis_rmse[2]),
            "scale": float(self.sim3.s),
            "drift_deg": float(self.drift_deg),
            "rot_err_rmse_deg": float(rmse(self.orientation_error_deg)),
            "gaze_err_rmse_deg": float(rmse(self.gaze_error_deg)),
            "yaw_rmse_deg": float(self.ypr_rmse_deg[0]),
            "pitch_rmse_deg": float(self.ypr_rmse_deg[1]),
            "roll_rmse_deg": float(self.ypr_rmse_deg[2]),
            "rpe_trans_rmse": rmse_or_nan(self.rpe_frame.trans),
            "rpe_rot_rmse_deg": rmse_or_nan(self.rpe_frame.rot_deg),
            "rpe_m_trans_rmse": rmse_or_nan(self.rpe_metre.trans),
            "rpe_m_rot_rmse_deg": rmse_or_nan(self.rpe_metre.rot_deg),
        }


def rmse_or_nan(x: np.ndarray) -> float:
    """RMSE, or NaN when there are no samples (e.g. a path shorter than the RPE distance)."""
    return float(rmse(x)) if x.size else float("nan")


def evaluate_trajectory(
    T_gt: np.ndarray, T_est: np.ndarray, *, with_scale: bool = True, rpe_delta_m: float = 1.0
) -> TrajectoryMetrics:
    """All trajectory metrics for associated (N, 4, 4) camera-to-world pose pairs."""
    T_gt = np.asarray(T_gt, np.float64)
    T_est = np.asarray(T_est, np.float64)
    if T_gt.shape != T_est.shape or T_gt.ndim != 3 or len(T_gt) < 3:
        raise ValueError(f"need ≥ 3 associated poses of equal shape, got {T_gt.shape} and {T_est.shape}")
    sim3 = umeyama(T_est[:, :3, 3], T_gt[:, :3, 3], with_scale=with_scale)
    T_sim = sim3.apply_poses(T_est)
    p_gt = T_gt[:, :3, 3]
    diff = T_sim[:, :3, 3] - p_gt
    ate_rmse = float(rmse(np.linalg.norm(diff, axis=1)))
    R_gt = T_gt[:, :3, :3]
    R_first = align_first_pose(T_gt, T_est)[:, :3, :3]
    ypr_gt = euler_ypr_deg(R_gt)
    ypr_est = euler_ypr_deg(R_first)
    orient = orientation_errors_deg(R_gt, R_first)
    return TrajectoryMetrics(
        sim3=sim3,
        p_gt=p_gt,
        p_est=T_sim[:, :3, 3],
        ate_errors=np.linalg.norm(diff, axis=1),
        ate_rmse=ate_rmse,
        axis_rmse=np.asarray(rmse(diff, axis=0)),
        ypr_gt_deg=ypr_gt,
        ypr_est_deg=ypr_est,
        ypr_rmse_deg=np.asarray(rmse(wrap_deg(ypr_est - ypr_gt), axis=0)),
        orientation_error_deg=orient,
        drift_deg=float(orient[-1]),
        gaze_error_deg=gaze_errors_deg(T_gt, T_sim[:, :3, :3], ate_rmse),
        rpe_frame=rpe(T_gt, T_sim, 1, "frames"),
        rpe_metre=rpe(T_gt, T_sim, rpe_delta_m, "m"),
    )

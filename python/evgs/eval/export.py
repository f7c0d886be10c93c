"""Trajectory export for other tools: TUM (``t tx ty tz qx qy qz qw``) and KITTI (the 3×4 matrix
``[R | t]`` row-major, 12 values per line, no timestamps)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from evgs.data.tum import write_tum
from evgs.io_util import atomic_path

if TYPE_CHECKING:
    from evgs.eval.run import RunEvaluation


def write_kitti(path: str | Path, T: np.ndarray) -> None:
    """Write (N, 4, 4) poses atomically in KITTI odometry format."""
    rows = np.asarray(T, np.float64)[:, :3, :].reshape(len(T), 12)
    with atomic_path(path) as tmp:
        np.savetxt(tmp, rows, fmt="%.9e")


def export_run(ev: RunEvaluation, out_dir: Path, fmt: str) -> list[Path]:
    """Ground truth (interpolated at the estimate's times) and the Sim(3)-aligned estimate of a
    :class:`evgs.eval.run.RunEvaluation` as ``<seq>_<run>.{gt,est}.{tum,kitti}`` files."""
    stem = f"{ev.run_dir.parent.name}_{ev.run_dir.name}"
    est = ev.traj.sim3.apply_poses(ev.assoc.T_est)
    paths = [out_dir / f"{stem}.gt.{fmt}", out_dir / f"{stem}.est.{fmt}"]
    for path, T in zip(paths, (ev.assoc.T_gt, est), strict=True):
        if fmt == "tum":
            write_tum(path, ev.assoc.t, T)
        elif fmt == "kitti":
            write_kitti(path, T)
        else:
            raise ValueError(f"unknown trajectory format {fmt!r}")
    return paths

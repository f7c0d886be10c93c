"""Render a run's final scene (``gaussians.ply``) at the ground-truth frame times for the image metrics.

Two viewpoints (``evgs.eval.run.ImagePoses``):
- ``"estimate"`` (default): the estimated poses at those frames. The map lives in the estimate's frame,
  so this equals rendering the Sim(3)-aligned map at the aligned estimate — what the run itself would
  show at those times; pose errors lower the scores.
- ``"gt"``: each ground-truth pose brought into the map with the inverse of the evaluation Sim(3)
  (estimate → ground truth), so the images show the scene from the true viewpoints and measure the map
  alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from evgs.data.sequence import Sequence
from evgs.eval.align import Sim3
from evgs.eval.associate import interpolate_poses
from evgs.geometry import invert_pose
from evgs.render import render
from evgs.slam.gaussians import load_ply


def gt_poses_at(seq: Sequence, frames: np.ndarray) -> np.ndarray:
    """(F, 4, 4) camera-to-world ground-truth poses at the given sequence frames (interpolated)."""
    gt = seq.poses_gt()
    if gt is None:
        raise ValueError(f"{seq.root}: sequence has no poses_gt.txt")
    t_us = seq.frames_us()[frames]
    return interpolate_poses(gt[0].astype(np.float64), gt[1], t_us.astype(np.float64))


def gt_poses_in_map(seq: Sequence, sim3: Sim3, frames: np.ndarray) -> np.ndarray:
    """(F, 4, 4) camera-to-map poses of the ground truth at the given sequence frames."""
    return sim3.inverse().apply_poses(gt_poses_at(seq, frames))


def render_at_gt_frames(
    ply: str | Path, seq: Sequence, sim3: Sim3, frames: np.ndarray, *, batch: int = 4
) -> np.ndarray:
    """Renders from the ground-truth viewpoints (``"gt"``) at the given sequence frames."""
    return render_map(ply, seq, gt_poses_in_map(seq, sim3, frames), batch=batch)


def render_map(ply: str | Path, seq: Sequence, T_map_c: np.ndarray, *, batch: int = 4) -> np.ndarray:
    """(F, H, W) grey renders in [0, 1] from camera-to-map poses; colour renders are averaged over
    channels to match the grey ground-truth images."""
    g = load_ply(ply)
    viewmats = torch.from_numpy(invert_pose(T_map_c).astype(np.float32))
    out = []
    with torch.inference_mode():
        for s in range(0, len(viewmats), batch):
            res = render(**g.render_inputs(), viewmats=viewmats[s : s + batch], camera=seq.camera)
            out.append(res.color.mean(dim=-1).clamp(0.0, 1.0).numpy())
    return np.concatenate(out).astype(np.float64)

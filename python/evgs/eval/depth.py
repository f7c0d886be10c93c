"""Where the map's surfaces are: its depth against the simulated scene's, from the ground-truth viewpoints.

PSNR says whether the map looks right from the cameras; a target's shape, and the range meter's
first-surface scale (evgs.slam.metric_scale), depend on where its surfaces lie. A sequence evgs
simulated names its scene in ``sequence.toml`` (``[simulator]``), so the renderer's depth pass gives the
true depth at every ground-truth frame. The map is rendered from the same viewpoints, brought into its
frame by the inverse of the evaluation Sim(3) (evgs.eval.render_gt), and its depths are put in metres by
that Sim(3)'s scale. Compared at the pixels where both see a surface (the map's opacity ≥ ``MIN_ALPHA``,
its mean depth ``D / alpha`` there), per frame:

- depth L1 (metres): the mean ``|D_map − D_gt|`` (the dense-SLAM convention);
- relative error: the median of ``D_map / D_gt − 1``, signed: below 0 the map sits nearer the camera
  than the target, as if the meter read short;
- coverage: the share of the target's pixels the map covers;
- spill: the map's opaque pixels off the target, per target pixel. On a black background dark Gaussians
  beside the target cost no PSNR, but they are surfaces all the same (a range meter would meet them).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from evgs.data.sequence import Sequence
from evgs.eval.align import Sim3
from evgs.eval.render_gt import gt_poses_at
from evgs.geometry import invert_pose
from evgs.render import render
from evgs.slam.gaussians import load_ply

if TYPE_CHECKING:
    from evgs.sim.scene import Scene

MIN_ALPHA = 0.5  # a pixel whose opacity is below this is the background's, not the map's


@dataclass(frozen=True)
class DepthView:
    """One frame's depths for a figure (evgs.eval.plots.plot_depth_views)."""

    frame: int
    gt_m: np.ndarray  # (H, W) the scene's depth, inf off the target
    map_m: np.ndarray  # (H, W) the map's mean depth in metres, NaN where its opacity is below MIN_ALPHA


@dataclass(frozen=True)
class DepthMetrics:
    frames: np.ndarray  # (F,) sequence frames
    l1_m: np.ndarray  # (F,) mean |D_map − D_gt| over the compared pixels, metres (NaN: none compared)
    rel: np.ndarray  # (F,) median D_map / D_gt − 1 over them
    coverage: np.ndarray  # (F,) compared pixels / the target's pixels
    spill: np.ndarray  # (F,) the map's opaque pixels off the target / the target's pixels
    views: tuple[DepthView, ...] = ()  # the first, middle and last frames' depths

    def summary(self) -> dict[str, float]:
        """The errors' means over the frames with compared pixels (the relative error in per cent; NaN
        where the map covers the target in none), coverage and spill over every frame that sees it."""

        def mean(x: np.ndarray, scale: float = 1.0) -> float:
            ok = np.isfinite(x)
            return float(np.mean(x[ok]) * scale) if ok.any() else float("nan")

        return {
            "depth_l1_m": mean(self.l1_m),
            "depth_err_pct": mean(self.rel, 100.0),
            "depth_coverage": mean(self.coverage),
            "depth_spill": mean(self.spill),
        }


def map_depth_m(map_depth: np.ndarray, map_alpha: np.ndarray, scale: float) -> np.ndarray:
    """The map's mean depth ``D / alpha`` in metres (``scale`` per map unit), NaN below ``MIN_ALPHA``."""
    opaque = map_alpha >= MIN_ALPHA
    return np.where(opaque, scale * map_depth / np.where(opaque, map_alpha, 1.0), np.nan)


def compare_depth(
    map_depth: np.ndarray, map_alpha: np.ndarray, gt_depth: np.ndarray, scale: float
) -> tuple[float, float, float, float]:
    """``(l1_m, rel, coverage, spill)`` of one view: the map's expected depth ``map_depth``
    (un-normalised, map units) and opacity against the true depth ``gt_depth`` (metres, inf off the
    target), the map's depths taken to metres by ``scale``."""
    target = np.isfinite(gt_depth)
    d_map = map_depth_m(map_depth, map_alpha, scale)
    seen = target & np.isfinite(d_map)
    coverage = float(seen.sum() / target.sum()) if target.any() else 0.0
    spill = float((np.isfinite(d_map) & ~target).sum() / target.sum()) if target.any() else float("nan")
    if not seen.any():
        return float("nan"), float("nan"), coverage, spill
    d_map, d_gt = d_map[seen], gt_depth[seen]
    return float(np.mean(np.abs(d_map - d_gt))), float(np.median(d_map / d_gt - 1.0)), coverage, spill


def simulated_scene(seq: Sequence) -> Scene | None:
    """The scene a sequence was simulated from, or None for any other sequence (or a mesh file that is
    no longer where it was). The simulator is imported here, not at the top: trimesh and moderngl are
    for simulated sequences only."""
    sim = seq.meta.get("simulator")
    if not isinstance(sim, dict) or "target" not in sim:
        return None
    from evgs.sim.scene import SURFACE_SEED, make_scene

    try:
        return make_scene(
            str(sim["target"]), str(sim.get("material", "paint")), float(sim.get("mesh_scale", 1.0)),
            int(sim.get("seed", SURFACE_SEED)),
        )  # fmt: skip
    except ValueError:
        return None


def evaluate_depth(
    ply: str | Path, seq: Sequence, scene: Scene, sim3: Sim3, frames: np.ndarray
) -> DepthMetrics:
    """:class:`DepthMetrics` of the map ``ply`` at the sequence ``frames``, against ``scene`` (the
    simulated one, :func:`simulated_scene`), the map brought to the ground truth by ``sim3``."""
    from evgs.sim.lights import Lighting
    from evgs.sim.render import Renderer

    T_world_c = gt_poses_at(seq, frames)
    T_map_c = sim3.inverse().apply_poses(T_world_c)
    g = load_ply(ply)
    viewmats = torch.from_numpy(invert_pose(T_map_c).astype(np.float32))
    shown = {0, len(frames) // 2, len(frames) - 1}
    rows, views = [], []
    with Renderer(scene, seq.camera, Lighting(sun_dir=(0.0, 0.0, 1.0), sun=0.0), msaa=0) as r:
        for i in range(len(frames)):
            with torch.inference_mode():
                out = render(**g.render_inputs(), viewmats=viewmats[i : i + 1], camera=seq.camera)
            depth, alpha, gt_m = out.depth[0].numpy(), out.alpha[0].numpy(), r.depth(T_world_c[i])
            rows.append(compare_depth(depth, alpha, gt_m, sim3.s))
            if i in shown:
                views.append(DepthView(int(frames[i]), gt_m, map_depth_m(depth, alpha, sim3.s)))
    l1, rel, cov, spill = np.array(rows, dtype=np.float64).reshape(-1, 4).T
    return DepthMetrics(np.asarray(frames), l1, rel, cov, spill, tuple(views))

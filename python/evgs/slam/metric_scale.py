"""Metric outputs: the scale of a monocular run from a range meter or a known target size.

The event loss cannot see scale: scaling the map and every knot's translation by ``s`` leaves every
render unchanged. So a run ends with one similarity that makes its outputs metric:

- ``range``: a range meter (ELOPE's, or the simulator's ``range.csv``) measures the distance along the
  optical axis at the image centre; the map's expected depth on that ray at the same times (a 1×1 render
  of the principal ray) is the same distance in map units. ``s`` = the median of their ratios over the
  samples whose ray the map covers (alpha ≥ ``scale.min_alpha``), robust to samples that hit a part of
  the target the map lacks.
- ``target_size``: the map's largest extent (2nd–98th percentile of the opaque Gaussians' centres along
  their principal axes) is ``scale.target_size`` metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from evgs.config import ScaleConfig
from evgs.slam.gaussians import Gaussians
from evgs.slam.range_prior import covered_ratios
from evgs.slam.state import SlamState


@dataclass(frozen=True)
class ScaleEstimate:
    scale: float  # metres per map unit
    samples: int  # range samples used (0 for target_size)
    source: str


def range_scale(state: SlamState, t_us: np.ndarray, ranges: np.ndarray, min_alpha: float) -> ScaleEstimate:
    """Median of ``range / rendered depth`` on the principal ray over the samples inside the run."""
    keep = np.isfinite(ranges) & (ranges > 0)
    ratios, inside = covered_ratios(
        state.gaussians, state.traj, t_us[keep], ranges[keep], state.data.camera,
        state.cfg.gaussians.background, min_alpha,
    )  # fmt: skip
    if not inside:
        lo, hi = int(state.traj.t_us[0]), int(state.traj.t_us[-1])
        raise ValueError(f"scale: no range sample lies inside the run's time span [{lo}, {hi}] µs")
    if not len(ratios):
        raise ValueError(
            f"scale: the map covers the image centre (alpha ≥ {min_alpha:g}) at none of the "
            f"{inside} range samples; lower scale.min_alpha or use scale.source = 'target_size'"
        )
    return ScaleEstimate(float(np.median(ratios)), len(ratios), "range")


@torch.no_grad()
def map_extent(gaussians: Gaussians, min_opacity: float = 0.5) -> float:
    """Largest 2nd–98th percentile spread of the opaque Gaussians' centres along their principal axes."""
    means = gaussians["means"][gaussians.opacities() >= min_opacity].double()
    if len(means) < 4:
        raise ValueError(f"scale: only {len(means)} Gaussians with opacity ≥ {min_opacity:g}: no extent")
    centred = means - means.mean(0)
    _, _, axes = torch.linalg.svd(centred, full_matrices=False)
    proj = centred @ axes.T
    q = torch.quantile(proj, torch.tensor([0.02, 0.98], dtype=torch.float64), dim=0)
    return float((q[1] - q[0]).max())


def estimate_scale(state: SlamState, cfg: ScaleConfig) -> ScaleEstimate | None:
    if cfg.source == "none":
        return None
    if cfg.source == "target_size":
        return ScaleEstimate(cfg.target_size / map_extent(state.gaussians), 0, "target_size")
    seq_ranges = state.data.ranges
    if seq_ranges is None:
        raise ValueError("scale.source = 'range' but the sequence has no range.csv")
    return range_scale(state, *seq_ranges, cfg.min_alpha)


@torch.no_grad()
def apply_scale(state: SlamState, s: float) -> None:
    """Scale the world about its origin: knot translations, Gaussian centres and sizes (renders unchanged)."""
    traj = state.traj
    traj.rebase()
    traj.base[:, :3, 3] *= s
    state.gaussians["means"].mul_(s)
    state.gaussians["log_scales"].add_(math.log(s))

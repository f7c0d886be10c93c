"""Metric outputs: the scale of a monocular run from a range meter or a known target size.

The event loss cannot see scale: scaling the map and every knot's translation by ``s`` leaves every
render unchanged. So a run ends with one similarity that makes its outputs metric:

- ``range``: a range meter (ELOPE's, or the simulator's ``range.csv``) measures the distance along the
  optical axis at the image centre to the first surface it meets. Two ways to read it, chosen by how
  much of the meter's change the trajectory's own motion explains:
  - the *closing rate* (:func:`closing_scale`): between consecutive samples the range falls by as much
    as the camera advances along its optical axis (exact for a surface facing the camera, or a motion
    along the axis: an approach; a descent's glide, 20° off the axis, over level ground would read 6.5 %
    low, and the simulated terrain averages out to 0.999 over the run, docs/ablations.md §61). ``s`` =
    the meter's total decrease over the camera's total advance, from the initialization's last knot on
    (:func:`after_initialization`). It needs the trajectory only, and the trajectory is what must come
    out metric: the map's depth can be a few per cent off its trajectory (docs/ablations.md §26, §28).
    Its error is the run's own share of travel along the axis: a descent whose glide comes out 27° off
    the axis instead of 20° reads 4.5 % short (§62). Used when the advances explain at least
    ``scale.closing_min_explained`` of the decreases' energy (≈ 1 on approaches and descents).
  - the *first surface* (:func:`range_scale`), otherwise (an orbit: the range changes with the target's
    shape while the camera hardly advances): the map's first surface on that ray at the same times
    (:func:`first_surface`) is the same distance in map units. ``s`` = the median of their ratios over
    the samples whose ray the map covers (opacity ≥ ``scale.min_alpha``), robust to samples that hit a
    part of the target the map lacks. Not the rendered expected depth: a surface the map holds
    half-transparent mixes what lies behind it into that (4–8 % deeper on docking_good, §26). Where
    ``scale.surface_read`` says, before the final global BA (:func:`read_surface_scale`) or at the end.
    That BA keeps the run's scale to 0.06 % but refits the map to windows from the whole run: from an
    initialization with free knots it moves the surface against the cameras (orbit, 3 seeds: read after
    it 5.0 % off, before it 3.1 %, docs/ablations.md §65); with the knots held on the search's orbit it
    brings the surface nearer the truth (2.5 % before, 1.1 % after, §72).
- ``target_size``: the map's largest extent (2nd–98th percentile of the opaque Gaussians' centres along
  their principal axes) is ``scale.target_size`` metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from evgs.config import ScaleConfig
from evgs.slam.gaussians import Gaussians, quat_to_rotmat
from evgs.slam.range_prior import axial_advance, meter_jumps, valid_samples
from evgs.slam.state import SlamState
from evgs.slam.trajectory import Trajectory

ALPHA_MIN, ALPHA_MAX = 1 / 255, 0.99  # the rasterizer's cut-off and clamp (src/raster/project.rs, forward.rs)


@dataclass(frozen=True)
class ScaleEstimate:
    scale: float  # metres per map unit
    samples: int  # range samples used (0 for target_size)
    source: str


@torch.no_grad()
def first_surface(gaussians: Gaussians, T_wc: Tensor) -> tuple[Tensor, Tensor]:
    """``(opacity, depth)`` (V,) on the optical axis of each camera-to-world pose ``T_wc`` (V, 4, 4):
    the ray's total opacity ``1 − Π(1 − αᵢ)`` and the depth at which it has lost half of the light it
    loses (the weighted median of the Gaussians' depths; NaN where nothing is hit).

    Each Gaussian meets the ray where its density along it peaks, at ``t* = dᵀP(μ − o) / dᵀPd`` (``P``
    the inverse covariance), with ``α = min(0.99, o·exp(−q/2))`` for the Mahalanobis distance ``q`` there;
    the ray composites them front to back, as the rasterizer does a pixel.
    """
    means = gaussians["means"].double()
    rot = quat_to_rotmat(gaussians["quats"].double())
    precision = rot @ torch.diag_embed(torch.exp(-2 * gaussians["log_scales"].double())) @ rot.transpose(1, 2)
    opacity = gaussians.opacities().double()
    total = torch.zeros(len(T_wc), dtype=torch.float64)
    depth = torch.full_like(total, math.nan)
    for i, pose in enumerate(torch.as_tensor(T_wc, dtype=torch.float64)):
        offset, axis = means - pose[:3, 3], pose[:3, 2]
        p_axis = precision @ axis  # (N, 3): P d of every Gaussian
        d_p_d = p_axis @ axis
        t_star = (offset * p_axis).sum(1) / d_p_d
        q = torch.einsum("ni,nij,nj->n", offset, precision, offset) - t_star**2 * d_p_d
        alpha = torch.clamp(opacity * torch.exp(-0.5 * q.clamp(min=0)), max=ALPHA_MAX)
        hit = (t_star > 0) & (alpha >= ALPHA_MIN)
        order = torch.argsort(t_star[hit])
        z, a = t_star[hit][order], alpha[hit][order]
        if not len(z):
            continue
        weights = a * torch.cumprod(torch.cat([a.new_ones(1), 1 - a[:-1]]), 0)
        total[i] = weights.sum()
        half = int(torch.searchsorted(torch.cumsum(weights, 0), 0.5 * total[i]))
        depth[i] = z[min(half, len(z) - 1)]
    return total, depth


def samples_inside(traj: Trajectory, t_us: np.ndarray, ranges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The valid samples (:func:`valid_samples`) inside the run's time span, in time order; an error if
    none."""
    t_us, ranges = valid_samples(t_us, ranges)
    lo, hi = int(traj.t_us[0]), int(traj.t_us[-1])
    inside = (t_us >= lo) & (t_us <= hi)
    if not inside.any():
        raise ValueError(f"scale: no range sample lies inside the run's time span [{lo}, {hi}] µs")
    return t_us[inside], ranges[inside]


@dataclass(frozen=True)
class ClosingFit:
    scale: float  # metres per map unit
    explained: float  # share of the decreases' energy the advances explain, 1 − Σ(Δr − s·adv)² / ΣΔr²
    samples: int
    jumps: int  # pairs left out: the meter jumps across them (range_prior.meter_jumps)


@torch.no_grad()
def closing_scale(traj: Trajectory, t_us: np.ndarray, ranges: np.ndarray) -> ClosingFit | None:
    """``s = ΣΔr / Σ advance`` over consecutive samples (time-ordered, inside the trajectory): the
    meter's decreases against the camera's advances along its optical axis, over the pairs across which
    the meter does not jump. None with fewer than two samples or no net advance.

    A ratio of sums, not the least-squares slope through the origin: every sample's position carries
    the tracker's jitter, a pair's advance the difference of two such errors, and least squares adds
    their variance to its denominator, reading the scale low (regression dilution: the trajectory came
    out 1.2–4.5 % too small on every docking_low seed and two swirl_good seeds of three). Summed along a
    steady axis, the advances telescope to the displacement between the first and the last sample,
    where the jitter enters once (docs/ablations.md §60)."""
    if len(t_us) < 2:
        return None
    poses = traj.pose_at(t_us).double()
    steady = ~meter_jumps(ranges)
    advance = axial_advance(poses, poses[:, :3, 2]).numpy()[steady]
    decrease = (ranges[:-1] - ranges[1:])[steady]
    if not (advance.sum() != 0 and decrease @ decrease > 0):
        return None
    s = float(decrease.sum() / advance.sum())
    explained = 1.0 - float(((decrease - s * advance) ** 2).sum() / (decrease @ decrease))
    return ClosingFit(s, explained, len(t_us), int((~steady).sum()))


def after_initialization(
    state: SlamState, t_us: np.ndarray, ranges: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The samples from the initialization's last knot on, when the run goes beyond it (else all).

    The initialization's knots rest on a few frames' baseline and fall behind an approach on every
    swirl seed (knot 1 behind knot 0, §33, §59), which the closing rate would read as scale."""
    m = state.num_init_chunks()
    if len(state.traj) <= m + 1:
        return t_us, ranges
    keep = t_us >= int(state.traj.t_us[m])
    return t_us[keep], ranges[keep]


@dataclass(frozen=True)
class RangeAgreement:
    """The meter against the map along the run: at each range sample inside it, the range and the map's
    first surface on the principal ray (NaN where the map covers the ray less than ``min_alpha``)."""

    t_us: np.ndarray  # (S,)
    ranges: np.ndarray  # (S,) metres
    depth: np.ndarray  # (S,) the run's units

    @property
    def covered(self) -> np.ndarray:
        return np.isfinite(self.depth)

    @property
    def ratios(self) -> np.ndarray:
        """``range / depth`` at the covered samples, in time order."""
        return self.ranges[self.covered] / self.depth[self.covered]

    def median_ratio(self) -> float:
        """The median ``range / depth`` (metres per unit of the run's map); NaN with no covered sample."""
        r = self.ratios
        return float(np.median(r)) if len(r) else math.nan

    def spread(self) -> float:
        """Standard deviation of ``log(range / depth)`` over the covered samples: 0 when the map's
        distance from the cameras keeps to the meter's at one scale; NaN with fewer than two."""
        r = self.ratios
        return float(np.log(r).std()) if len(r) >= 2 else math.nan

    def drift(self) -> float:
        """Median ratio over the last fifth of the covered samples against the first fifth's, minus 1.

        0 when the camera's distance to the map follows the meter's over the run. The events see a
        target's looming weakly, so a run can close in too slowly (or drift along the axis) while its
        map still explains every view: the map then ends farther (negative) or nearer (positive) than the
        meter says, which no ground truth is needed to see (docs/ablations.md §47). NaN with fewer than
        two covered samples."""
        r = self.ratios
        if len(r) < 2:
            return math.nan
        k = max(1, len(r) // 5)
        return float(np.median(r[-k:]) / np.median(r[:k]) - 1.0)


@torch.no_grad()
def range_agreement(
    state: SlamState, t_us: np.ndarray, ranges: np.ndarray, min_alpha: float
) -> RangeAgreement:
    """:class:`RangeAgreement` of the valid samples inside the run (an error if none)."""
    t_us, ranges = samples_inside(state.traj, t_us, ranges)
    opacity, depth = first_surface(state.gaussians, state.traj.pose_at(t_us))
    depth = torch.where(opacity >= min_alpha, depth, torch.full_like(depth, math.nan))
    return RangeAgreement(t_us, ranges, depth.numpy())


def range_scale(state: SlamState, t_us: np.ndarray, ranges: np.ndarray, min_alpha: float) -> ScaleEstimate:
    """Median of ``range / first-surface depth`` on the principal ray over the samples inside the run."""
    agreement = range_agreement(state, t_us, ranges, min_alpha)
    ratios = agreement.ratios
    if not len(ratios):
        raise ValueError(
            f"scale: the map covers the image centre (opacity ≥ {min_alpha:g}) at none of the "
            f"{len(agreement.t_us)} range samples; lower scale.min_alpha or use scale.source = 'target_size'"
        )
    return ScaleEstimate(agreement.median_ratio(), len(ratios), "range, first surface")


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


def read_surface_scale(state: SlamState) -> ScaleEstimate | None:
    """:func:`range_scale` of the state as it stands, for a run with ``scale.source = "range"``,
    ``scale.surface_read = "before_final_ba"`` and a range meter; None otherwise, or when the map covers
    none of the samples (the final read then reports why)."""
    scale = state.cfg.scale
    if scale.source != "range" or scale.surface_read != "before_final_ba" or state.data.ranges is None:
        return None
    try:
        est = range_scale(state, *state.data.ranges, scale.min_alpha)
    except ValueError:
        return None
    return replace(est, source=f"{est.source}, read before the final BA")


def estimate_scale(state: SlamState, cfg: ScaleConfig) -> ScaleEstimate | None:
    """The scale as ``cfg.source`` says. With ``range``, the closing rate when the run's advances explain
    the meter, else the first surface: with ``cfg.surface_read = "before_final_ba"``
    ``state.surface_scale`` (read before the final BA) if there is one, else read now."""
    if cfg.source == "none":
        return None
    if cfg.source == "target_size":
        return ScaleEstimate(cfg.target_size / map_extent(state.gaussians), 0, "target_size")
    seq_ranges = state.data.ranges
    if seq_ranges is None:
        raise ValueError("scale.source = 'range' but the sequence has no range.csv")
    t_us, ranges = samples_inside(state.traj, *seq_ranges)
    fit = closing_scale(state.traj, *after_initialization(state, t_us, ranges))
    if fit is not None and fit.scale > 0 and fit.explained >= cfg.closing_min_explained:
        jumps = f", {fit.jumps} jumps left out" if fit.jumps else ""
        source = f"range, closing rate ({fit.explained:.1%} explained{jumps})"
        return ScaleEstimate(fit.scale, fit.samples, source)
    if cfg.surface_read == "before_final_ba" and state.surface_scale is not None:
        return state.surface_scale
    return range_scale(state, t_us, ranges, cfg.min_alpha)


@torch.no_grad()
def apply_scale(state: SlamState, s: float) -> None:
    """Scale the world about its origin: knot translations, Gaussian centres and sizes (renders unchanged)."""
    traj = state.traj
    traj.rebase()
    traj.base[:, :3, 3] *= s
    state.gaussians["means"].mul_(s)
    state.gaussians["log_scales"].add_(math.log(s))

"""A range meter inside the optimisation (``scale.range_weight``, ``init.search_range_weight`` > 0).

The event loss cannot see scale, and sees motion along the optical axis only through the slow looming
of the image: an approach at the wrong speed, or an orbit at the wrong rate with the relief scaled to
match, explains the events almost as well. A range meter (ELOPE's, the simulator's ``range.csv``)
measures the distance along the optical axis at the image centre: the expected depth ``D̄`` of a 1×1
render on the principal ray. Its *ratios* between times are what the trajectory lacks: along an
approach they fix the speed, and as the ray sweeps the target they fix the relief the motion must
agree with.

So every stage adds ``scale.range_weight · mean(h(q))``, ``q = D̄ · u / r − 1``, and the motion search
adds ``init.search_range_weight · mean(h(q))`` to each hypothesis' score, over the range samples in their
chunks whose principal ray the map covers (alpha ≥ ``scale.min_alpha``), each rendered at the
trajectory's pose at the sample's own time (no interpolation: the range jumps where the ray crosses an
edge). ``h`` is ``q²`` up to ``HUBER`` and linear beyond, so a sample on an edge or on a part the map
lacks cannot dominate. ``u`` (metres per map unit) is the median ratio ``r / D̄`` over every sample
the trajectory has reached so far, re-estimated at the start of each stage (the run's scale is free
until its end, :mod:`evgs.slam.metric_scale`). The term moves the poses only: the Gaussians are the
events' to place — free to move, a few of them on the principal ray would echo any range sequence
back (an orbit with a star of surfaces about its centre), and the motion search could not tell an
orbit from an approach.

``scale.rate_weight`` adds a second, map-free term: between consecutive samples the camera's advance
along its optical axis, in metres, equals the decrease of the range, ``q = (u₀·aᵢ·(Cᵢ₊₁ − Cᵢ) − (rᵢ −
rᵢ₊₁)) / rᵢ₊₁`` — exact for a flat surface facing the camera, as the target of an approach or the ground
of a descent is, and a small error where the ray sweeps relief. It is independent of the map's depth on
the principal ray (too rough to steer poses by, docs/ablations.md §9; empty in the dark, where the
centre of a uniform face fires no events):
- its unit ``u₀`` is fixed once, by the seeding: the map is seeded around ``gaussians.init_depth`` on the
  first camera's axis, so the meter's first reading is that depth in metres. The meter thereby sets the
  run's gauge from the start, and the map, shaped by the events, follows the trajectory;
- the axis ``aᵢ`` is held where the pose has it (no gradient): the meter measures how far the camera
  advanced, not where it points;
- pairs across which the meter jumps (:func:`meter_jumps`: the ray crossed an edge onto a nearer or
  farther surface) are left out: no advance explains them, and at the weights that hold an approach a
  single one would outweigh the events (the orbit's first pairs: the search picked a retreat).
In the dark, where the looming of the few edges that fire hardly tells the tracker how fast the camera
closes in, it does (docs/ablations.md §28).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from evgs.config import Config
from evgs.data.sequence import Camera
from evgs.render import render
from evgs.slam.gaussians import Gaussians
from evgs.slam.trajectory import Trajectory
from evgs.slam.windows import EventData

HUBER = 0.05  # relative range error beyond which a sample counts linearly (an edge, a part not mapped)
JUMP = 0.02  # a pair's range change this far (× range) from the median around it: the ray crossed an edge


def principal_camera(camera: Camera) -> Camera:
    """A 1×1 camera whose only pixel centre lies on ``camera``'s principal ray (distortion-free there)."""
    return replace(camera, width=1, height=1, cx=0.0, cy=0.0, distortion=())


def principal_depth(
    gaussians: Gaussians, viewmats: Tensor, camera: Camera, background: float
) -> tuple[Tensor, Tensor]:
    """``(alpha, mean depth D/alpha)`` (V,) on the principal ray of each view; differentiable in the
    views only (the map is the events' to shape, see the module docstring)."""
    inputs = {k: v.detach() for k, v in gaussians.render_inputs().items()}
    out = render(**inputs, viewmats=viewmats, camera=principal_camera(camera), background=background)
    alpha, depth = out.alpha.reshape(-1), out.depth.reshape(-1)
    return alpha, depth / alpha.clamp(min=1e-6)


def valid_samples(t_us: np.ndarray, metres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(t_us, metres)`` of the samples that are ranges (finite, positive), in time order: a meter
    without a return (NaN) or reading 0 says nothing about the distance."""
    t, r = np.asarray(t_us), np.asarray(metres)
    keep = np.isfinite(r) & (r > 0)
    order = np.argsort(t[keep], kind="stable")
    return t[keep][order].astype(np.int64), r[keep][order].astype(np.float64)


def meter_jumps(metres: np.ndarray) -> np.ndarray:
    """(S − 1,) bool: the pairs of consecutive samples ``metres`` (S,) across which the meter jumps.

    The camera's advance changes smoothly from one pair to the next; where the ray crosses an edge (the
    orbit's dish onto the bus behind it: +7 % in one sample) the range steps by a depth gap no motion
    explains. A pair jumps when its decrease differs from the median decrease of the (up to) five pairs
    centred on it by more than ``JUMP`` of the range; the closing rate leaves such pairs out."""
    r = np.asarray(metres, dtype=np.float64)
    dec = r[:-1] - r[1:]
    if len(dec) < 2:
        return np.zeros(len(dec), dtype=bool)
    padded = np.pad(dec, 2, constant_values=np.nan)
    around = np.stack([padded[k : k + len(dec)] for k in range(5)])
    return np.abs(dec - np.nanmedian(around, axis=0)) > JUMP * r[1:]


def axial_advance(poses: Tensor, axes: Tensor) -> Tensor:
    """(..., S − 1) ``aᵢ·(Cᵢ₊₁ − Cᵢ)``: how far camera-to-world ``poses`` (..., S, 4, 4) advance between
    consecutive ones along the optical axes ``axes`` (S, 3), given apart (the callers hold them fixed)."""
    return (axes[:-1] * (poses[..., 1:, :3, 3] - poses[..., :-1, :3, 3])).sum(-1)


def closing_residuals(poses: Tensor, axes: Tensor, metres: np.ndarray, unit: float) -> Tensor:
    """(..., S − 1) ``(unit·aᵢ·(Cᵢ₊₁ − Cᵢ) − (rᵢ − rᵢ₊₁)) / rᵢ₊₁`` at S consecutive range samples ``metres``
    (S,) (:func:`axial_advance`): how far the camera's advance misses the range's decrease, relative to
    the range."""
    r = torch.as_tensor(np.asarray(metres, dtype=np.float64), dtype=poses.dtype)
    return (unit * axial_advance(poses, axes) - (r[:-1] - r[1:])) / r[1:]


def huber(q: Tensor) -> Tensor:
    """``q²`` for ``|q| ≤ HUBER``, continued linearly (with the same slope) beyond."""
    a = q.abs()
    return torch.where(a <= HUBER, q * q, HUBER * (2 * a - HUBER))


def huber_weights(q: Tensor) -> Tensor:
    """IRLS weights of :func:`huber`: minimising ``Σ w·q²`` with them takes the same Gauss–Newton step."""
    return (HUBER / q.abs().clamp(min=HUBER)).to(q.dtype)


def meter_samples(data: EventData, why: str) -> tuple[np.ndarray, np.ndarray]:
    """The sequence's valid range samples (:func:`valid_samples`); ``why`` names what needs them, for the
    error when the sequence has no meter."""
    if data.ranges is None:
        raise ValueError(f"{why} needs the sequence's range meter (range.csv)")
    return valid_samples(*data.ranges)


def seed_unit(cfg: Config, data: EventData, t: np.ndarray, r: np.ndarray, why: str) -> float:
    """Metres per map unit as the seeding sets them: the map is seeded around ``gaussians.init_depth`` on
    the first camera's axis, so the meter's first reading (of ``t``, ``r``, at or after the first frame)
    is that depth in metres. ``why`` names the setting that needs it, for the error."""
    first = np.searchsorted(t, int(data.frames_us[0]))
    if cfg.gaussians.init_depth <= 0 or first == len(t):
        raise ValueError(
            f"{why} needs gaussians.init_depth > 0 (the seeding's depth on the first camera's axis, which "
            "the meter's first reading sets in metres) and a range sample at or after the first frame "
            f"({int(data.frames_us[0])} µs)"
        )
    return float(r[first]) / cfg.gaussians.init_depth


def meter_advance(cfg: Config, data: EventData, chunks: int) -> float:
    """Map units per chunk the camera advances along its optical axis over chunks ``0..chunks``, read
    from how fast the range meter closes there (pairs across which it jumps left out, :func:`meter_jumps`),
    at the seeding's unit (:func:`seed_unit`). Exact for a surface facing the camera; 0 without a steady
    pair in those chunks."""
    why = "init.search_meter_advance"
    t, r = meter_samples(data, why)
    unit = seed_unit(cfg, data, t, r, why)
    t0, t1 = int(data.frames_us[0]), int(data.frames_us[chunks])
    inside = (t >= t0) & (t <= t1)
    t, r = t[inside], r[inside]
    steady = ~meter_jumps(r)  # empty with fewer than two samples
    if not steady.any():
        return 0.0
    closed = float((r[:-1] - r[1:])[steady].sum())  # metres
    elapsed = float(np.diff(t)[steady].sum())  # µs
    return closed / elapsed * (t1 - t0) / chunks / unit


@dataclass(frozen=True)
class RangePrior:
    t_us: np.ndarray  # (S,) sample times, increasing
    ranges: np.ndarray  # (S,) metres, finite and positive
    min_alpha: float
    camera: Camera
    background: float
    seed_unit: float | None = None  # metres per map unit set by the seeding (the closing rate's u₀)

    @cached_property
    def jumps(self) -> np.ndarray:
        """(S − 1,) bool: the pairs the closing rate leaves out (:func:`meter_jumps`)."""
        return meter_jumps(self.ranges)

    @classmethod
    def for_run(cls, cfg: Config, data: EventData) -> RangePrior | None:
        """The prior of a run on ``data`` (None when ``scale.range_weight``, ``scale.rate_weight`` and
        ``init.search_range_weight`` are all 0)."""
        if cfg.scale.range_weight == 0 and cfg.scale.rate_weight == 0 and cfg.init.search_range_weight == 0:
            return None
        t, r = meter_samples(data, "a range weight > 0")
        unit = seed_unit(cfg, data, t, r, "scale.rate_weight > 0") if cfg.scale.rate_weight > 0 else None
        return cls(t, r, cfg.scale.min_alpha, data.camera, cfg.gaussians.background, unit)

    def samples(self, t_lo: int, t_hi: int, traj: Trajectory | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(t_us, metres)`` of the samples with ``t_lo <= t <= t_hi`` (and inside ``traj``'s knots)."""
        if traj is not None:
            t_lo, t_hi = max(t_lo, int(traj.t_us[0])), min(t_hi, int(traj.t_us[-1]))
        keep = (self.t_us >= t_lo) & (self.t_us <= t_hi)
        return self.t_us[keep], self.ranges[keep]

    def rate_samples(
        self, t_lo: int, t_hi: int, traj: Trajectory
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t_us, metres, steady)`` of the consecutive samples whose pairs end between ``t_lo`` and
        ``t_hi`` µs: those inside, and the one before them if ``traj`` reaches it (a chunk shorter than
        the meter's period holds one sample at most); ``steady`` (S − 1,) marks the pairs across which
        the meter does not jump (:attr:`jumps`)."""
        first, last = int(traj.t_us[0]), int(traj.t_us[-1])
        i0 = int(np.searchsorted(self.t_us, max(t_lo, first), "left"))
        i1 = int(np.searchsorted(self.t_us, min(t_hi, last), "right"))
        if 0 < i0 < i1 and self.t_us[i0 - 1] >= first:
            i0 -= 1
        return self.t_us[i0:i1], self.ranges[i0:i1], ~self.jumps[i0 : max(i0, i1 - 1)]

    def rate_penalty(self, traj: Trajectory, t_lo: int, t_hi: int) -> Tensor:
        """``mean(h(q))`` of the closing-rate residuals (:func:`closing_residuals`) of the pairs ending
        between ``t_lo`` and ``t_hi`` µs across which the meter does not jump, at the seeding's unit; 0
        when there is none."""
        t, metres, steady = self.rate_samples(t_lo, t_hi, traj)
        if not steady.any() or self.seed_unit is None:
            return torch.zeros(())
        poses = traj.pose_at(t)
        q = closing_residuals(poses, poses.detach()[:, :3, 2], metres, self.seed_unit)
        return huber(q[..., torch.from_numpy(steady)]).mean().float()

    @torch.no_grad()
    def unit(self, gaussians: Gaussians, traj: Trajectory) -> float | None:
        """Metres per map unit now: the median ``r / D̄`` over the covered samples the trajectory has
        reached (None if none is)."""
        t, metres = self.samples(int(traj.t_us[0]), int(traj.t_us[-1]))
        if not len(t):
            return None
        alpha, depth = principal_depth(gaussians, traj.viewmats_at(t), self.camera, self.background)
        covered = (alpha >= self.min_alpha).numpy()
        ratios = metres[covered] / depth.double().numpy()[covered]
        return float(np.median(ratios)) if len(ratios) else None

    def residuals(self, gaussians: Gaussians, viewmats: Tensor, metres: np.ndarray, unit: float) -> Tensor:
        """(V,) ``D̄ · unit / r − 1`` of views with ranges ``metres`` (V,), differentiable in the views
        only; NaN where the map does not cover the view's principal ray."""
        r = torch.from_numpy(np.asarray(metres, dtype=np.float64)).float()
        alpha, depth = principal_depth(gaussians, viewmats, self.camera, self.background)
        q = depth * unit / r - 1
        return torch.where(alpha >= self.min_alpha, q, torch.full_like(q, float("nan")))

    def penalty(
        self, gaussians: Gaussians, traj: Trajectory, t_lo: int, t_hi: int, unit: float | None
    ) -> Tensor:
        """``mean(h(q))`` over the used samples between ``t_lo`` and ``t_hi`` µs (and inside the
        trajectory); 0 when there is none or no unit yet."""
        t, metres = self.samples(t_lo, t_hi, traj)
        if len(t) == 0 or unit is None:
            return torch.zeros(())
        q = self.residuals(gaussians, traj.viewmats_at(t), metres, unit)
        used = ~torch.isnan(q)
        if not bool(used.any()):
            return torch.zeros(())
        return huber(q[used]).mean()

"""The continuous camera trajectory: camera-to-world SE(3) control knots at frame timestamps.

Parameterisation: each knot is ``T_k = B_k · Exp(δ_k)``, a fixed base ``B_k`` (float64 buffer) times a
trainable right (camera-frame) increment ``δ_k ∈ se(3)`` that starts at zero. Why:
- a camera-frame increment means the same thing at any position and heading, so one ``pose_lr`` fits
  every knot and every scene gauge (world-frame se(3) vectors, as in the reference, couple translation
  steps to the distance from the origin through the V(φ) Jacobian);
- ``δ`` stays small, where ``Exp`` is nearly linear and Adam's per-coordinate scaling is well
  conditioned; :meth:`Trajectory.rebase` folds ``δ`` into ``B`` after every stage (each stage builds a
  fresh optimizer, so no Adam state refers to the old ``δ``).
Knots that a stage must not move are masked out of ``δ`` (:meth:`Trajectory.set_trainable`), so they
get exactly zero gradient and Adam leaves them untouched.

Between knots ``i`` and ``i+1`` the pose at ``τ = (t − t_i)/(t_{i+1} − t_i)`` is the paper's eq. 12,
``T_i · Exp(τ · Log(T_i⁻¹ T_{i+1}))`` (``"geodesic"``), or the reference code's ``Exp((1−τ)·Log T_i +
τ·Log T_{i+1})`` (``"lerp"``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
from torch import Tensor

from evgs.slam.lie import project_se3, se3_exp, se3_inverse, se3_log

Interpolation = Literal["geodesic", "lerp"]
RIGID_TOL = 1e-12  # knots whose rotation is further from orthonormal are projected back onto SE(3)


def interpolate(t0: Tensor, t1: Tensor, tau: Tensor, method: Interpolation = "geodesic") -> Tensor:
    """Poses between (..., 4, 4) ``t0`` and ``t1`` at fractions (...,) ``tau`` (0 → t0, 1 → t1)."""
    if method == "geodesic":
        return t0 @ se3_exp(tau[..., None] * se3_log(se3_inverse(t0) @ t1))
    if method == "lerp":
        return se3_exp((1 - tau[..., None]) * se3_log(t0) + tau[..., None] * se3_log(t1))
    raise ValueError(f"unknown interpolation {method!r} (expected 'geodesic' or 'lerp')")


def constant_velocity(t_prev2: Tensor, t_prev: Tensor, ratio: float = 1.0) -> Tensor:
    """Predict the next knot from the last two: ``T_{k-1} · Exp(r · Log(T_{k-2}⁻¹ T_{k-1}))``.

    ``r`` = (t_k − t_{k−1}) / (t_{k−1} − t_{k−2}); for evenly spaced frames (r = 1) this is exactly the
    reference's ``T_{k-1} · T_{k-2}⁻¹ · T_{k-1}``.
    """
    rel = se3_inverse(t_prev2) @ t_prev
    return t_prev @ (rel if ratio == 1.0 else se3_exp(ratio * se3_log(rel)))


def scaled_motion(knots: Tensor, factor: float) -> Tensor:
    """``knots`` (K, 4, 4) with each one's motion from the first scaled: ``T_0 · Exp(f · Log(T_0⁻¹ T_k))``.
    For a constant velocity (an orbit, an approach) this is the same path at ``f`` times the speed."""
    rel = se3_log(se3_inverse(knots[:1]) @ knots)
    return knots[:1] @ se3_exp(factor * rel)


def random_knots(n: int, sigma: float, generator: torch.Generator) -> Tensor:
    """``n`` near-identity poses ``Exp(ξ)``, ``ξ ~ N(0, σ²)`` (the reference's initial knots)."""
    xi = torch.randn(n, 6, generator=generator, dtype=torch.float64) * sigma
    return se3_exp(xi)


TRANSLATION = torch.tensor([True, True, True, False, False, False])  # the (v, ω) increment's position half
KnotMotion = Literal["pose", "position", "rotation"]  # what a stage's trainable knots may change
MOTION_MASKS = {"pose": torch.ones(6, dtype=torch.bool), "position": TRANSLATION, "rotation": ~TRANSLATION}


class Trajectory(torch.nn.Module):
    """Knots ``T_wc`` (camera-to-world) at strictly increasing integer-µs timestamps."""

    def __init__(
        self, t_us: np.ndarray | Tensor, T_wc: np.ndarray | Tensor, method: Interpolation = "geodesic"
    ):
        super().__init__()
        t = torch.as_tensor(np.asarray(t_us), dtype=torch.int64)
        base = torch.as_tensor(np.asarray(T_wc), dtype=torch.float64)
        if t.ndim != 1 or base.shape != (len(t), 4, 4) or len(t) == 0:
            raise ValueError(
                f"trajectory: need K ≥ 1 timestamps and (K, 4, 4) poses, got {tuple(base.shape)}"
            )
        if torch.any(t[1:] <= t[:-1]):
            raise ValueError("trajectory: knot timestamps must be strictly increasing")
        if method not in ("geodesic", "lerp"):
            raise ValueError(f"unknown interpolation {method!r} (expected 'geodesic' or 'lerp')")
        self.method: Interpolation = method
        self.register_buffer("t_us", t)
        self.register_buffer("base", base.clone())
        # (K, 6): which coordinates of each knot's increment ``(v, ω)`` a stage optimises
        self.register_buffer("trainable", torch.ones(len(t), 6, dtype=torch.bool))
        self.delta = torch.nn.Parameter(torch.zeros(len(t), 6, dtype=torch.float64))

    def __len__(self) -> int:
        return len(self.t_us)

    def knots(self) -> Tensor:
        """(K, 4, 4) current knots, differentiable w.r.t. the trainable increments."""
        delta = torch.where(self.trainable, self.delta, torch.zeros_like(self.delta))
        return self.base @ se3_exp(delta)

    def set_trainable(self, indices: slice | list[int] | Tensor | None, moves: KnotMotion = "pose") -> None:
        """Only these knots (None = all) receive gradients; Python-style negative indices work. ``moves``
        "position": ``δ = (v, 0)`` translates a knot in its own frame and keeps its rotation; "rotation":
        ``δ = (0, ω)`` turns it about its own centre, which stays put."""
        mask = torch.zeros(len(self), 6, dtype=torch.bool)
        mask[slice(None) if indices is None else indices] = MOTION_MASKS[moves]
        self.trainable = mask

    @torch.no_grad()
    def rebase(self) -> None:
        """Fold the increments into the base poses and zero them (call between stages)."""
        self.base = project_se3(self.knots().detach(), RIGID_TOL)
        self.delta.zero_()

    def forward(self, t_us: Tensor | np.ndarray) -> Tensor:
        return self.pose_at(t_us)

    def pose_at(self, t_us: Tensor | np.ndarray, knots: Tensor | None = None) -> Tensor:
        """(M, 4, 4) float64 camera-to-world poses at integer-µs times inside the knot range; ``knots``
        (..., K, 4, 4) replaces the current knots (a pose solver's trial values; a batch of V sets gives
        (V, M, 4, 4) in one pass)."""
        t = torch.as_tensor(np.asarray(t_us), dtype=torch.int64).reshape(-1)
        lo, hi = int(self.t_us[0]), int(self.t_us[-1])
        outside = (t < lo) | (t > hi)
        if torch.any(outside):
            bad = int(t[outside][0])
            raise ValueError(f"trajectory: time {bad} µs is outside the knot range [{lo}, {hi}] µs")
        knots = self.knots() if knots is None else knots
        if len(self) == 1:
            return knots.expand(*knots.shape[:-3], len(t), 4, 4)
        seg = (torch.searchsorted(self.t_us, t, right=True) - 1).clamp(0, len(self) - 2)
        t0, t1 = self.t_us[seg], self.t_us[seg + 1]
        tau = (t - t0).to(torch.float64) / (t1 - t0).to(torch.float64)
        return interpolate(knots[..., seg, :, :], knots[..., seg + 1, :, :], tau, self.method)

    def viewmats_at(self, t_us: Tensor | np.ndarray) -> Tensor:
        """(M, 4, 4) float32 world-to-camera matrices, the rasterizer's ``viewmats``."""
        return se3_inverse(self.pose_at(t_us)).float()

    @torch.no_grad()
    def append(self, t_us: int, T_wc: Tensor | np.ndarray | None = None) -> None:
        """Add a knot after the last one; without a pose it is predicted by constant velocity (a single
        existing knot is repeated). The new knot is trainable; the mask of the others is kept. Call it
        between stages: it rebases, and ``delta`` becomes a new Parameter (build optimizers after)."""
        t_new = int(t_us)
        if t_new <= int(self.t_us[-1]):
            raise ValueError(
                f"trajectory: new knot at {t_new} µs is not after the last ({int(self.t_us[-1])} µs)"
            )
        knots = self.knots()
        if T_wc is not None:
            pose = torch.as_tensor(np.asarray(T_wc), dtype=torch.float64).reshape(4, 4)
        elif len(self) == 1:
            pose = knots[-1]
        else:
            ratio = (t_new - int(self.t_us[-1])) / int(self.t_us[-1] - self.t_us[-2])
            pose = constant_velocity(knots[-2], knots[-1], ratio)
        self.base = project_se3(torch.cat([knots, pose[None]]), RIGID_TOL)
        self.t_us = torch.cat([self.t_us, torch.tensor([t_new])])
        self.trainable = torch.cat([self.trainable, torch.ones(1, 6, dtype=torch.bool)])
        self.delta = torch.nn.Parameter(torch.zeros(len(self.t_us), 6, dtype=torch.float64))

    def acceleration_penalty(self, scene_scale: float) -> Tensor:
        """Mean squared change of the body-frame velocity ``Log(T_{k-1}⁻¹ T_k)`` between consecutive
        segments (translation in units of ``scene_scale``), per unit of time²: zero for constant
        velocity, the motion a spacecraft in free flight keeps between frames."""
        if len(self) < 3:
            return torch.zeros((), dtype=torch.float64)
        knots = self.knots()
        dt = (self.t_us[1:] - self.t_us[:-1]).to(torch.float64) * 1e-6
        vel = se3_log(se3_inverse(knots[:-1]) @ knots[1:]) / dt[:, None]
        vel = torch.cat([vel[:, :3] / scene_scale, vel[:, 3:]], 1)
        mid = 0.5 * (dt[1:] + dt[:-1])
        return (((vel[1:] - vel[:-1]) / mid[:, None]) ** 2).sum(1).mean()

    def poses_numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """``(t_us (K,), T_wc (K, 4, 4))`` of the current knots, for TUM export."""
        with torch.no_grad():
            return self.t_us.numpy().copy(), self.knots().numpy().copy()

    def state(self) -> dict[str, Tensor | str]:
        """Everything needed to rebuild the trajectory (checkpoints); the increments are folded in."""
        t, T = self.poses_numpy()
        return {"t_us": torch.from_numpy(t), "T_wc": torch.from_numpy(T), "method": self.method}

    @classmethod
    def from_state(cls, state: dict) -> Trajectory:
        return cls(state["t_us"], state["T_wc"], state["method"])

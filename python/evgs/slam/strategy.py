"""Densification and pruning with gsplat's "default strategy" semantics, plus new Gaussians from the
low-alpha pixels of a view.

Every edit goes through :func:`edit_rows`, which rebuilds each parameter as ``cat(p[keep], extra)`` and
applies the same row operation to the optimizer's per-element state (Adam's ``exp_avg``,
``exp_avg_sq``; zeros for new rows) and to any auxiliary per-Gaussian tensors, so parameters, moments
and statistics can never drift out of alignment.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from evgs.config import StrategyConfig
from evgs.data.sequence import Camera
from evgs.slam.gaussians import PARAM_NAMES, Gaussians, camera_rays, opacity_logit, quat_to_rotmat


def _find_group(optimizer: torch.optim.Optimizer, param: Tensor) -> tuple[dict, int]:
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is param:
                return group, i
    raise ValueError("strategy: a Gaussian parameter is not in the optimizer")


def edit_rows(
    gaussians: Gaussians,
    optimizer: torch.optim.Optimizer | None,
    keep: Tensor,
    extra: dict[str, Tensor] | None = None,
    aux: Sequence[Tensor] = (),
) -> list[Tensor]:
    """Keep rows ``keep`` (bool mask or indices) of every parameter, then append ``extra[name]`` rows.

    The optimizer's state tensors shaped like a parameter get the same rows (zeros for the appended
    ones) and the new Parameter replaces the old one in its group. ``aux`` per-Gaussian tensors are
    edited likewise and returned.
    """
    n_extra = 0 if extra is None else len(extra["means"])

    def rebuild(t: Tensor, rows: Tensor | None) -> Tensor:
        if rows is None:
            rows = torch.zeros((n_extra, *t.shape[1:]), dtype=t.dtype, device=t.device)
        return torch.cat([t[keep], rows.to(t.dtype)])

    for name in PARAM_NAMES:
        old = gaussians.params[name]
        new = torch.nn.Parameter(rebuild(old.detach(), None if extra is None else extra[name]))
        if optimizer is not None:
            group, i = _find_group(optimizer, old)
            state = optimizer.state.pop(old, {})
            for key, value in state.items():
                if torch.is_tensor(value) and value.shape == old.shape:
                    state[key] = rebuild(value, None)
            group["params"][i] = new
            if state:
                optimizer.state[new] = state
        gaussians.params[name] = new
    return [rebuild(a, None) for a in aux]


def duplicate(gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, mask: Tensor) -> None:
    """Clone the selected Gaussians (appended at the end, fresh optimizer state)."""
    extra = {k: gaussians.params[k].detach()[mask] for k in PARAM_NAMES}
    edit_rows(gaussians, optimizer, torch.ones_like(mask), extra)


def split(
    gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, mask: Tensor, generator: torch.Generator
) -> None:
    """Replace each selected Gaussian by two drawn from its own distribution, 1.6× smaller (3DGS)."""
    p = {k: gaussians.params[k].detach()[mask] for k in PARAM_NAMES}
    scales = torch.exp(p["log_scales"])
    rot = quat_to_rotmat(p["quats"])
    noise = torch.randn((2, len(scales), 3), generator=generator, dtype=scales.dtype)
    offsets = torch.einsum("nij,bnj->bni", rot, scales * noise)
    extra = {k: v.repeat(2, *[1] * (v.ndim - 1)) for k, v in p.items()}
    extra["means"] = (p["means"] + offsets).reshape(-1, 3)
    extra["log_scales"] = torch.log(scales / 1.6).repeat(2, 1)
    edit_rows(gaussians, optimizer, ~mask, extra)


def remove(gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, mask: Tensor) -> None:
    edit_rows(gaussians, optimizer, ~mask)


@torch.no_grad()
def reset_opacity(gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, value: float) -> None:
    """Clamp opacities to at most ``value`` and clear their Adam moments (gsplat's reset)."""
    logits = gaussians.params["opacity_logits"]
    logits.clamp_(max=opacity_logit(value))
    if optimizer is not None:
        for v in optimizer.state.get(logits, {}).values():
            if torch.is_tensor(v) and v.shape == logits.shape:
                v.zero_()


@dataclass
class RefineReport:
    cloned: int = 0
    split: int = 0
    pruned: int = 0
    reset: bool = False


@dataclass
class DefaultStrategy:
    """Accumulates per-Gaussian image-space gradients and visibility; grows, prunes and resets on the
    configured schedule. ``scene_scale`` turns ``grow_scale3d``/``prune_scale3d`` into world units."""

    cfg: StrategyConfig
    scene_scale: float
    grad2d: Tensor = field(default_factory=lambda: torch.zeros(0))
    count: Tensor = field(default_factory=lambda: torch.zeros(0))

    def _ensure(self, n: int) -> None:
        """Start the statistics on first use; refuse to silently drop them if they are out of step."""
        if len(self.grad2d) == 0:
            self.grad2d, self.count = torch.zeros(n), torch.zeros(n)
        elif len(self.grad2d) != n:
            raise ValueError(
                f"strategy: statistics cover {len(self.grad2d)} Gaussians but there are {n}; "
                "add or remove Gaussians through DefaultStrategy.add/remove"
            )

    def accumulate(self, grad2d_norm: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Add one step's (B, N) per-view ‖∂L/∂(u,v)‖ (pixels) for the visible Gaussians (radii > 0).

        gsplat measures the gradient w.r.t. normalised device coordinates times the number of views
        (its loss averages over them), i.e. ``(W/2·g_u, H/2·g_v)·B``; from the norm alone this is
        ``‖g‖·½√(WH)·B``, exact for square images and within √(W/H) otherwise, which keeps
        ``grow_grad2d`` on gsplat's scale.
        """
        self._ensure(grad2d_norm.shape[1])
        visible = radii > 0
        scale = 0.5 * math.sqrt(width * height) * grad2d_norm.shape[0]
        self.grad2d += (grad2d_norm.detach().float() * scale * visible).sum(0)
        self.count += visible.sum(0).float()

    def step(
        self,
        gaussians: Gaussians,
        optimizer: torch.optim.Optimizer | None,
        step: int,
        generator: torch.Generator,
    ) -> RefineReport:
        """Call after ``optimizer.step()`` of iteration ``step`` (counted from 0 within a stage)."""
        cfg, report = self.cfg, RefineReport()
        self._ensure(len(gaussians))
        if cfg.refine_start < step < cfg.refine_stop and step % cfg.refine_every == 0:
            with torch.no_grad():
                grads = self.grad2d / self.count.clamp(min=1)
                high = grads > cfg.grow_grad2d
                small = gaussians.scales().max(-1).values <= cfg.grow_scale3d * self.scene_scale
                clone_mask, split_mask = high & small, high & ~small
                duplicate(gaussians, optimizer, clone_mask)
                split_mask = torch.cat([split_mask, torch.zeros(int(clone_mask.sum()), dtype=torch.bool)])
                split(gaussians, optimizer, split_mask, generator)
                prune = gaussians.opacities() < cfg.prune_opa
                if step > cfg.prune_scale3d_start:
                    prune |= gaussians.scales().max(-1).values > cfg.prune_scale3d * self.scene_scale
                remove(gaussians, optimizer, prune)
            report = RefineReport(int(clone_mask.sum()), int(split_mask.sum()), int(prune.sum()))
            self.grad2d, self.count = torch.zeros(len(gaussians)), torch.zeros(len(gaussians))
        if cfg.reset_every > 0 and step > 0 and step % cfg.reset_every == 0:
            reset_opacity(gaussians, optimizer, cfg.reset_opacity)
            report.reset = True
        return report

    def remove(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, mask: Tensor) -> None:
        """Remove Gaussians outside the schedule (guards), keeping the statistics aligned."""
        self._ensure(len(gaussians))
        self.grad2d, self.count = edit_rows(gaussians, optimizer, ~mask, aux=(self.grad2d, self.count))

    def add(
        self, gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, extra: dict[str, Tensor]
    ) -> None:
        """Append new Gaussians (e.g. from :func:`gaussians_from_view`) with zero statistics."""
        self._ensure(len(gaussians))
        keep = torch.ones(len(gaussians), dtype=torch.bool)
        self.grad2d, self.count = edit_rows(gaussians, optimizer, keep, extra, aux=(self.grad2d, self.count))


def gaussians_from_view(
    alpha: Tensor,
    T_wc: Tensor,
    camera: Camera,
    depth: float,
    *,
    max_new: int,
    max_alpha: float,
    opacity: float,
    color: float,
    generator: torch.Generator,
    events: Tensor | None = None,
    event_threshold: float = 0.0,
) -> dict[str, Tensor]:
    """New Gaussians back-projected at ``depth`` through up to ``max_new`` random pixels of the view
    whose rendered alpha is below ``max_alpha`` (and, given ``events``, whose |E| > ``event_threshold``).

    Each is isotropic with the spacing of the chosen pixels at that depth as its scale, so together
    they tile the uncovered area without large overlaps.
    """
    candidates = alpha < max_alpha
    if events is not None:
        candidates &= events.abs() > event_threshold
    rows, cols = torch.nonzero(candidates, as_tuple=True)
    n = min(max_new, len(rows))
    pick = torch.randperm(len(rows), generator=generator)[:n]
    u = cols[pick].double()  # pixel centres (OpenCV, as the camera)
    v = rows[pick].double()
    rays = camera_rays(u, v, camera)
    T = torch.as_tensor(T_wc, dtype=torch.float64)
    means = (rays * depth) @ T[:3, :3].T + T[:3, 3]
    spacing_px = math.sqrt(len(rows) / max(n, 1))
    log_scale = float(np.log(spacing_px * depth / math.sqrt(camera.fx * camera.fy)))
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    return {
        "means": means.float(),
        "log_scales": torch.full((n, 3), log_scale),
        "quats": quats,
        "opacity_logits": torch.full((n,), opacity_logit(opacity)),
        "colors": torch.full((n, 1), float(color)),
    }

"""Torch implementations of the loss terms the Rust core computes for :mod:`evgs.slam.loss` (the SSIM
term and the relief prior): plain autograd code, the float64 references the tests check the kernels'
values and gradients against, and the peers ``benches/loss_bench.py`` times them beside."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from evgs.slam.depth import mean_depth
from evgs.slam.loss import gaussian_window


def blur_valid(x: Tensor, k: Tensor) -> Tensor:
    """The separable "valid" correlation of the last two axes with ``k``, by two 1-D conv2d."""
    flat = x.reshape(-1, 1, *x.shape[-2:])
    out = F.conv2d(F.conv2d(flat, k.view(1, 1, 1, -1)), k.view(1, 1, -1, 1))
    return out.reshape(*x.shape[:-2], *out.shape[-2:])


def ssim(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5, data_range: float = 1.0) -> Tensor:
    """:func:`evgs.slam.loss.ssim` in torch: mean SSIM per image of (B, H, W) batches."""
    k = gaussian_window(window, sigma, a.dtype)
    mu_a, mu_b, aa, bb, ab = blur_valid(torch.stack([a, b, a * a, b * b, a * b], 1), k).unbind(1)
    var_a, var_b, cov = aa - mu_a**2, bb - mu_b**2, ab - mu_a * mu_b
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return s.mean(dim=(-2, -1))


def depth_variation(depth: Tensor, alpha: Tensor, min_alpha: float = 0.5) -> Tensor:
    """:func:`evgs.slam.loss.depth_variation` in torch."""
    mean, opaque = mean_depth(depth, alpha, min_alpha)
    if not bool(opaque.any()):
        return depth.sum() * 0
    mean = mean / mean[opaque].median()
    dx = (mean[..., :, 1:] - mean[..., :, :-1]).abs()[opaque[..., :, 1:] & opaque[..., :, :-1]]
    dy = (mean[..., 1:, :] - mean[..., :-1, :]).abs()[opaque[..., 1:, :] & opaque[..., :-1, :]]
    return sum((d.mean() for d in (dx, dy) if d.numel()), depth.sum() * 0)

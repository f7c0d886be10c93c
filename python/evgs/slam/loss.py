"""The event loss (paper eq. 8–11) on batches of rendered gray images (B, H, W) in [0, 1].

``Ê = L(Î_end) − L(Î_start)`` with ``L = log(I + eps)`` (paper eq. 9) or the reference's
``linlog(255·I)``; ``L = (1−λ)·L_event(E, Ê) + λ·(1 − SSIM(Î_start, Î_end))``, with ``L_event`` the L1
(paper eq. 10) or squared (reference code) error, averaged over the valid pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from evgs import _core
from evgs.config import LossConfig
from evgs.slam.depth import mean_depth


def linlog(x: Tensor, threshold: float = 20.0) -> Tensor:
    """``ln x`` above ``threshold``, the line through the origin meeting it (``x·ln(t)/t``) below.

    Keeps the log response finite and bounded in slope on the black background.
    """
    safe = torch.clamp(x, min=threshold)  # the log branch never sees small values (nor their gradient)
    return torch.where(x < threshold, x * (math.log(threshold) / threshold), torch.log(safe))


def log_intensity(img: Tensor, cfg: LossConfig) -> Tensor:
    if cfg.log_mode == "log":
        return torch.log(img + cfg.log_eps)
    return linlog(255.0 * img, cfg.linlog_threshold)


def predicted_events(start: Tensor, end: Tensor, cfg: LossConfig) -> Tensor:
    """``Ê``: the log-intensity change between two renders of the same shape."""
    return log_intensity(end, cfg) - log_intensity(start, cfg)


def _gaussian_kernel(size: int, sigma: float, dtype: torch.dtype) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    k = torch.exp(-(x**2) / (2 * sigma**2))
    return (k / k.sum()).to(dtype)


def _correlate_valid(x: Tensor, k: Tensor) -> Tensor:
    """Separable "valid" correlation of the last two axes with the 1-D kernel ``k`` (no autograd), in
    the Rust core (``evgs._core.correlate_valid_*``): the same arithmetic as torch's ``mul`` then
    ``add_(alpha=k[i])`` per tap, bit for bit, without 44 small ops' dispatch and OpenMP barriers, which
    took a quarter of the motion search's time on two cores (docs/ablations.md §68)."""
    *lead, height, width = x.shape
    correlate = {torch.float32: _core.correlate_valid_f32, torch.float64: _core.correlate_valid_f64}
    if x.dtype not in correlate or x.device.type != "cpu":
        raise ValueError(f"blur: CPU float32 or float64 tensors only, got {x.dtype} on {x.device}")
    planes = math.prod(lead)
    out = correlate[x.dtype](
        x.detach().contiguous().view(-1).numpy(),
        planes,
        height,
        width,
        k.detach().to(device="cpu", dtype=x.dtype).contiguous().numpy(),
    )
    return torch.from_numpy(out).view(*lead, height - len(k) + 1, width - len(k) + 1)


class _BlurValid(torch.autograd.Function):
    """``_correlate_valid`` with its adjoint as the backward (a full correlation with the flipped
    kernel). On the CPU, torch's conv2d with a 1×11 single-channel kernel, and above all its backward,
    cost ~20× more than fused multiply-adds, and torch's own loop of them 2.4× the Rust core's."""

    @staticmethod
    def forward(ctx, x: Tensor, k: Tensor) -> Tensor:
        ctx.save_for_backward(k)
        return _correlate_valid(x, k)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:
        (k,) = ctx.saved_tensors
        m = len(k) - 1
        return _correlate_valid(F.pad(grad, (m, m, m, m)), k.flip(0)), None


def _blur_valid(x: Tensor, k: Tensor) -> Tensor:
    return _BlurValid.apply(x, k)


def ssim(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5, data_range: float = 1.0) -> Tensor:
    """Mean SSIM per image of (B, H, W) batches, Gaussian-weighted, population (co)variances.

    Only windows that lie wholly inside the image count (a "valid" convolution): no padding values
    leak into the statistics. This equals scikit-image's ``structural_similarity(gaussian_weights=True,
    sigma=σ, use_sample_covariance=False)``, which crops the same border before averaging.
    """
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(
            f"ssim: need two (B, H, W) tensors of one shape, got {tuple(a.shape)}, {tuple(b.shape)}"
        )
    if min(a.shape[-2:]) < window:
        raise ValueError(f"ssim: images {tuple(a.shape[-2:])} are smaller than the {window}-px window")
    k = _gaussian_kernel(window, sigma, a.dtype).to(a.device)
    x = _blur_valid(torch.stack([a, b, a * a, b * b, a * b], 1), k)
    mu_a, mu_b, aa, bb, ab = x.unbind(1)
    var_a, var_b, cov = aa - mu_a**2, bb - mu_b**2, ab - mu_a * mu_b
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return s.mean(dim=(-2, -1))


def valid_mask(
    alpha_start: Tensor, alpha_end: Tensor, border: int = 0, min_alpha: float | None = None
) -> Tensor:
    """(B, H, W) bool: the reference tracking's mask — no ``border``-px frame, and (if ``min_alpha``)
    only pixels whose rendered alpha exceeds ``min_alpha`` at both ends of the window."""
    mask = torch.ones_like(alpha_start, dtype=torch.bool)
    if border > 0:
        mask[..., :border, :] = False
        mask[..., -border:, :] = False
        mask[..., :, :border] = False
        mask[..., :, -border:] = False
    if min_alpha is not None:
        mask &= (alpha_start > min_alpha) & (alpha_end > min_alpha)
    return mask


def event_mask(events: Tensor, threshold: float) -> Tensor:
    """Pixels whose accumulated event value exceeds ``threshold`` in magnitude."""
    return events.abs() > threshold


def pointwise_error(diff: Tensor, kind: str) -> Tensor:
    """The per-pixel event error: ``|E − Ê|`` for ``"l1"`` (paper eq. 10), its square for ``"mse"``."""
    return diff.abs() if kind == "l1" else diff * diff


def total_variation(img: Tensor) -> Tensor:
    """Mean anisotropic total variation ``|∂x I| + |∂y I|`` of (B, H, W) images."""
    dx = (img[..., :, 1:] - img[..., :, :-1]).abs().mean()
    dy = (img[..., 1:, :] - img[..., :-1, :]).abs().mean()
    return dx + dy


def depth_variation(depth: Tensor, alpha: Tensor, min_alpha: float = 0.5) -> Tensor:
    """Mean ``|∂x D̄| + |∂y D̄|`` of the mean depth ``D̄ = D / α`` (B, H, W), relative to its median, over
    neighbouring pixels that are both opaque (``α > min_alpha``); 0 where none are.

    A prior on the map's relief (``loss.depth_tv``). From a narrow baseline the events fix a target's
    outline, not its relief, and a map free to put each Gaussian at any depth predicts parallax the
    next views do not show; tracking on it takes too short a step (the bas-relief trade of turn
    against depth, docs/ablations.md §14, §35). Relative, so the map's arbitrary scale does not weigh;
    L1, so a true step in depth (a panel's edge in front of the bus) costs only its height.
    """
    mean, opaque = mean_depth(depth, alpha, min_alpha)
    if not bool(opaque.any()):
        return depth.sum() * 0
    # the median of this very tensor, not median_depth's own copy: one graph, so the gradient's sums run
    # in one order (a last-bit change here turns the default run's search to another motion, §42)
    mean = mean / mean[opaque].median()
    dx = (mean[..., :, 1:] - mean[..., :, :-1]).abs()[opaque[..., :, 1:] & opaque[..., :, :-1]]
    dy = (mean[..., 1:, :] - mean[..., :-1, :]).abs()[opaque[..., 1:, :] & opaque[..., :-1, :]]
    return sum((d.mean() for d in (dx, dy) if d.numel()), depth.sum() * 0)


@dataclass(frozen=True)
class LossTerms:
    total: Tensor
    event: Tensor
    ssim: Tensor  # the SSIM term ``1 − SSIM``, averaged over the batch


def event_term(
    events: Tensor, start: Tensor, end: Tensor, cfg: LossConfig, mask: Tensor | None = None
) -> Tensor:
    """``L_event`` of eq. 8: the pointwise error between the measured event frame ``E`` (B, H, W) and the
    one the renders ``start``/``end`` predict. ``mask`` (B, H, W) bool selects the pixels (None = all);
    ``cfg.event_mask_threshold ≥ 0`` further restricts them to pixels with events. A batch with no valid
    pixel gives 0."""
    if not (events.shape == start.shape == end.shape) or events.ndim != 3:
        raise ValueError(
            f"event term: events/start/end must be (B, H, W) of one shape, got "
            f"{tuple(events.shape)}, {tuple(start.shape)}, {tuple(end.shape)}"
        )
    diff = events - predicted_events(start, end, cfg)
    err = pointwise_error(diff, cfg.event_loss)
    if cfg.event_mask_threshold >= 0:
        m = event_mask(events, cfg.event_mask_threshold)
        mask = m if mask is None else mask & m
    if mask is None:
        return err.mean()
    w = mask.to(err.dtype)
    return (err * w).sum() / w.sum().clamp(min=1.0)


def event_loss(
    events: Tensor, start: Tensor, end: Tensor, cfg: LossConfig, mask: Tensor | None = None
) -> LossTerms:
    """Eq. 8: ``(1−λ)·L_event + λ·(1 − SSIM(start, end))``, the event term by :func:`event_term` (the
    same arguments)."""
    l_event = event_term(events, start, end, cfg, mask)
    l_ssim = (1 - ssim(start, end, cfg.ssim_window, cfg.ssim_sigma)).mean()
    lam = cfg.lambda_ssim
    return LossTerms((1 - lam) * l_event + lam * l_ssim, l_event, l_ssim)

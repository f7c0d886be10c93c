"""The event loss (paper eq. 8–11) on batches of rendered gray images (B, H, W) in [0, 1].

``Ê = L(Î_end) − L(Î_start)`` with ``L = log(I + eps)`` (paper eq. 9) or the reference's
``linlog(255·I)``; ``L = (1−λ)·L_event(E, Ê) + λ·(1 − SSIM(Î_start, Î_end))``, with ``L_event`` the L1
(paper eq. 10) or squared (reference code) error, averaged over the valid pixels. The SSIM term and the
relief prior on the rendered depth (``loss.depth_tv``) run in the Rust core, their gradients in the same
pass (their torch form, the tests' reference: :mod:`evgs.slam.loss_torch`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from evgs import _core
from evgs.config import LossConfig


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


def gaussian_window(size: int, sigma: float, dtype: torch.dtype) -> Tensor:
    """The SSIM window's normalised 1-D Gaussian taps."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    k = torch.exp(-(x**2) / (2 * sigma**2))
    return (k / k.sum()).to(dtype)


def _numpy(t: Tensor):
    """A flat numpy view of ``t``'s values (a copy only if it is not contiguous)."""
    return t.detach().contiguous().view(-1).numpy()


def _kernel(kind: str, *tensors: Tensor):
    """The Rust kernel ``_core.<kind>_f32`` or ``_f64`` for the tensors' common dtype."""
    dtype = tensors[0].dtype
    if dtype not in (torch.float32, torch.float64) or any(
        t.dtype != dtype or t.device.type != "cpu" for t in tensors
    ):
        got = ", ".join(f"{t.dtype} on {t.device}" for t in tensors)
        raise ValueError(f"{kind}: CPU float32 or float64 tensors of one dtype only, got {got}")
    return getattr(_core, f"{kind}_{'f32' if dtype == torch.float32 else 'f64'}")


class _Ssim(torch.autograd.Function):
    """Mean SSIM per image by the Rust core (``src/loss/ssim.rs``), which computes the gradient in the
    same pass when one is needed: torch spent 36 ms on a 640×480 pair's SSIM and its autograd, most of
    it in the dispatch of about a hundred small element-wise ops (docs/ablations.md §81)."""

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, k: Tensor, c1: float, c2: float) -> Tensor:
        with_grad = bool(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        values, grads = _kernel("ssim", a, b, k)(
            _numpy(a), _numpy(b), tuple(a.shape), _numpy(k), c1, c2, with_grad
        )
        if grads is not None:
            ctx.save_for_backward(*(torch.from_numpy(g).view(a.shape) for g in grads))
        return torch.from_numpy(values)

    @staticmethod
    def backward(ctx, grad: Tensor):
        ga, gb = ctx.saved_tensors
        g = grad[:, None, None]
        return g * ga, g * gb, None, None, None


def ssim(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5, data_range: float = 1.0) -> Tensor:
    """Mean SSIM per image of (B, H, W) batches, Gaussian-weighted, population (co)variances.

    Only windows that lie wholly inside the image count (a "valid" convolution): no padding values
    leak into the statistics. This equals scikit-image's ``structural_similarity(gaussian_weights=True,
    sigma=σ, use_sample_covariance=False)``, which crops the same border before averaging.
    Differentiable in ``a`` and ``b`` (CPU float32 or float64).
    """
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(
            f"ssim: need two (B, H, W) tensors of one shape, got {tuple(a.shape)}, {tuple(b.shape)}"
        )
    if min(a.shape[-2:]) < window:
        raise ValueError(f"ssim: images {tuple(a.shape[-2:])} are smaller than the {window}-px window")
    k = gaussian_window(window, sigma, a.dtype)
    return _Ssim.apply(a, b, k, (0.01 * data_range) ** 2, (0.03 * data_range) ** 2)


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


class _DepthVariation(torch.autograd.Function):
    """The relief prior by the Rust core (``src/loss/relief.rs``), its gradient in the same pass: in
    torch its boolean indexing and median cost 43 ms per 640×480 pair of views (docs/ablations.md §81)."""

    @staticmethod
    def forward(ctx, depth: Tensor, alpha: Tensor, min_alpha: float) -> Tensor:
        with_grad = bool(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        value, grads = _kernel("depth_variation", depth, alpha)(
            _numpy(depth), _numpy(alpha), tuple(depth.shape), min_alpha, with_grad
        )
        if grads is not None:
            ctx.save_for_backward(*(torch.from_numpy(g).view(depth.shape) for g in grads))
        return torch.tensor(value, dtype=depth.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):
        gd, ga = ctx.saved_tensors
        return grad * gd, grad * ga, None


def depth_variation(depth: Tensor, alpha: Tensor, min_alpha: float = 0.5) -> Tensor:
    """Mean ``|∂x D̄| + |∂y D̄|`` of the mean depth ``D̄ = D / α`` (B, H, W), relative to its median over
    the batch's opaque pixels (``α > min_alpha``), over neighbouring pixels that are both opaque; 0 where
    none are. Differentiable in ``depth`` and ``alpha`` (CPU float32 or float64).

    A prior on the map's relief (``loss.depth_tv``). From a narrow baseline the events fix a target's
    outline, not its relief, and a map free to put each Gaussian at any depth predicts parallax the
    next views do not show; tracking on it takes too short a step (the bas-relief trade of turn
    against depth, docs/ablations.md §14, §35). Relative, so the map's arbitrary scale does not weigh;
    L1, so a true step in depth (a panel's edge in front of the bus) costs only its height.
    """
    if depth.shape != alpha.shape or depth.ndim != 3:
        raise ValueError(
            f"depth variation: need depth and alpha (B, H, W) of one shape, got {tuple(depth.shape)}, "
            f"{tuple(alpha.shape)}"
        )
    return _DepthVariation.apply(depth, alpha, min_alpha)


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

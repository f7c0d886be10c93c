"""The rendered mean depth ``D̄ = D / α`` over the opaque pixels, which the relief prior makes scale-free by
its median (:func:`evgs.slam.loss.depth_variation`), and that median as a number: the view's depth, at
which new Gaussians are back-projected (:func:`evgs.slam.stages.add_gaussians_from_newest_view`)."""

from __future__ import annotations

from torch import Tensor


def mean_depth(depth: Tensor, alpha: Tensor, min_alpha: float = 0.5) -> tuple[Tensor, Tensor]:
    """``(D̄, opaque)``: the mean depth ``D / α`` (α clamped at ``min_alpha``, so transparent pixels stay
    finite and carry no gradient through α) and the mask of opaque pixels ``α > min_alpha``."""
    return depth / alpha.clamp(min=min_alpha), alpha > min_alpha


def median_depth(depth: Tensor, alpha: Tensor, min_alpha: float = 0.5) -> float | None:
    """Median mean depth over the opaque pixels, or None when no pixel is opaque."""
    mean, opaque = mean_depth(depth, alpha, min_alpha)
    if not bool(opaque.any()):
        return None
    return float(mean[opaque].median())

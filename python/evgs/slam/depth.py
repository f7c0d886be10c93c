"""The rendered mean depth ``D̄ = D / α`` and its median over the opaque pixels: the view's depth scale, which
the relief prior divides by (:func:`evgs.slam.loss.depth_variation`, scale-free) and new Gaussians are
back-projected at (:func:`evgs.slam.stages.add_gaussians_from_newest_view`)."""

from __future__ import annotations

from torch import Tensor


def mean_depth(depth: Tensor, alpha: Tensor, min_alpha: float = 0.5) -> tuple[Tensor, Tensor]:
    """``(D̄, opaque)``: the mean depth ``D / α`` (α clamped at ``min_alpha``, so transparent pixels stay
    finite and carry no gradient through α) and the mask of opaque pixels ``α > min_alpha``."""
    return depth / alpha.clamp(min=min_alpha), alpha > min_alpha


def median_depth(depth: Tensor, alpha: Tensor, min_alpha: float = 0.5) -> Tensor | None:
    """Median mean depth over the opaque pixels (differentiable), or None when no pixel is opaque."""
    mean, opaque = mean_depth(depth, alpha, min_alpha)
    if not bool(opaque.any()):
        return None
    return mean[opaque].median()

"""Guards against the two failure modes the paper reports (§5.5).

Brightness drift: the event term compares log-intensity *differences*, which do not change when every
intensity is scaled (``log kI₁ − log kI₀ = log I₁ − log I₀``), so the overall brightness is unobserved
and wanders, pushed further by opacity resets. Guards: colours are clamped to ``[0, max_color]``, the
opacity reset is off by default (``strategy.reset_every = 0``), and :class:`BrightnessAnchor` pins the
scene's surface brightness (alpha-weighted mean rendered colour — view independent for gray,
view-independent Gaussians) to its value after initialisation.

Blockers: Gaussians placed just in front of a camera project to huge, opaque discs that explain any
event frame by occlusion. :func:`blocker_mask` flags those whose centre is closer than a margin in front
of a recent camera and inside its image, or whose opaque footprint covers a large part of the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evgs.data.sequence import Camera
from evgs.slam.gaussians import Gaussians


@torch.no_grad()
def clamp_colors_(gaussians: Gaussians, max_color: float) -> None:
    """Project the gray colours onto ``[0, max_color]`` (call after every optimizer step)."""
    gaussians.params["colors"].clamp_(0.0, max_color)


def surface_brightness(color: Tensor, alpha: Tensor) -> Tensor:
    """``Σ I / Σ V`` over a batch of renders on a black background: the mean colour of what is seen."""
    return color.sum() / alpha.sum().clamp(min=1e-6)


@dataclass
class BrightnessAnchor:
    """Quadratic penalty on the relative change of :func:`surface_brightness` from a reference."""

    weight: float
    reference: float | None = None

    def set_reference(self, color: Tensor, alpha: Tensor) -> None:
        self.reference = float(surface_brightness(color.detach(), alpha.detach()))

    def penalty(self, color: Tensor, alpha: Tensor) -> Tensor:
        """``w·((b − b₀)/b₀)²``; zero while no reference is set or the guard is off."""
        if self.weight == 0 or self.reference is None or self.reference <= 0:
            return color.new_zeros(())
        rel = surface_brightness(color, alpha) / self.reference - 1
        return self.weight * rel * rel


@torch.no_grad()
def near_camera_mask(means: Tensor, T_wc: Tensor, camera: Camera, margin: float) -> Tensor:
    """(N,) True for Gaussians whose centre lies within ``margin`` in front of any of the (V, 4, 4)
    camera-to-world poses and projects inside that camera's image."""
    T = T_wc.to(means.dtype)
    rot, trans = T[:, :3, :3], T[:, :3, 3]
    p = torch.einsum("vji,vnj->vni", rot, means[None] - trans[:, None])  # Rᵀ(μ − t), camera frame
    z = p[..., 2]
    zs = torch.where(z > 0, z, torch.ones_like(z))
    u = camera.fx * p[..., 0] / zs + camera.cx
    v = camera.fy * p[..., 1] / zs + camera.cy
    # The image spans [-0.5, size - 0.5) with OpenCV's pixel centres at integers.
    inside = (u >= -0.5) & (u < camera.width - 0.5) & (v >= -0.5) & (v < camera.height - 0.5)
    return ((z > 0) & (z < margin) & inside).any(0)


@torch.no_grad()
def large_footprint_mask(
    radii: Tensor, opacities: Tensor, camera: Camera, max_fraction: float, min_opacity: float
) -> Tensor:
    """(N,) True for Gaussians more opaque than ``min_opacity`` whose screen radius in any of the
    (B, N) views exceeds ``max_fraction`` of the smaller image side."""
    limit = max_fraction * min(camera.width, camera.height)
    return (radii.max(0).values > limit) & (opacities > min_opacity)


@torch.no_grad()
def blocker_mask(
    gaussians: Gaussians,
    T_wc: Tensor,
    camera: Camera,
    *,
    near_margin: float,
    radii: Tensor | None = None,
    max_footprint: float = 1.0,
    footprint_min_opacity: float = 1.0,
) -> Tensor:
    """Union of :func:`near_camera_mask` (recent poses ``T_wc``) and, given the last render's ``radii``,
    :func:`large_footprint_mask`; prune the result with ``DefaultStrategy.remove``."""
    mask = near_camera_mask(gaussians.params["means"].detach(), T_wc, camera, near_margin)
    if radii is not None:
        mask |= large_footprint_mask(
            radii, gaussians.opacities(), camera, max_footprint, footprint_min_opacity
        )
    return mask

"""Differentiable Gaussian rendering on the CPU: a ``torch.autograd.Function`` over the Rust rasterizer.

Conventions (``/work/shared/design/RASTER_MATH.md``, gsplat semantics): ``viewmats`` are world-to-camera
4×4 matrices with OpenCV axes; quaternions ``(w, x, y, z)``, normalised inside; opacities already
activated. ``Camera`` intrinsics follow OpenCV, as every calibration, the simulator and the event
undistortion do: pixel ``(i, j)``'s centre is at ``(i, j)``. The Rust kernels keep gsplat's grid (pixel
``(i, j)`` sampled at ``(i + 0.5, j + 0.5)``), so :func:`raster_camera` moves the principal point by half a
pixel on the way in; without it every render sits half a pixel off the events. Inputs are used zero-copy
when they are contiguous float32 CPU tensors; the GIL is released during forward and backward, and the
forward state (tile lists, final transmittance) is kept in Rust for the backward pass.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from evgs import _core
from evgs.data.sequence import Camera

__all__ = ["PoseJvp", "RenderResult", "raster_camera", "render", "render_pose_jvp"]


class _Sink:
    """What the autograd function reports back beside its outputs."""

    forward_evaluations: int = 0
    backward_evaluations: int = 0
    grad2d: Tensor | None = None  # (B, N) ‖∂L/∂(u, v)‖, set by the backward pass


@dataclass
class RenderResult:
    color: Tensor  # (B, H, W, C)
    depth: Tensor  # (B, H, W) un-normalised expected depth D; D / alpha = mean depth
    alpha: Tensor  # (B, H, W) accumulated opacity V
    radii: Tensor  # (B, N) int32 screen radius in px, 0 = culled
    _sink: _Sink = field(default_factory=_Sink, repr=False)

    @property
    def forward_evaluations(self) -> int:
        """Pixel–Gaussian pairs evaluated by the forward pass (see ``raster::Forward::evaluations``)."""
        return self._sink.forward_evaluations

    @property
    def backward_evaluations(self) -> int:
        """Pixel–Gaussian pairs evaluated by the backward pass (0 before it ran)."""
        return self._sink.backward_evaluations

    def grad2d_norm(self) -> Tensor | None:
        """(B, N) norm of the image-space mean gradient per view, after ``backward()`` (else None)."""
        return self._sink.grad2d


def raster_camera(camera: Camera) -> Camera:
    """``camera`` (OpenCV: pixel centres at integers) in the rasterizer's convention (pixel centres at
    half-integers): the same rays through the same pixels."""
    return replace(camera, cx=camera.cx + 0.5, cy=camera.cy + 0.5)


def _flat(t: Tensor) -> np.ndarray:
    """A flat float32 numpy view of ``t`` (a copy only if ``t`` is not contiguous float32 on the CPU)."""
    return t.detach().to(device="cpu", dtype=torch.float32).contiguous().view(-1).numpy()


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, log_scales, quats, opacities, colors, viewmats, camera, near, far, bg, sink):
        inputs = [means, log_scales, quats, opacities, colors, viewmats]
        flat = [_flat(t) for t in inputs]
        flat.insert(5, colors.shape[1])
        cam = raster_camera(camera)
        color, depth, alpha, radii, state = _core.rasterize_forward(
            *flat, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, near, far, bg
        )
        b, n, c = viewmats.shape[0], opacities.shape[0], colors.shape[1]
        h, w = camera.height, camera.width
        ctx.state, ctx.sink = state, sink
        ctx.save_for_backward(*inputs)
        sink.forward_evaluations = state.forward_evaluations
        radii_t = torch.from_numpy(radii).view(b, n)
        ctx.mark_non_differentiable(radii_t)
        return (
            torch.from_numpy(color).view(b, h, w, c),
            torch.from_numpy(depth).view(b, h, w),
            torch.from_numpy(alpha).view(b, h, w),
            radii_t,
        )

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha, _g_radii):
        inputs = ctx.saved_tensors
        flat = [_flat(t) for t in inputs]
        flat.insert(5, inputs[4].shape[1])
        out = _core.rasterize_backward(ctx.state, *flat, _flat(g_color), _flat(g_depth), _flat(g_alpha))
        gm, gs, gq, go, gc, gv, g2d, ctx.sink.backward_evaluations = out
        n, c, b = inputs[3].shape[0], inputs[4].shape[1], inputs[5].shape[0]
        ctx.sink.grad2d = torch.from_numpy(g2d).view(b, n)
        grads = (
            torch.from_numpy(gm).view(n, 3),
            torch.from_numpy(gs).view(n, 3),
            torch.from_numpy(gq).view(n, 4),
            torch.from_numpy(go),
            torch.from_numpy(gc).view(n, c),
            torch.from_numpy(gv).view(b, 4, 4),
        )
        return (*grads, None, None, None, None, None)


def _check_inputs(means: Tensor, log_scales: Tensor, quats: Tensor, opacities: Tensor, colors: Tensor,
                  viewmats: Tensor) -> None:  # fmt: skip
    """Refuse mismatched shapes here, with the tensor's name: the Rust core would only see flat buffers."""
    n = means.shape[0]
    shapes = {"means": (means, (n, 3)), "log_scales": (log_scales, (n, 3)), "quats": (quats, (n, 4)),
              "opacities": (opacities, (n,))}  # fmt: skip
    for name, (t, shape) in shapes.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"render: {name} has shape {tuple(t.shape)}, expected {shape}")
    if colors.ndim != 2 or colors.shape[0] != n or not 1 <= colors.shape[1] <= 3:
        raise ValueError(f"render: colors has shape {tuple(colors.shape)}, expected ({n}, C) with C in 1..3")
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"render: viewmats has shape {tuple(viewmats.shape)}, expected (B, 4, 4)")


def _background(background: float | Tensor, channels: int) -> np.ndarray:
    """One background value per channel, as the flat float32 buffer the core takes (a scalar is broadcast)."""
    return _flat(torch.as_tensor(background, dtype=torch.float32).reshape(-1).expand(channels))


def render(
    means: Tensor,
    log_scales: Tensor,
    quats: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    camera: Camera,
    *,
    near: float = 0.01,
    far: float = 1e10,
    background: float | Tensor = 0.0,
) -> RenderResult:
    """Render B views of N Gaussians (see the module docstring); gradients flow to every tensor input
    except ``background``. Shapes: means, log_scales (N, 3); quats (N, 4); opacities (N,);
    colors (N, C) with C in 1..3; viewmats (B, 4, 4)."""
    _check_inputs(means, log_scales, quats, opacities, colors, viewmats)
    sink = _Sink()
    outputs = _Rasterize.apply(
        means,
        log_scales,
        quats,
        opacities,
        colors,
        viewmats,
        camera,
        float(near),
        float(far),
        _background(background, colors.shape[1]),
        sink,
    )
    return RenderResult(*outputs, _sink=sink)


@dataclass
class PoseJvp:
    color: Tensor  # (B, H, W, C)
    alpha: Tensor  # (B, H, W)
    d_color: Tensor  # (B, H, W, 6, C): the colour's derivative along each view's six tangents


def render_pose_jvp(
    means: Tensor,
    log_scales: Tensor,
    quats: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    tangents: Tensor,
    camera: Camera,
    *,
    near: float = 0.01,
    far: float = 1e10,
    background: float | Tensor = 0.0,
) -> PoseJvp:
    """Render B views and, in forward mode, the colour's derivative along six tangents of each view
    (``tangents`` (B, 6, 4, 4): d viewmat / d coordinate): a pose's whole Jacobian in one pass, where
    central differences take twelve renders. No autograd; culling and each pixel's contributors are held
    fixed, as in :func:`render`'s backward pass."""
    _check_inputs(means, log_scales, quats, opacities, colors, viewmats)
    b = viewmats.shape[0]
    if tuple(tangents.shape) != (b, 6, 4, 4):
        raise ValueError(f"render: tangents has shape {tuple(tangents.shape)}, expected ({b}, 6, 4, 4)")
    c, cam = colors.shape[1], raster_camera(camera)
    flat = [_flat(t) for t in (means, log_scales, quats, opacities, colors)]
    color, alpha, d_color = _core.rasterize_pose_jvp(
        *flat, c, _flat(viewmats), _flat(tangents), cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
        float(near), float(far), _background(background, c),
    )  # fmt: skip
    h, w = camera.height, camera.width
    return PoseJvp(
        torch.from_numpy(color).view(b, h, w, c),
        torch.from_numpy(alpha).view(b, h, w),
        torch.from_numpy(d_color).view(b, h, w, 6, c),
    )

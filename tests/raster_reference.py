"""Dense float64 pure-torch reference rasterizer: every Gaussian against every pixel, the same
conventions and float32 thresholds as the Rust rasterizer (RASTER_MATH.md), differentiable by autograd.
Slow by design (a Python loop over Gaussians); only for small test scenes and the benchmark baseline."""

from __future__ import annotations

import numpy as np
import torch
from evgs.data.sequence import Camera
from torch import Tensor

ALPHA_MIN = float(np.float32(1.0 / 255.0))
ALPHA_MAX = float(np.float32(0.99))
T_MIN = float(np.float32(1e-4))


def quat_to_rotmat(q: Tensor) -> Tensor:
    """(N, 4) ``(w, x, y, z)`` → (N, 3, 3); a zero quaternion gives the identity (as the Rust side)."""
    n2 = (q * q).sum(-1, keepdim=True)
    ok = n2 > 1e-24
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype)
    q = torch.where(ok, q / torch.where(ok, n2, 1.0).sqrt(), identity)
    w, x, y, z = q.unbind(-1)
    r = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(r, -1).reshape(q.shape[:-1] + (3, 3))


def project(means, log_scales, quats, opacities, viewmat, camera: Camera, near: float, far: float):
    """Per-Gaussian screen-space quantities of one view: ``(u, v, a, b, c, z, valid, radii)``."""
    near, far = float(np.float32(near)), float(np.float32(far))  # the planes are float32 in Rust
    rot, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ rot.T + t
    m = quat_to_rotmat(quats) * log_scales.exp()[:, None, :]
    cov_c = rot @ (m @ m.transpose(1, 2)) @ rot.T
    x, y, z = p.unbind(-1)
    z_ok = (z >= near) & (z <= far)
    zs = torch.where(z_ok, z, 1.0)  # keeps culled Gaussians from putting NaN into the gradients
    w_, h_ = camera.width, camera.height
    mx, my = 0.3 * 0.5 * w_ / camera.fx, 0.3 * 0.5 * h_ / camera.fy
    xz, yz = x / zs, y / zs
    cxz = xz.clamp(-(camera.cx / camera.fx + mx), (w_ - camera.cx) / camera.fx + mx)
    cyz = yz.clamp(-(camera.cy / camera.fy + my), (h_ - camera.cy) / camera.fy + my)
    # The clamped coordinate is a constant for the gradient (3DGS / gsplat).
    tx = torch.where(cxz != xz, (cxz * zs).detach(), x)
    ty = torch.where(cyz != yz, (cyz * zs).detach(), y)
    zero = torch.zeros_like(zs)
    jac = torch.stack(
        [camera.fx / zs, zero, -camera.fx * tx / zs**2, zero, camera.fy / zs, -camera.fy * ty / zs**2], -1
    ).reshape(-1, 2, 3)
    cov2d = jac @ cov_c @ jac.transpose(1, 2) + 0.3 * torch.eye(2, dtype=means.dtype)
    sxx, sxy, syy = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = sxx * syy - sxy * sxy
    det_s = torch.where(det > 0, det, 1.0)
    a, b, c = syy / det_s, -sxy / det_s, sxx / det_s
    u = camera.fx * x / zs + camera.cx
    v = camera.fy * y / zs + camera.cy
    o = opacities.detach()
    extent = torch.sqrt(2 * torch.log(torch.clamp(o / ALPHA_MIN, min=1.0))).clamp(max=3.33)
    rx = torch.ceil(extent * sxx.detach().clamp(min=0).sqrt())
    ry = torch.ceil(extent * syy.detach().clamp(min=0).sqrt())
    ud, vd = u.detach(), v.detach()
    in_image = (ud + rx > 0) & (ud - rx < w_) & (vd + ry > 0) & (vd - ry < h_)
    valid = z_ok & (det > 0) & (o >= ALPHA_MIN) & ((rx > 0) | (ry > 0)) & in_image
    radii = torch.where(valid, torch.maximum(rx, ry), 0).to(torch.int32)
    return u, v, a, b, c, zs, valid, radii


def render_reference(
    means: Tensor,
    log_scales: Tensor,
    quats: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    camera: Camera,
    near: float = 0.01,
    far: float = 1e10,
    background: float = 0.0,
    screen: list | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(color (B,H,W,C), depth (B,H,W), alpha (B,H,W), radii (B,N))``. If ``screen`` is a list, the
    per-view ``(u, v)`` tensors are appended to it (to read their gradients)."""
    dt = means.dtype
    px = torch.arange(camera.width, dtype=dt) + 0.5
    py = torch.arange(camera.height, dtype=dt) + 0.5
    outs = []
    for view in viewmats:
        u, v, a, b, c, z, valid, radii = project(means, log_scales, quats, opacities, view, camera, near, far)
        if screen is not None:
            u.retain_grad()
            v.retain_grad()
            screen.append((u, v))
        dx = u[:, None, None] - px[None, None, :]
        dy = v[:, None, None] - py[None, :, None]
        sigma = 0.5 * (a[:, None, None] * dx**2 + c[:, None, None] * dy**2) + b[:, None, None] * dx * dy
        alpha = torch.clamp(opacities[:, None, None] * torch.exp(-sigma), max=ALPHA_MAX)
        ok = valid[:, None, None] & (sigma >= 0) & (alpha >= ALPHA_MIN)
        t = torch.ones(camera.height, camera.width, dtype=dt)
        col = torch.zeros(camera.height, camera.width, colors.shape[1], dtype=dt)
        dep = torch.zeros(camera.height, camera.width, dtype=dt)
        done = torch.zeros(camera.height, camera.width, dtype=torch.bool)
        for i in torch.sort(z.detach(), stable=True).indices.tolist():
            live = ok[i] & ~done
            a_i = torch.where(live, alpha[i], 0.0)
            t_next = t * (1 - a_i)
            stop = live & (t_next <= T_MIN)
            take = live & ~stop
            w = torch.where(take, a_i * t, 0.0)
            col = col + w[..., None] * colors[i]
            dep = dep + w * z[i]
            t = torch.where(take, t_next, t)
            done = done | stop
        outs.append((col + t[..., None] * background, dep, 1 - t, radii))
    return tuple(torch.stack(x) for x in zip(*outs, strict=True))

"""Tile-based pure-torch rasterizer: the tiled algorithm written with torch tensor ops, as a straightforward
torch implementation would be. The projection is the dense reference's (`raster_reference.project`);
then 16×16 tile binning (each Gaussian goes to the tiles its square screen-radius box touches, a
superset of the Rust boxes, so the image is the same), one sort of the (tile, depth rank) pairs, and
per tile front-to-back compositing vectorised over its Gaussians × pixels, with the same float32
thresholds (RASTER_MATH.md). Differentiable by autograd; float32 unless given float64 inputs. A
benchmark baseline beside the Rust rasterizer, checked against the dense reference in the tests."""

from __future__ import annotations

import torch
from evgs.data.sequence import Camera
from raster_reference import ALPHA_MAX, ALPHA_MIN, T_MIN, project
from torch import Tensor

TILE = 16


def bin_tiles(u: Tensor, v: Tensor, radii: Tensor, z: Tensor, camera: Camera) -> tuple[Tensor, Tensor]:
    """``(offsets, ids)``: the Gaussians of tile ``t`` are ``ids[offsets[t]:offsets[t + 1]]``, front to back
    (ties by index). Culled Gaussians (radius 0) are in no tile."""
    tiles_x, tiles_y = -(-camera.width // TILE), -(-camera.height // TILE)
    r = radii.to(u.dtype)
    ud, vd = u.detach(), v.detach()
    x0 = torch.floor((ud - r) / TILE).clamp(0, tiles_x).long()
    x1 = torch.ceil((ud + r) / TILE).clamp(0, tiles_x).long()
    y0 = torch.floor((vd - r) / TILE).clamp(0, tiles_y).long()
    y1 = torch.ceil((vd + r) / TILE).clamp(0, tiles_y).long()
    nx = x1 - x0
    count = torch.where(radii > 0, nx * (y1 - y0), 0)
    g = torch.repeat_interleave(torch.arange(len(u)), count)
    first = torch.cumsum(count, 0) - count
    local = torch.arange(len(g)) - first[g]
    tile = (y0[g] + local // nx[g]) * tiles_x + x0[g] + local % nx[g]
    rank = torch.empty(len(u), dtype=torch.long)
    rank[torch.sort(z.detach(), stable=True).indices] = torch.arange(len(u))
    order = torch.argsort(tile * max(len(u), 1) + rank[g])
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long)
    offsets[1:] = torch.cumsum(torch.bincount(tile, minlength=tiles_x * tiles_y), 0)
    return offsets, g[order]


def composite_tile(
    u: Tensor, v: Tensor, conic: Tensor, opacity: Tensor, color: Tensor, z: Tensor, xs: Tensor, ys: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Front-to-back compositing of K depth-ordered Gaussians over the pixel centres ``ys × xs``:
    ``(color (h, w, C), depth (h, w), final transmittance (h, w))``."""
    dx = u[:, None, None] - xs[None, None, :]
    dy = v[:, None, None] - ys[None, :, None]
    a, b, c = (conic[:, i, None, None] for i in range(3))
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(opacity[:, None, None] * torch.exp(-sigma), max=ALPHA_MAX)
    alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, 0.0)
    keep = 1 - alpha
    t_after = torch.cumprod(keep, 0)
    # A pixel stops at the first Gaussian that would take T to T_MIN or below (not composited);
    # T only decreases, so those are exactly the ones with t_after ≤ T_MIN.
    live = t_after > T_MIN
    t_before = torch.cat([torch.ones_like(t_after[:1]), t_after[:-1]])
    w = torch.where(live, alpha * t_before, 0.0)
    out_color = torch.einsum("khw,kc->hwc", w, color)
    out_depth = (w * z[:, None, None]).sum(0)
    t_final = torch.where(live, keep, 1.0).prod(0)
    return out_color, out_depth, t_final


def render_tiles(
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
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(color (B,H,W,C), depth (B,H,W), alpha (B,H,W), radii (B,N))``, as ``render_reference``."""
    dt, (w_, h_) = means.dtype, (camera.width, camera.height)
    tiles_x = -(-w_ // TILE)
    outs = []
    for view in viewmats:
        u, v, a, b, c, z, _, radii = project(means, log_scales, quats, opacities, view, camera, near, far)
        conic = torch.stack([a, b, c], -1)
        offsets, ids = bin_tiles(u, v, radii, z, camera)
        color = torch.zeros(h_, w_, colors.shape[1], dtype=dt)
        depth = torch.zeros(h_, w_, dtype=dt)
        t_final = torch.ones(h_, w_, dtype=dt)
        for t in torch.nonzero(offsets[1:] > offsets[:-1]).flatten().tolist():
            k = ids[offsets[t] : offsets[t + 1]]
            x0, y0 = (t % tiles_x) * TILE, (t // tiles_x) * TILE
            x1, y1 = min(x0 + TILE, w_), min(y0 + TILE, h_)
            xs = torch.arange(x0, x1, dtype=dt) + 0.5
            ys = torch.arange(y0, y1, dtype=dt) + 0.5
            tc, td, tt = composite_tile(u[k], v[k], conic[k], opacities[k], colors[k], z[k], xs, ys)
            color[y0:y1, x0:x1] = tc
            depth[y0:y1, x0:x1] = td
            t_final[y0:y1, x0:x1] = tt
        outs.append((color + t_final[..., None] * background, depth, 1 - t_final, radii))
    return tuple(torch.stack(x) for x in zip(*outs, strict=True))

"""SO(3)/SE(3) exponential and logarithm maps in torch, batched and differentiable.

Tangent vectors are ``ξ = (ρ, φ)``, translation first (as the reference code). Every function takes
``(..., 6)`` / ``(..., 3)`` vectors or ``(..., 4, 4)`` / ``(..., 3, 3)`` matrices of any float dtype.
Small-angle and near-π cases switch to series / alternative formulas through ``torch.where`` with
*safe* inputs in the unused branch, so neither values nor gradients become NaN at 0 or π.
"""

from __future__ import annotations

import torch
from torch import Tensor


def _small(x: Tensor) -> Tensor:
    """Where θ² (or sin²θ) is small enough that the closed forms cancel badly: the four-term series
    used there are accurate to O(θ⁸), below rounding for these thresholds in each precision."""
    return x < (1e-3 if x.dtype == torch.float64 else 0.1)


def hat(phi: Tensor) -> Tensor:
    """(..., 3) → (..., 3, 3) skew-symmetric matrices with ``hat(a) @ b = a × b``."""
    x, y, z = phi.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(*phi.shape[:-1], 3, 3)


def se3_hat(xi: Tensor) -> Tensor:
    """(..., 6) twists ``(ρ, φ)`` → (..., 4, 4) ``[[hat(φ), ρ], [0, 0]]``, whose matrix exponential is
    :func:`se3_exp`: the tangent of a pose moved along ``ξ`` on the left is ``se3_hat(ξ) @ T``."""
    out = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
    out[..., :3, :3] = hat(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def vee(m: Tensor) -> Tensor:
    """Inverse of :func:`hat` applied to the skew part of (..., 3, 3) matrices."""
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
    )


def _coefficients(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``A = sinθ/θ``, ``B = (1−cosθ)/θ²``, ``C = (θ−sinθ)/θ³`` with series near 0."""
    small = _small(theta2)
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    x = theta2
    a = torch.where(small, 1 - x / 6 * (1 - x / 20 * (1 - x / 42)), t.sin() / t)
    b = torch.where(small, 0.5 - x / 24 * (1 - x / 30 * (1 - x / 56)), (1 - t.cos()) / t2)
    c = torch.where(small, 1 / 6 - x / 120 * (1 - x / 42 * (1 - x / 72)), (t - t.sin()) / (t2 * t))
    return a, b, c


def so3_exp(phi: Tensor) -> Tensor:
    """Rodrigues: (..., 3) rotation vectors → (..., 3, 3) rotation matrices."""
    a, b, _ = _coefficients((phi * phi).sum(-1))
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(r: Tensor) -> Tensor:
    """(..., 3, 3) rotation matrices → (..., 3) rotation vectors with ``|φ| ≤ π``.

    ``θ = atan2(|v|, (tr R − 1)/2)`` with ``v = vee(R)`` = sinθ·axis is well conditioned at every angle.
    Away from π the axis is ``v / sinθ``; near π (cos θ < −0.5, where sinθ → 0) it is read from the
    symmetric part ``(R + Rᵀ)/2 = cosθ·I + (1 − cosθ)·aaᵀ`` instead, its sign taken from ``v``.
    """
    v = vee(r)
    cos = ((r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]) - 1) / 2
    s2 = (v * v).sum(-1)
    small = s2 < 1e-8  # only to avoid 0/0: θ = atan2(|v|, cos) and |v| are accurate at any angle
    sin = torch.where(small, torch.ones_like(s2), s2).sqrt()
    theta = torch.atan2(torch.where(small, torch.zeros_like(s2), sin), cos)
    # Regular branch: θ/sinθ · v, with the series asin(s)/s = 1 + s²/6 + 3s⁴/40 + 5s⁶/112 near 0.
    near_pi = cos < -0.5
    factor = torch.where(small, 1 + s2 / 6 + 3 * s2**2 / 40 + 5 * s2**3 / 112, theta / sin)
    regular = factor[..., None] * v
    # Near-π branch: the largest column of aaᵀ, normalised, signed along v.
    cos_safe = torch.where(near_pi, cos, -torch.ones_like(cos))
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    aat = (0.5 * (r + r.transpose(-1, -2)) - cos_safe[..., None, None] * eye) / (1 - cos_safe)[
        ..., None, None
    ]
    diag = torch.diagonal(aat, dim1=-2, dim2=-1)
    idx = diag.argmax(-1, keepdim=True)
    col = torch.gather(aat, -1, idx[..., None, :].expand(*aat.shape[:-1], 1)).squeeze(-1)
    col = torch.where(near_pi[..., None], col, torch.ones_like(col))
    axis = col / col.norm(dim=-1, keepdim=True)
    axis = torch.where((axis * v).sum(-1, keepdim=True) < 0, -axis, axis)
    # sinθ = axis·v ≥ 0 here: linear in R, so no square root (and no infinite gradient) at θ = π.
    theta_pi = torch.atan2((axis * v).sum(-1), cos_safe)
    return torch.where(near_pi[..., None], theta_pi[..., None] * axis, regular)


def se3_exp(xi: Tensor) -> Tensor:
    """(..., 6) twists ``(ρ, φ)`` → (..., 4, 4) rigid transforms ``[Exp(φ) | V(φ)ρ]``."""
    rho, phi = xi[..., :3], xi[..., 3:]
    a, b, c = _coefficients((phi * phi).sum(-1))
    k = hat(phi)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    rot = eye + a[..., None, None] * k + b[..., None, None] * k2
    v = eye + b[..., None, None] * k + c[..., None, None] * k2
    return _compose(rot, (v @ rho[..., None])[..., 0])


def se3_log(t: Tensor) -> Tensor:
    """(..., 4, 4) rigid transforms → (..., 6) twists ``(ρ, φ)``, the inverse of :func:`se3_exp`."""
    phi = so3_log(t[..., :3, :3])
    theta2 = (phi * phi).sum(-1)
    a, b, _ = _coefficients(theta2)
    # V⁻¹ = I − K/2 + D·K², D = (1 − A/(2B))/θ², series 1/12 + θ²/720 + θ⁴/30240 + θ⁶/1209600 near 0.
    # Near 2π the closed form would blow up, but |φ| ≤ π here, so B ≥ 4/π² stays well away from 0.
    small = _small(theta2)
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    x = theta2
    d = torch.where(small, 1 / 12 + x / 720 + x**2 / 30240 + x**3 / 1209600, (1 - a / (2 * b)) / t2)
    k = hat(phi)
    eye = torch.eye(3, dtype=t.dtype, device=t.device)
    v_inv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    rho = (v_inv @ t[..., :3, 3:])[..., 0]
    return torch.cat([rho, phi], -1)


def se3_inverse(t: Tensor) -> Tensor:
    """Inverse of (..., 4, 4) rigid transforms."""
    rt = t[..., :3, :3].transpose(-1, -2)
    return _compose(rt, -(rt @ t[..., :3, 3:])[..., 0])


def _compose(rot: Tensor, trans: Tensor) -> Tensor:
    top = torch.cat([rot, trans[..., None]], -1)
    bottom = torch.zeros(*rot.shape[:-2], 1, 4, dtype=rot.dtype, device=rot.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def project_se3(t: Tensor, tol: float = 0.0) -> Tensor:
    """The nearest rigid transform: the rotation block replaced by its polar factor ``U Vᵀ`` — for the
    transforms whose ``|R Rᵀ − I|`` exceeds ``tol`` (the others are returned bit for bit).

    Knots are products of many exponentials; without this, rounding makes their rotations slightly
    non-orthonormal, and the constant-velocity prediction ``T₁ T₀⁻¹ T₁`` (with the transpose as inverse)
    roughly triples that error every frame until poses blow up some 40 frames later.
    """
    rot = t[..., :3, :3]
    eye = torch.eye(3, dtype=t.dtype, device=t.device)
    bad = (rot @ rot.transpose(-1, -2) - eye).abs().amax((-1, -2)) > tol
    u, _, vh = torch.linalg.svd(rot)
    d = torch.sign(torch.linalg.det(u @ vh))  # keep det +1
    u = torch.cat([u[..., :2], u[..., 2:] * d[..., None, None]], -1)
    return torch.where(bad[..., None, None], _compose(u @ vh, t[..., :3, 3]), t)

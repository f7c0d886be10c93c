"""The Rust rasterizer against the dense float64 reference: forward, every gradient (incl. the view
matrix), SE(3) pose gradients by finite differences, edge cases, determinism across thread counts."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from evgs.data.sequence import Camera
from evgs.render import _flat, raster_camera, render, render_pose_jvp
from evgs.slam.lie import se3_hat
from raster_reference import render_reference

CAM = Camera(width=40, height=28, fx=36.0, fy=34.0, cx=19.3, cy=14.1)
REF_CAM = raster_camera(CAM)  # the reference keeps the kernels' grid (pixel centres at i + 0.5)


def look_at_viewmat(yaw: float, pitch: float, shift: tuple[float, float, float]) -> torch.Tensor:
    """World-to-camera matrix of a camera rotated by (yaw, pitch) and translated."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    r = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]) @ np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, shift
    return torch.tensor(m, dtype=torch.float32)


def scene(n: int, channels: int = 3, seed: int = 0) -> dict[str, torch.Tensor]:
    """Gaussians around (0, 0, 3), moderately opaque, a few pixels across."""
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g) * torch.tensor([0.6, 0.45, 0.3]) + torch.tensor([0, 0, 3.0]),
        "log_scales": torch.rand(n, 3, generator=g) * 1.2 - 3.2,
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.rand(n, generator=g) * 0.5 + 0.2,
        "colors": torch.rand(n, channels, generator=g),
    }


def views(b: int = 2) -> torch.Tensor:
    poses = [(0.0, 0.0, (0.0, 0.0, 0.0)), (0.08, -0.05, (0.1, -0.05, 0.2)), (-0.1, 0.04, (-0.15, 0.1, -0.1))]
    return torch.stack([look_at_viewmat(*p) for p in poses[:b]])


def as64(d: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.double().requires_grad_() for k, v in d.items()}


@pytest.mark.parametrize("channels", [1, 3])
def test_forward_matches_reference(channels: int) -> None:
    g, vm = scene(40, channels), views(2)
    out = render(**g, viewmats=vm, camera=CAM, background=0.25)
    ref = render_reference(**as64(g), viewmats=vm.double(), camera=REF_CAM, background=0.25)
    assert out.color.shape == (2, CAM.height, CAM.width, channels) and out.color.dtype == torch.float32
    assert out.alpha.max() > 0.5  # the scene covers the image
    torch.testing.assert_close(out.color.double(), ref[0].detach(), rtol=0, atol=1e-5)
    torch.testing.assert_close(out.alpha.double(), ref[2].detach(), rtol=0, atol=1e-5)
    torch.testing.assert_close(out.depth.double(), ref[1].detach(), rtol=0, atol=4e-5)
    assert torch.equal(out.radii, ref[3])


def test_pixel_centres_follow_the_opencv_camera() -> None:
    """``Camera`` intrinsics are OpenCV's (pixel i's centre at u = i, as calibrations, the simulator and
    the events): a small round Gaussian projected to ``(12, 9)`` renders centred on pixel (12, 9), one
    projected to ``(12.5, 9)`` evenly across pixels 12 and 13."""
    z = 3.0
    for u, v in ((12.0, 9.0), (12.5, 9.0)):
        mean = torch.tensor([[(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z]])
        g = {"means": mean, "log_scales": torch.full((1, 3), -4.0), "quats": torch.tensor([[1.0, 0, 0, 0]]),
             "opacities": torch.tensor([0.9]), "colors": torch.ones(1, 1)}  # fmt: skip
        a = render(**g, viewmats=torch.eye(4)[None], camera=CAM).alpha[0].double()
        row = a[9]
        if u == 12.0:
            assert int(a.argmax()) == 9 * CAM.width + 12
            assert float(row[11]) == pytest.approx(float(row[13]), rel=1e-4)
            assert float(a[8, 12]) == pytest.approx(float(a[10, 12]), rel=1e-4)
        else:
            assert float(row[12]) == pytest.approx(float(row[13]), rel=1e-4) and float(row[12]) > 0.3


def loss_weights(b: int, channels: int, seed: int = 1) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    shape = (b, CAM.height, CAM.width)
    return (
        torch.randn(*shape, channels, generator=g),
        torch.randn(*shape, generator=g),
        torch.randn(*shape, generator=g),
    )


def weighted_loss(color, depth, alpha, w) -> torch.Tensor:
    return (color * w[0]).sum() + 0.3 * (depth * w[1]).sum() + (alpha * w[2]).sum()


@pytest.mark.parametrize("channels", [1, 3])
def test_gradients_match_reference_autograd(channels: int) -> None:
    g, vm = scene(30, channels, seed=3), views(2)
    w = loss_weights(2, channels)
    params = {k: v.clone().requires_grad_() for k, v in g.items()}
    vm32 = vm.clone().requires_grad_()
    out = render(**params, viewmats=vm32, camera=CAM, background=0.1)
    assert out.grad2d_norm() is None
    weighted_loss(out.color, out.depth, out.alpha, w).backward()

    ref_params = as64(g)
    vm64 = vm.double().requires_grad_()
    screen: list = []
    ref = render_reference(**ref_params, viewmats=vm64, camera=REF_CAM, background=0.1, screen=screen)
    weighted_loss(ref[0], ref[1], ref[2], [x.double() for x in w]).backward()

    for name in g:
        want = ref_params[name].grad
        assert want.abs().max() > 0, name
        torch.testing.assert_close(
            params[name].grad.double(), want, rtol=1e-4, atol=1e-4 * want.abs().max().item(), msg=name
        )
    want = vm64.grad
    torch.testing.assert_close(vm32.grad.double(), want, rtol=1e-4, atol=1e-4 * want.abs().max().item())
    assert torch.all(vm32.grad[:, 3] == 0)
    norm = torch.stack([torch.hypot(u.grad, v.grad) for u, v in screen])
    got = out.grad2d_norm()
    assert got.shape == (2, 30)
    torch.testing.assert_close(got.double(), norm, rtol=1e-4, atol=1e-4 * norm.max().item())


def se3_exp(xi: np.ndarray) -> torch.Tensor:
    """Exp of the twist ``(ρ, θ)`` as a 4×4 matrix (float64), by the matrix exponential."""
    return torch.linalg.matrix_exp(se3_hat(torch.as_tensor(xi, dtype=torch.float64)))


def test_pose_gradient_matches_se3_finite_differences() -> None:
    g, vm = scene(30, 1, seed=5), views(1)
    w = loss_weights(1, 1, seed=7)
    vm32 = vm.clone().requires_grad_()
    out = render(**g, viewmats=vm32, camera=CAM)
    weighted_loss(out.color, out.depth, out.alpha, w).backward()
    m = vm32.grad[0].double() @ vm[0].double().T
    vee = torch.stack([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    analytic = torch.cat([m[:3, 3], vee])

    g64 = {k: v.double() for k, v in g.items()}
    w64 = [x.double() for x in w]

    def loss_at(xi: np.ndarray) -> float:
        pose = (se3_exp(xi) @ vm[0].double())[None]
        return weighted_loss(*render_reference(**g64, viewmats=pose, camera=REF_CAM)[:3], w64).item()

    eps = 1e-6
    fd = torch.tensor(
        [(loss_at(eps * e) - loss_at(-eps * e)) / (2 * eps) for e in np.eye(6)], dtype=torch.float64
    )
    torch.testing.assert_close(analytic, fd, rtol=1e-3, atol=1e-3 * fd.abs().max().item())


def twist_tangents(vm: torch.Tensor) -> torch.Tensor:
    """(B, 6, 4, 4) float64 ``d(exp(ε·ξ̂)·V)/dε = ξ̂·V`` for the six unit twists (translation, rotation)."""
    return se3_hat(torch.eye(6, dtype=torch.float64))[None] @ vm.double()[:, None]


@pytest.mark.parametrize("channels", [1, 3])
def test_pose_jvp_matches_reference_autograd_and_finite_differences(channels: int) -> None:
    """The forward-mode pose derivative per pixel against central differences of the float64 reference,
    and its projections on random cotangents against the reference's autograd (reverse mode)."""
    g, vm = scene(30, channels, seed=4), views(2)
    tangents = twist_tangents(vm)
    out = render_pose_jvp(**g, viewmats=vm, tangents=tangents.float(), camera=CAM, background=0.3)
    plain = render(**g, viewmats=vm, camera=CAM, background=0.3)
    assert torch.equal(out.color, plain.color) and torch.equal(out.alpha, plain.alpha)
    assert out.d_color.shape == (2, CAM.height, CAM.width, 6, channels)

    g64 = {k: v.double() for k, v in g.items()}
    eps = 1e-6
    for k in range(6):
        hi, lo = (
            render_reference(**g64, viewmats=vm.double() + s * eps * tangents[:, k], camera=REF_CAM,
                             background=0.3)[0]
            for s in (1, -1)
        )  # fmt: skip
        fd = (hi - lo) / (2 * eps)
        assert fd.abs().max() > 0.05, k
        got = out.d_color[..., k, :].double()
        torch.testing.assert_close(got, fd, rtol=0, atol=2e-3 * fd.abs().max().item())

    w = loss_weights(2, channels, seed=9)[0].double()
    vm64 = vm.double().requires_grad_()
    (render_reference(**g64, viewmats=vm64, camera=REF_CAM, background=0.3)[0] * w).sum().backward()
    reverse = torch.einsum("bij,bkij->bk", vm64.grad, tangents)
    forward_mode = torch.einsum("bhwc,bhwkc->bk", w, out.d_color.double())
    torch.testing.assert_close(forward_mode, reverse, rtol=1e-4, atol=1e-4 * reverse.abs().max().item())


def test_pose_jvp_rejects_bad_tangents() -> None:
    g, vm = scene(5, 1), views(2)
    with pytest.raises(ValueError, match="tangents has shape"):
        render_pose_jvp(**g, viewmats=vm, tangents=torch.zeros(2, 5, 4, 4), camera=CAM)
    with pytest.raises(ValueError, match="tangents must be finite"):
        render_pose_jvp(**g, viewmats=vm, tangents=torch.full((2, 6, 4, 4), float("nan")), camera=CAM)


def test_batch_equals_separate_views() -> None:
    g, vm = scene(30, 3, seed=2), views(3)
    batch = render(**g, viewmats=vm, camera=CAM)
    for i in range(3):
        single = render(**g, viewmats=vm[i : i + 1], camera=CAM)
        assert torch.equal(batch.color[i], single.color[0])
        assert torch.equal(batch.depth[i], single.depth[0])
        assert torch.equal(batch.radii[i], single.radii[0])
    assert not torch.equal(batch.color[0], batch.color[1])


def test_no_gaussians() -> None:
    empty = {k: v[:0].clone().requires_grad_() for k, v in scene(1, 2).items()}
    vm = views(2).requires_grad_()
    out = render(**empty, viewmats=vm, camera=CAM, background=torch.tensor([0.2, 0.7]))
    assert torch.all(out.color[..., 0] == 0.2) and torch.all(out.color[..., 1] == 0.7)
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0) and out.radii.shape == (2, 0)
    (out.color.sum() + out.alpha.sum()).backward()
    assert empty["means"].grad.shape == (0, 3) and torch.all(vm.grad == 0)


def edge_scene() -> dict[str, torch.Tensor]:
    """One Gaussian per edge case, in front of a normal one."""
    means = torch.tensor(
        [
            [0.0, 0.0, 3.0],  # 0 normal
            [0.1, 0.0, -2.0],  # 1 behind the camera
            [0.0, 0.0, 0.01],  # 2 exactly on the near plane: kept
            [0.0, 0.0, 0.0099],  # 3 just in front of the near plane: culled
            [30.0, 0.0, 3.0],  # 4 outside the image
            [0.2, 0.1, 4.0],  # 5 huge
            [-0.3, 0.2, 2.5],  # 6 needle-thin
            [0.3, -0.2, 2.8],  # 7 zero quaternion
            [-0.4, -0.3, 3.5],  # 8 near-zero scale, very transparent: culled
        ]
    )
    log_scales = torch.full((9, 3), -2.0)
    log_scales[2] = -6.0
    log_scales[5] = 2.5
    log_scales[6] = torch.tensor([-9.0, 0.0, -9.0])
    quats = torch.tensor([[1.0, 0.2, -0.1, 0.3]]).repeat(9, 1)
    quats[7] = 0.0
    opacities = torch.full((9,), 0.6)
    opacities[5] = 0.3
    opacities[8] = 0.003
    return {"means": means, "log_scales": log_scales, "quats": quats, "opacities": opacities,
            "colors": torch.linspace(0.1, 0.9, 9)[:, None]}  # fmt: skip


def test_edge_cases_match_reference_without_nan() -> None:
    g, vm = edge_scene(), views(1)
    params = {k: v.clone().requires_grad_() for k, v in g.items()}
    vm32 = vm.clone().requires_grad_()
    out = render(**params, viewmats=vm32, camera=CAM)
    radii = out.radii[0]
    assert radii[1] == 0 and radii[3] == 0 and radii[4] == 0 and radii[8] == 0
    assert (
        radii[0] > 0
        and radii[2] > 0
        and radii[5] > max(CAM.width, CAM.height)
        and radii[6] > 0
        and radii[7] > 0
    )
    ref = render_reference(**as64(g), viewmats=vm.double(), camera=REF_CAM)
    assert torch.equal(radii, ref[3][0])
    torch.testing.assert_close(out.color.double(), ref[0].detach(), rtol=0, atol=1e-5)
    torch.testing.assert_close(out.alpha.double(), ref[2].detach(), rtol=0, atol=1e-5)
    (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()
    for t in [*params.values(), vm32]:
        assert torch.isfinite(t.grad).all()
    assert torch.all(params["quats"].grad[7] == 0)
    for culled in (1, 3, 4, 8):
        assert torch.all(params["means"].grad[culled] == 0)


def test_zero_quaternion_renders_as_identity() -> None:
    g = scene(5, 1, seed=9)
    g["quats"][2] = 0.0
    ident = {k: v.clone() for k, v in g.items()}
    ident["quats"][2] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    a = render(**g, viewmats=views(1), camera=CAM)
    b = render(**ident, viewmats=views(1), camera=CAM)
    assert torch.equal(a.color, b.color)


def test_float32_threshold_semantics() -> None:
    """Two Gaussians at the 0.99 clamp: T = 0.01² ≤ 1e-4 in float32, so the second is not composited
    and 1 % of the background shows through (RASTER_MATH.md)."""
    g = {
        "means": torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.5]]),
        "log_scales": torch.full((2, 3), 0.0),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2),
        "opacities": torch.tensor([0.999, 0.999]),
        "colors": torch.tensor([[0.0], [1.0]]),
    }
    out = render(**g, viewmats=views(1), camera=CAM, background=1.0)
    centre = out.color[0, CAM.height // 2, CAM.width // 2, 0].item()
    assert centre == pytest.approx(0.01, abs=1e-6)


def test_inputs_are_not_copied() -> None:
    t = torch.rand(10, 3)
    assert _flat(t).ctypes.data == t.data_ptr()


def test_bad_shapes_are_rejected() -> None:
    g = scene(4)
    with pytest.raises(ValueError, match="log_scales"):
        render(**{**g, "log_scales": g["log_scales"][:, :2]}, viewmats=views(1), camera=CAM)
    with pytest.raises(ValueError, match="viewmats"):
        render(**g, viewmats=torch.eye(4), camera=CAM)
    with pytest.raises(ValueError, match="near"):
        render(**g, viewmats=views(1), camera=CAM, near=0.0)


DETERMINISM_SCRIPT = """
import hashlib, sys, torch
sys.path.insert(0, sys.argv[1])
from test_raster import CAM, scene, views, loss_weights, weighted_loss
from evgs.render import render
g = {k: v.requires_grad_() for k, v in scene(3000, 3, seed=11).items()}
vm = views(3).requires_grad_()
out = render(**g, viewmats=vm, camera=CAM)
weighted_loss(out.color, out.depth, out.alpha, loss_weights(3, 3)).backward()
h = hashlib.sha256()
for t in [out.color, out.depth, out.alpha, out.grad2d_norm(), vm.grad, *(v.grad for v in g.values())]:
    h.update(t.detach().numpy().tobytes())
print(h.hexdigest())
"""


def test_bitwise_identical_across_thread_counts() -> None:
    digests = []
    for threads in ("1", "2"):
        env = {**os.environ, "RAYON_NUM_THREADS": threads}
        run = subprocess.run(
            [sys.executable, "-c", DETERMINISM_SCRIPT, str(Path(__file__).parent)],
            env=env, capture_output=True, text=True, check=True,
        )  # fmt: skip
        digests.append(run.stdout.strip())
    assert len(digests[0]) == 64 and digests[0] == digests[1]
    assert hashlib.sha256(b"").hexdigest() not in digests

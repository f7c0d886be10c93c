"""The event loss on known images, and SSIM against scikit-image."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from evgs.config import load_config
from evgs.slam import loss_torch
from evgs.slam.loss import (
    depth_variation,
    event_loss,
    event_mask,
    linlog,
    predicted_events,
    ssim,
    total_variation,
    valid_mask,
)
from skimage.metrics import structural_similarity

LOSS = load_config().loss


def cfg(**kw):
    return dataclasses.replace(LOSS, **kw)


def blobs(seed: int, shape=(2, 40, 48)) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    return torch.nn.functional.avg_pool2d(x[:, None], 5, 1, 2)[:, 0]


@pytest.mark.parametrize("data_range", [1.0, 2.0])
def test_ssim_matches_skimage(data_range: float):
    a, b = blobs(0), blobs(1) * 0.7 + 0.1 * blobs(0)
    got = ssim(a, b, 11, 1.5, data_range)
    for i in range(len(a)):
        ref = structural_similarity(
            a[i].numpy(),
            b[i].numpy(),
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=data_range,
        )
        assert got[i].item() == pytest.approx(ref, abs=1e-10)


def test_ssim_identical_is_one_and_float32_works():
    a = blobs(3).float()
    assert torch.allclose(ssim(a, a), torch.ones(2), atol=1e-6)
    with pytest.raises(ValueError, match="smaller than"):
        ssim(a[:, :8, :8], a[:, :8, :8])


def test_linlog_is_continuous_and_matches_its_branches():
    x = torch.tensor([0.0, 10.0, 20.0, 100.0], dtype=torch.float64)
    want = torch.tensor([0.0, 10 * math.log(20) / 20, math.log(20), math.log(100)], dtype=torch.float64)
    assert torch.allclose(linlog(x), want)
    x = torch.tensor([0.0, 5.0], requires_grad=True)
    linlog(x).sum().backward()
    assert torch.allclose(x.grad, torch.full((2,), math.log(20) / 20))  # finite slope on black


def test_predicted_events_log_and_linlog():
    start = torch.full((1, 16, 16), 0.2, dtype=torch.float64)
    end = start * 2
    e = predicted_events(start, end, cfg(log_mode="log", log_eps=0.0))
    assert torch.allclose(e, torch.full_like(e, math.log(2)))
    e = predicted_events(start, end, cfg(log_mode="linlog"))  # 255·0.2 = 51 ≥ 20: the log branch
    assert torch.allclose(e, torch.full_like(e, math.log(2)))
    dark = torch.full((1, 16, 16), 0.02, dtype=torch.float64)  # 5.1 < 20: the linear branch
    e = predicted_events(dark, dark * 2, cfg(log_mode="linlog"))
    assert torch.allclose(e, torch.full_like(e, 5.1 * math.log(20) / 20))


def test_identical_renders_and_no_events_give_zero_loss():
    img = blobs(5)
    terms = event_loss(torch.zeros_like(img), img, img, LOSS)
    assert terms.total.item() == pytest.approx(0.0, abs=1e-12)


def test_known_brightness_step_l1_and_mse():
    start = torch.full((2, 24, 24), 0.25, dtype=torch.float64)
    end = start.clone()
    end[:, :, 12:] = 0.5  # right half brightens by a factor 2: Ê = ln 2 there (eps 0)
    events = torch.zeros_like(start)
    events[:, :, 12:] = 0.5
    c = cfg(log_eps=0.0, lambda_ssim=0.0)
    half = 0.5 * abs(0.5 - math.log(2))  # half the pixels err by |0.5 − ln 2|
    assert event_loss(events, start, end, c).total.item() == pytest.approx(half, rel=1e-12)
    mse = event_loss(events, start, end, dataclasses.replace(c, event_loss="mse")).total.item()
    assert mse == pytest.approx(0.5 * (0.5 - math.log(2)) ** 2, rel=1e-12)
    # λ mixes in 1 − SSIM(start, end) exactly as eq. 8.
    lam = 0.1
    terms = event_loss(events, start, end, dataclasses.replace(c, lambda_ssim=lam))
    s = ssim(start, end).mean()
    assert terms.total.item() == pytest.approx((1 - lam) * half + lam * (1 - s.item()), rel=1e-12)


def test_total_variation_known_values_and_preference_for_filled_faces():
    img = torch.zeros((1, 10, 10), dtype=torch.float64)
    img[0, :, 5:] = 0.4  # one vertical edge of height 0.4 on every row
    assert total_variation(img).item() == pytest.approx(0.4 * 10 / (10 * 9), rel=1e-12)
    # A face lit only along its outline (what the events constrain) varies more than the filled face:
    # the prior fills uniform faces whose inside fires no events.
    filled = torch.zeros((1, 20, 20), dtype=torch.float64)
    filled[0, 5:15, 5:15] = 0.5
    ring = filled.clone()
    ring[0, 7:13, 7:13] = 0.0
    assert total_variation(filled) < total_variation(ring)
    assert total_variation(torch.full((2, 8, 8), 0.3)).item() == 0.0


def test_depth_variation_known_values_scale_invariance_and_transparent_pixels():
    alpha = torch.ones((1, 6, 8), dtype=torch.float64)
    assert depth_variation(torch.full((1, 6, 8), 3.0, dtype=torch.float64), alpha).item() == 0.0
    # A plane tilted along x: depth 3 + 0.1·x over 8 columns, whose median torch takes as the lower of
    # the two middle values, 3.3; every horizontal pair differs by 0.1, every vertical pair by 0.
    tilted = (3.0 + 0.1 * torch.arange(8, dtype=torch.float64)).expand(1, 6, 8).clone()
    assert depth_variation(tilted, alpha).item() == pytest.approx(0.1 / 3.3, rel=1e-12)
    # The map's scale does not matter: the depth is relative to its median.
    assert depth_variation(5 * tilted, alpha).item() == pytest.approx(0.1 / 3.3, rel=1e-12)
    # The expected depth D is alpha-weighted: D / alpha is what varies; transparent pixels do not count.
    half = alpha.clone()
    half[0, :, 4:] = 0.8
    wild = tilted * half
    wild[0, 0, :] = 100.0
    half[0, 0, :] = 0.1
    assert depth_variation(wild, half).item() == pytest.approx(0.1 / 3.3, rel=1e-12)
    assert depth_variation(wild, torch.zeros_like(half)).item() == 0.0


def test_depth_variation_gradients_match_finite_differences():
    gen = torch.Generator().manual_seed(3)
    alpha = torch.rand((2, 7, 9), dtype=torch.float64, generator=gen) * 0.45 + 0.55
    depth = (torch.rand((2, 7, 9), dtype=torch.float64, generator=gen) + 2) * alpha
    assert torch.autograd.gradcheck(depth_variation, (depth.requires_grad_(), alpha.requires_grad_()))


def test_a_shifted_edge_is_penalised_more_the_further_it_moves():
    x = torch.arange(64, dtype=torch.float64)
    edge = lambda c: (0.1 + 0.8 * torch.sigmoid((x - c) / 1.5)).expand(1, 32, 64).clone()  # noqa: E731
    truth = predicted_events(edge(30), edge(33), LOSS)  # events of an edge moving 3 px
    losses = [event_loss(truth, edge(30), edge(30 + s), LOSS).event.item() for s in (3, 2, 1, 0, 6)]
    assert losses[0] == pytest.approx(0.0, abs=1e-12)
    assert losses[0] < losses[1] < losses[2] < losses[3] and losses[0] < losses[4]


def test_masks():
    a = torch.full((1, 50, 60), 0.9)
    a[0, 25, 30] = 0.8  # alpha ≤ 0.8 at the start: masked
    b = a.clone()
    b[0, 26, 31] = 0.5  # ... or at the end
    m = valid_mask(a, b, border=20, min_alpha=0.8)
    assert m.shape == a.shape and m.sum().item() == 10 * 20 - 2
    assert not m[0, 19, 30] and not m[0, 25, 30] and not m[0, 26, 31] and m[0, 22, 35]
    assert valid_mask(a, b).all()
    assert torch.equal(
        event_mask(torch.tensor([-0.3, 0.1, 0.0, 0.2]), 0.1), torch.tensor([True, False, False, True])
    )


def test_masked_loss_ignores_masked_pixels_and_event_threshold():
    start = blobs(7)[:1]
    end = blobs(8)[:1]
    events = predicted_events(start, end, LOSS)
    bad = events.clone()
    bad[0, :5] += 10.0  # corrupt the top rows
    mask = torch.ones_like(bad, dtype=torch.bool)
    mask[0, :5] = False
    assert event_loss(bad, start, end, LOSS, mask).event.item() == pytest.approx(0.0, abs=1e-12)
    assert event_loss(bad, start, end, LOSS).event.item() > 1.0
    sparse = torch.zeros_like(events)
    sparse[0, 10, 10] = 0.3
    thr = cfg(event_mask_threshold=0.1)
    e_hat = predicted_events(start, end, LOSS)
    want = abs(0.3 - e_hat[0, 10, 10].item())  # only the one pixel with events counts
    assert event_loss(sparse, start, end, thr).event.item() == pytest.approx(want, rel=1e-12)
    empty = torch.zeros_like(mask)
    assert event_loss(bad, start, end, LOSS, empty).event.item() == 0.0


def test_gradients_reach_both_renders():
    start = blobs(9).requires_grad_(True)
    end = blobs(10).requires_grad_(True)
    events = torch.zeros_like(start)
    event_loss(events, start, end, LOSS).total.backward()
    assert start.grad.abs().sum() > 0 and end.grad.abs().sum() > 0
    assert torch.isfinite(start.grad).all()


def test_shape_errors():
    with pytest.raises(ValueError, match="one shape"):
        event_loss(torch.zeros(1, 20, 20), torch.zeros(1, 20, 20), torch.zeros(1, 20, 21), LOSS)


def test_ssim_kernel_matches_the_torch_reference_and_finite_differences():
    """The Rust SSIM's value and gradient (computed in its forward pass) against torch autograd of the
    float64 reference (:mod:`evgs.slam.loss_torch`), and against finite differences (gradcheck)."""
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(2, 23, 29, dtype=torch.float64, generator=gen, requires_grad=True)
    b = (0.6 * a.detach() + 0.4 * torch.rand(2, 23, 29, dtype=torch.float64, generator=gen)).requires_grad_()
    w = torch.tensor([0.7, -1.3], dtype=torch.float64)  # a different upstream gradient per image
    got = ssim(a, b, 7, 1.2, 2.0)
    want = loss_torch.ssim(a, b, 7, 1.2, 2.0)
    assert torch.allclose(got, want, atol=1e-13)
    g_got = torch.autograd.grad((got * w).sum(), (a, b))
    g_want = torch.autograd.grad((want * w).sum(), (a, b))
    for x, y in zip(g_got, g_want, strict=True):
        assert torch.allclose(x, y, atol=1e-12)
    small = (a[:1, :9, :10].detach().requires_grad_(), b[:1, :9, :10].detach().requires_grad_())
    assert torch.autograd.gradcheck(lambda x, y: ssim(x, y, 5, 1.0), small)
    # Only the inputs that need a gradient get one; without any, no gradient is computed.
    c = b.detach()
    (ga,) = torch.autograd.grad(ssim(a, c).sum(), (a,))
    assert torch.allclose(ga, torch.autograd.grad(loss_torch.ssim(a, c).sum(), (a,))[0], atol=1e-12)
    assert not ssim(a.detach(), c).requires_grad


def test_ssim_in_float32_matches_float64_and_refuses_what_it_cannot_compute():
    gen = torch.Generator().manual_seed(1)
    a = torch.rand(2, 30, 41, dtype=torch.float64, generator=gen)
    b = 0.5 * a + 0.5 * torch.rand(2, 30, 41, dtype=torch.float64, generator=gen)
    got = ssim(a.float(), b.float())
    assert got.dtype == torch.float32 and got.shape == (2,)
    assert torch.allclose(got.double(), loss_torch.ssim(a, b), atol=1e-5)
    with pytest.raises(ValueError, match="float32 or float64"):
        ssim(a.to(torch.int32), b.to(torch.int32))
    with pytest.raises(ValueError, match="one dtype"):
        ssim(a, b.float())


def test_depth_variation_kernel_matches_the_torch_reference():
    """The Rust relief prior's value and gradient against torch autograd of the float64 reference, on
    views with transparent pixels, and in float32."""
    gen = torch.Generator().manual_seed(4)
    alpha = torch.rand((2, 11, 13), dtype=torch.float64, generator=gen)  # about half opaque
    depth = ((torch.rand((2, 11, 13), dtype=torch.float64, generator=gen) + 2) * alpha).requires_grad_()
    alpha.requires_grad_()
    got, want = depth_variation(depth, alpha), loss_torch.depth_variation(depth, alpha)
    assert got.item() == pytest.approx(want.item(), rel=1e-12)
    for x, y in zip(
        torch.autograd.grad(got, (depth, alpha)), torch.autograd.grad(want, (depth, alpha)), strict=True
    ):
        assert torch.allclose(x, y, atol=1e-12)
    got32 = depth_variation(depth.detach().float(), alpha.detach().float())
    assert got32.dtype == torch.float32 and got32.item() == pytest.approx(want.item(), rel=1e-5)
    with pytest.raises(ValueError, match="one shape"):
        depth_variation(depth, alpha[:1])

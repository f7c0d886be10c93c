"""Image metrics: PSNR/SSIM conventions against independent references, LPIPS properties."""

import numpy as np
import pytest
import torch
from evgs.eval.images import LPIPS, evaluate_images, lpips, psnr, ssim
from scipy.ndimage import gaussian_filter


def smooth_image(rng, shape=(64, 64)):
    img = gaussian_filter(rng.random(shape), 2.0)
    return (img - img.min()) / (img.max() - img.min())


def reference_ssim(x, y):
    """Wang et al. SSIM, Gaussian σ = 1.5 truncated at 11×11, population statistics, border of 5 px
    excluded (the window must lie inside the image), data range 1."""

    def f(a):
        return gaussian_filter(a, 1.5, truncate=5 / 1.5, mode="reflect")

    c1, c2 = 0.01**2, 0.03**2
    mx, my = f(x), f(y)
    vx, vy, cxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return s[5:-5, 5:-5].mean()


def test_psnr_hand_computed():
    a = np.zeros((8, 8))
    assert psnr(a + 0.1, a) == pytest.approx(20.0)
    assert psnr(a, a) == float("inf")


def test_ssim_matches_gaussian_window_reference():
    rng = np.random.default_rng(0)
    x = smooth_image(rng)
    y = np.clip(x + 0.05 * rng.normal(size=x.shape), 0, 1)
    assert ssim(y, x) == pytest.approx(reference_ssim(y, x), abs=1e-9)
    assert ssim(x, x) == pytest.approx(1.0)


@pytest.fixture(scope="module")
def distorted():
    rng = np.random.default_rng(1)
    ref = np.stack([smooth_image(rng) for _ in range(2)])
    noise = rng.normal(size=ref.shape)
    levels = [0.0, 0.02, 0.05, 0.1, 0.2]
    return ref, [np.clip(ref + s * noise, 0, 1) for s in levels]


def test_lpips_identity_symmetry_and_monotonic_noise(distorted):
    ref, imgs = distorted
    d = [lpips(img, ref) for img in imgs]
    np.testing.assert_array_equal(d[0], 0.0)
    for a, b in zip(d, d[1:], strict=False):
        assert np.all(b > a)
    np.testing.assert_allclose(lpips(ref, imgs[3]), d[3], rtol=1e-5)
    assert np.all(d[-1] < 1.5)


def test_lpips_monotonic_under_blur():
    rng = np.random.default_rng(2)
    ref = rng.random((1, 64, 96))
    d = [float(lpips(gaussian_filter(ref, (0, s, s)), ref)[0]) for s in (0.5, 1.0, 2.0, 4.0)]
    assert all(b > a for a, b in zip(d, d[1:], strict=False))


def test_lpips_grey_equals_replicated_rgb(distorted):
    ref, imgs = distorted
    rgb = lambda a: np.repeat(a[..., None], 3, axis=-1)  # noqa: E731
    np.testing.assert_allclose(lpips(rgb(imgs[2]), rgb(ref)), lpips(imgs[2], ref), rtol=1e-6)


def test_lpips_is_differentiable_and_checks_size():
    net = LPIPS()
    x = torch.rand(1, 3, 40, 40, requires_grad=True)
    net(x * 2 - 1, torch.zeros(1, 3, 40, 40)).sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    with pytest.raises(ValueError, match="at least"):
        net(torch.zeros(1, 3, 16, 16), torch.zeros(1, 3, 16, 16))


def test_evaluate_images_summary(distorted):
    ref, imgs = distorted
    m = evaluate_images(imgs[2], ref)
    assert m.psnr.shape == m.ssim.shape == m.lpips.shape == (2,)
    s = m.summary()
    assert s["psnr_db"] == pytest.approx(np.mean([psnr(a, b) for a, b in zip(imgs[2], ref, strict=True)]))
    assert 0 < s["ssim"] < 1 and 0 < s["lpips"] < 1
    with pytest.raises(ValueError, match="need equal"):
        evaluate_images(imgs[2], ref[:1])

"""The tile-based pure-torch rasterizer (the benchmark's torch baseline) against the dense float64 reference:
the same image in float32, and in float64 the same gradients (the same algorithm, reordered)."""

from __future__ import annotations

import pytest
import torch
from raster_reference import render_reference
from raster_tile_torch import render_tiles
from test_raster import CAM, as64, edge_scene, loss_weights, scene, views, weighted_loss


def assert_images_close(got: tuple, want: tuple) -> None:
    for name, g, w, atol in zip(("color", "depth", "alpha"), got, want, (1e-5, 4e-5, 1e-5), strict=False):
        torch.testing.assert_close(g.double(), w.detach(), rtol=0, atol=atol, msg=name)
    assert torch.equal(got[3], want[3])


@pytest.mark.parametrize("channels", [1, 3])
def test_float32_image_matches_reference(channels: int) -> None:
    g, vm = scene(40, channels), views(2)
    out = render_tiles(**g, viewmats=vm, camera=CAM, background=0.25)
    ref = render_reference(**as64(g), viewmats=vm.double(), camera=CAM, background=0.25)
    assert out[0].dtype == torch.float32 and out[0].shape == (2, CAM.height, CAM.width, channels)
    assert ref[2].max() > 0.5  # the scene covers the image
    assert_images_close(out, ref)


def test_edge_cases_match_reference() -> None:
    g, vm = edge_scene(), views(1)
    assert_images_close(
        render_tiles(**g, viewmats=vm, camera=CAM),
        render_reference(**as64(g), viewmats=vm.double(), camera=CAM),
    )


def test_float64_gradients_equal_reference() -> None:
    g, vm = scene(30, 3, seed=3), views(2)
    w = [x.double() for x in loss_weights(2, 3)]
    grads = []
    for renderer in (render_tiles, render_reference):
        params, vm64 = as64(g), vm.double().requires_grad_()
        out = renderer(**params, viewmats=vm64, camera=CAM, background=0.1)
        weighted_loss(out[0], out[1], out[2], w).backward()
        grads.append([*(params[k].grad for k in g), vm64.grad])
    for name, got, want in zip([*g, "viewmats"], *grads, strict=True):
        assert want.abs().max() > 0, name
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9 * want.abs().max().item(), msg=name)

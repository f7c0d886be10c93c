"""Guard logic: brightness anchor, colour clamp, blocker detection (the end-to-end demonstrations
with the rasterizer belong to the pipeline tests)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from evgs.config import load_config
from evgs.data.sequence import Camera
from evgs.slam.gaussians import Gaussians
from evgs.slam.guards import (
    BrightnessAnchor,
    blocker_mask,
    clamp_colors_,
    large_footprint_mask,
    near_camera_mask,
    surface_brightness,
)
from evgs.slam.lie import se3_exp
from evgs.slam.loss import event_loss, predicted_events

CAM = Camera(64, 48, 50.0, 50.0, 32.0, 24.0)
LOSS = dataclasses.replace(load_config().loss, log_eps=0.0, lambda_ssim=0.0)


def scene() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Two renders of a dim blob (start, end) and its alpha; black background."""
    y, x = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    alpha = torch.exp(-((x - 30) ** 2 + (y - 24) ** 2) / 200)[None].double()
    alpha_end = torch.exp(-((x - 33) ** 2 + (y - 24) ** 2) / 200)[None].double()
    return 0.3 * alpha + 1e-3, 0.3 * alpha_end + 1e-3, alpha


def test_event_loss_cannot_see_global_brightness_but_the_anchor_can():
    start, end, alpha = scene()
    events = predicted_events(start, end, LOSS)
    k = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    for value in (1.0, 2.5):  # the failure mode: any brightness scale explains the events equally well
        with torch.no_grad():
            k.fill_(value)
        loss = event_loss(events, k * start, k * end, LOSS).total
        k.grad = None
        loss.backward()
        assert loss.item() == pytest.approx(0.0, abs=1e-12) and k.grad.abs().item() < 1e-12
    anchor = BrightnessAnchor(weight=1.0)
    assert anchor.penalty(start, alpha).item() == 0.0  # inactive until a reference is set
    anchor.set_reference(start, alpha)
    assert anchor.penalty(start, alpha).item() == pytest.approx(0.0, abs=1e-12)
    k.grad = None
    anchor.penalty(k * start, alpha).backward()  # k = 2.5: brighter than the reference
    assert anchor.penalty(k * start, alpha).item() == pytest.approx(1.5**2, rel=1e-9)
    assert k.grad.item() > 0  # gradient descent pulls the brightness back down
    assert BrightnessAnchor(weight=0.0, reference=1.0).penalty(start, alpha).item() == 0.0


def test_surface_brightness_is_the_mean_colour_seen():
    alpha = torch.tensor([[[1.0, 0.5, 0.0]]])
    color = 0.4 * alpha  # uniform colour 0.4 composited over black
    assert surface_brightness(color, alpha).item() == pytest.approx(0.4)


def test_clamp_colors():
    g = Gaussians.random(6, 1.0, 0.1, 0.1, torch.Generator().manual_seed(0))
    with torch.no_grad():
        g["colors"][:, 0] = torch.tensor([-0.2, 0.0, 0.3, 0.8, 1.2, 5.0])
    clamp_colors_(g, 0.8)
    assert g["colors"][:, 0].tolist() == pytest.approx([0.0, 0.0, 0.3, 0.8, 0.8, 0.8])


def test_near_camera_mask_only_flags_close_in_front_and_in_view():
    T = se3_exp(torch.tensor([0.5, -1.0, 2.0, 0.3, -0.2, 0.4], dtype=torch.float64))
    local = torch.tensor(
        [
            [0.0, 0.0, 0.05],  # close, centred: flagged
            [0.0, 0.0, 0.5],  # far enough
            [0.0, 0.0, -0.05],  # close but behind
            [1.0, 0.0, 0.05],  # close but far outside the image
            [0.02, 0.01, 0.08],  # close, inside the image: flagged
        ],
        dtype=torch.float64,
    )
    world = local @ T[:3, :3].T + T[:3, 3]
    mask = near_camera_mask(world.float(), T[None], CAM, margin=0.1)
    assert mask.tolist() == [True, False, False, False, True]
    other = se3_exp(torch.tensor([0.0, 0, 5, 0, 0, 0], dtype=torch.float64))  # a second, distant view
    assert near_camera_mask(world.float(), torch.stack([other, T]), CAM, 0.1).tolist() == mask.tolist()


def test_large_footprint_mask_needs_size_and_opacity():
    radii = torch.tensor([[3, 30, 30, 0], [2, 5, 13, 20]], dtype=torch.int32)
    opac = torch.tensor([0.9, 0.9, 0.2, 0.9])
    # limit = 0.25 · min(64, 48) = 12 px
    assert large_footprint_mask(radii, opac, CAM, 0.25, 0.5).tolist() == [False, True, False, True]


def test_blocker_mask_combines_both():
    g = Gaussians.random(4, 1.0, 0.9, 0.1, torch.Generator().manual_seed(0))
    with torch.no_grad():
        g["means"][:] = torch.tensor([[0, 0, 0.05], [0, 0, 2.0], [0, 0, 3.0], [0, 0, 4.0]])
    T = torch.eye(4, dtype=torch.float64)[None]
    radii = torch.tensor([[40, 40, 1, 1]], dtype=torch.int32)
    assert blocker_mask(g, T, CAM, near_margin=0.1).tolist() == [True, False, False, False]
    both = blocker_mask(
        g, T, CAM, near_margin=0.1, radii=radii, max_footprint=0.25, footprint_min_opacity=0.5
    )
    assert both.tolist() == [True, True, False, False]

"""The rendered mean depth and its median over the opaque pixels (the view's depth scale)."""

from __future__ import annotations

import pytest
import torch
from evgs.slam.depth import mean_depth, median_depth


def test_median_depth_is_over_the_opaque_pixels_mean_depths():
    alpha = torch.tensor([[1.0, 0.8, 0.1], [0.0, 0.9, 1.0]])
    depth = torch.tensor([[2.0, 1.6, 9.0], [0.0, 4.5, 3.0]])  # D = z·α: z = 2, 2, 90, –, 5, 3
    assert float(median_depth(depth, alpha)) == pytest.approx(2.0)
    assert float(median_depth(depth, alpha, min_alpha=0.85)) == pytest.approx(3.0)  # z = 2, 5, 3
    assert median_depth(depth, torch.zeros_like(alpha)) is None


def test_mean_depth_stays_finite_on_transparent_pixels_and_marks_the_opaque():
    alpha = torch.tensor([0.0, 0.25, 1.0], dtype=torch.float64, requires_grad=True)
    depth = torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64)
    mean, opaque = mean_depth(depth, alpha)
    assert mean.tolist() == [0.0, 2.0, 3.0]  # α clamped at 0.5 below it
    assert opaque.tolist() == [False, False, True]
    mean.sum().backward()
    assert alpha.grad.tolist() == [0.0, 0.0, -3.0]  # no gradient through the clamp

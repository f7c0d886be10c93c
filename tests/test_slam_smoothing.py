"""The fixed-interval smoother over the tracked positions: its cost minimised (autograd), its null space,
its frequency response, and the trajectory's rotations left alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from evgs.slam.lie import se3_exp
from evgs.slam.smoothing import second_differences, smooth_positions, smooth_trajectory
from evgs.slam.trajectory import Trajectory

D = torch.float64


def uneven_times(n: int, seed: int = 0) -> np.ndarray:
    """Strictly increasing times (s) whose steps vary by ± 40 % around 40 ms."""
    steps = 0.04 * (1 + 0.4 * np.random.default_rng(seed).uniform(-1, 1, n - 1))
    return np.concatenate([[0.0], np.cumsum(steps)])


def cost(p: torch.Tensor, p_hat: torch.Tensor, t: torch.Tensor, tau: float) -> torch.Tensor:
    """The module's cost written out term by term, in float64 (the reference the solver must minimise)."""
    h = t[1:] - t[:-1]
    v = (p[1:] - p[:-1]) / h[:, None]
    a = 2 * (v[1:] - v[:-1]) / (h[1:] + h[:-1])[:, None]
    share = 0.5 * (h[1:] + h[:-1]) / h.mean()
    return ((p - p_hat) ** 2).sum() + tau**4 * (share[:, None] * a**2).sum()


def test_second_differences_match_a_quadratic_exactly():
    t = uneven_times(12)
    # x(t) = 3t² − t + 2 has acceleration 6 everywhere, whatever the spacing
    x = 3 * t**2 - t + 2
    assert np.allclose(second_differences(t) @ x, 6.0, atol=1e-9)


def test_smoothed_positions_minimise_the_cost():
    t = uneven_times(40, seed=1)
    rng = np.random.default_rng(2)
    p_hat = np.stack([np.sin(3 * t), np.cos(2 * t), t**2], 1) + 0.02 * rng.normal(size=(40, 3))
    tau = 0.2
    p = torch.tensor(smooth_positions(t, p_hat, tau), dtype=D, requires_grad=True)
    c = cost(p, torch.tensor(p_hat), torch.tensor(t), tau)
    (grad,) = torch.autograd.grad(c, p)
    assert float(grad.abs().max()) < 1e-9 * float(c.detach())
    # and a finite step off the solution costs more, in every direction tried
    with torch.no_grad():
        for _ in range(5):
            step = torch.tensor(rng.normal(size=(40, 3)) * 1e-3)
            assert float(cost(p + step, torch.tensor(p_hat), torch.tensor(t), tau)) > float(c.detach())


def test_constant_velocity_is_kept_and_noise_is_removed():
    t = uneven_times(60, seed=3)
    line = np.outer(t, [0.5, -0.2, 1.0]) + np.array([1.0, 2.0, 3.0])
    assert np.allclose(smooth_positions(t, line, 0.3), line, atol=1e-10)
    noisy = line + 0.01 * np.random.default_rng(4).normal(size=line.shape)
    err_before = np.abs(noisy - line).mean()
    err_after = np.abs(smooth_positions(t, noisy, 0.3) - line).mean()
    assert err_after < 0.35 * err_before
    assert np.array_equal(smooth_positions(t, noisy, 0.0), noisy)
    assert np.array_equal(smooth_positions(t[:2], noisy[:2], 0.3), noisy[:2])


@pytest.mark.parametrize(("period_over_tau", "kept"), [(2 * np.pi, 0.5), (60.0, 0.999), (1.5, 0.005)])
def test_frequency_response_halves_a_period_of_two_pi_tau(period_over_tau: float, kept: float):
    """Far from the ends, a sinusoid of period P keeps 1 / (1 + (2πτ/P)⁴) of its amplitude on uniform
    frames (to the order of the frame step): half at P = 2πτ, as the docstring says."""
    tau, dt = 0.2, 0.002
    t = np.arange(6000) * dt
    x = np.sin(2 * np.pi * t / (period_over_tau * tau))
    y = smooth_positions(t, np.stack([x, x, x], 1), tau)[:, 0]
    mid = slice(2000, 4000)
    gain = (y[mid] @ x[mid]) / (x[mid] @ x[mid])
    assert gain == pytest.approx(kept, rel=0.02, abs=2e-3)


def test_smooth_trajectory_moves_positions_only():
    t_us = np.round(uneven_times(20, seed=5) * 1e6).astype(np.int64)
    g = torch.Generator().manual_seed(6)
    T = se3_exp(torch.randn(20, 6, generator=g, dtype=D) * 0.3)
    traj = Trajectory(t_us, T)
    with torch.no_grad():
        traj.delta[3] = torch.tensor([0.01, 0.0, -0.02, 0.001, 0.0, 0.0], dtype=D)  # folded in first
    before = traj.knots().detach().clone()
    moved = smooth_trajectory(traj, 0.1)
    after = traj.knots().detach()
    assert torch.allclose(after[:, :3, :3], before[:, :3, :3], atol=1e-9)
    want = smooth_positions(t_us * 1e-6, before[:, :3, 3].numpy(), 0.1)
    assert np.allclose(after[:, :3, 3].numpy(), want, atol=1e-12)
    assert moved == pytest.approx(float(np.linalg.norm(want - before[:, :3, 3].numpy(), axis=1).max()))
    assert float(traj.delta.detach().abs().max()) == 0.0

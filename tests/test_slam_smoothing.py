"""The fixed-interval smoother over the tracked positions: its cost minimised (autograd), its null space,
its frequency response, at the prior's orders 2 and 3, and the trajectory's rotations left alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from evgs.slam.lie import se3_exp
from evgs.slam.smoothing import divided_differences, end_extension, smooth_positions, smooth_trajectory
from evgs.slam.trajectory import Trajectory

D = torch.float64


def uneven_times(n: int, seed: int = 0) -> np.ndarray:
    """Strictly increasing times (s) whose steps vary by ± 40 % around 40 ms."""
    steps = 0.04 * (1 + 0.4 * np.random.default_rng(seed).uniform(-1, 1, n - 1))
    return np.concatenate([[0.0], np.cumsum(steps)])


def cost(p: torch.Tensor, p_hat: torch.Tensor, t: torch.Tensor, tau: float, order: int) -> torch.Tensor:
    """The module's cost written out from the divided-difference recursion, in float64 (the reference
    the solver must minimise)."""
    d, span = p, None
    for j in range(1, order + 1):
        span = t[j:] - t[:-j]
        d = j * (d[1:] - d[:-1]) / span[:, None]
    h = t[1:] - t[:-1]
    share = span / (order * h.mean())
    return ((p - p_hat) ** 2).sum() + tau ** (2 * order) * (share[:, None] * d**2).sum()


def test_second_differences_are_the_acceleration():
    """Order 2 is the acceleration ``2 / (h₀ + h₁) · ((p₊ − p)/h₁ − (p − p₋)/h₀)`` at each interior knot."""
    t = uneven_times(12)
    x = np.random.default_rng(7).normal(size=12)
    h = np.diff(t)
    want = 2 / (h[:-1] + h[1:]) * ((x[2:] - x[1:-1]) / h[1:] - (x[1:-1] - x[:-2]) / h[:-1])
    assert np.allclose(divided_differences(t, 2) @ x, want, rtol=1e-12)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_divided_differences_match_a_polynomial_exactly(order: int):
    """The ``order``-th derivative of a polynomial of that degree, whatever the spacing: x(t) = c tᵐ + …
    has ``m! c`` everywhere."""
    t = uneven_times(14)
    x = 3 * t**order - t ** (order - 1) + 2
    want = 3.0 * np.prod(np.arange(1, order + 1))
    assert divided_differences(t, order).shape == (14 - order, 14)
    assert np.allclose(divided_differences(t, order) @ x, want, rtol=1e-7)


@pytest.mark.parametrize("order", [2, 3])
def test_smoothed_positions_minimise_the_cost(order: int):
    t = uneven_times(40, seed=1)
    rng = np.random.default_rng(2)
    p_hat = np.stack([np.sin(3 * t), np.cos(2 * t), t**2], 1) + 0.02 * rng.normal(size=(40, 3))
    tau = 0.2
    p = torch.tensor(smooth_positions(t, p_hat, tau, order), dtype=D, requires_grad=True)
    c = cost(p, torch.tensor(p_hat), torch.tensor(t), tau, order)
    (grad,) = torch.autograd.grad(c, p)
    # the normal equations' condition number grows as (τ/h)²ᵐ: 1e-9 of the cost at order 2, 1e-8 at 3
    assert float(grad.abs().max()) < 10.0 ** (order - 11) * float(c.detach())
    # and a finite step off the solution costs more, in every direction tried
    with torch.no_grad():
        for _ in range(5):
            step = torch.tensor(rng.normal(size=(40, 3)) * 1e-3)
            assert float(cost(p + step, torch.tensor(p_hat), torch.tensor(t), tau, order)) > float(c.detach())


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


def test_order_three_keeps_a_constant_acceleration():
    """White noise on jerk: a constant acceleration is its null space (order 2 would bend it)."""
    t = uneven_times(60, seed=8)
    curve = np.outer(t**2, [0.4, -1.0, 0.2]) + np.outer(t, [0.5, -0.2, 1.0])
    assert np.allclose(smooth_positions(t, curve, 0.3, order=3), curve, atol=1e-9)
    assert not np.allclose(smooth_positions(t, curve, 0.3, order=2), curve, atol=1e-4)
    assert np.array_equal(smooth_positions(t[:3], curve[:3], 0.3, order=3), curve[:3])


@pytest.mark.parametrize("order", [2, 3])
@pytest.mark.parametrize("period_over_tau", [2 * np.pi, 60.0, 1.5])
def test_frequency_response_halves_a_period_of_two_pi_tau(period_over_tau: float, order: int):
    """Far from the ends, a sinusoid of period P keeps 1 / (1 + (2πτ/P)²ᵐ) of its amplitude on uniform
    frames (to the order of the frame step): half at P = 2πτ at either order, as the docstring says,
    and the higher order keeps more of the slow motion and less of the fast."""
    tau, dt = 0.2, 0.002
    t = np.arange(6000) * dt
    x = np.sin(2 * np.pi * t / (period_over_tau * tau))
    y = smooth_positions(t, np.stack([x, x, x], 1), tau, order)[:, 0]
    mid = slice(2000, 4000)
    gain = (y[mid] @ x[mid]) / (x[mid] @ x[mid])
    kept = 1 / (1 + (2 * np.pi / period_over_tau) ** (2 * order))
    assert gain == pytest.approx(kept, rel=0.02, abs=2e-3)


def test_smooth_trajectory_moves_positions_only():
    t_us = np.round(uneven_times(20, seed=5) * 1e6).astype(np.int64)
    g = torch.Generator().manual_seed(6)
    T = se3_exp(torch.randn(20, 6, generator=g, dtype=D) * 0.3)
    traj = Trajectory(t_us, T)
    with torch.no_grad():
        traj.delta[3] = torch.tensor([0.01, 0.0, -0.02, 0.001, 0.0, 0.0], dtype=D)  # folded in first
    before = traj.knots().detach().clone()
    moved = smooth_trajectory(traj, 0.1, order=3)
    after = traj.knots().detach()
    assert torch.allclose(after[:, :3, :3], before[:, :3, :3], atol=1e-9)
    want = smooth_positions(t_us * 1e-6, before[:, :3, 3].numpy(), 0.1, order=3)
    assert np.allclose(after[:, :3, 3].numpy(), want, atol=1e-12)
    assert moved == pytest.approx(float(np.linalg.norm(want - before[:, :3, 3].numpy(), axis=1).max()))
    assert float(traj.delta.detach().abs().max()) == 0.0


def test_end_extension_is_the_least_squares_polynomial():
    """The fit through the knots within ``fit_s`` of the end (at least degree + 1 of them), against
    float64 least squares on the Vandermonde matrix, evaluated past the end."""
    t = uneven_times(30, seed=9)
    p = np.random.default_rng(10).normal(size=(30, 3))
    out = t[0] - np.array([0.12, 0.04])
    n = int((t - t[0] <= 0.3).sum())
    V = np.vander(t[:n] - t[0], 3, increasing=True)
    coef = np.linalg.lstsq(V, p[:n], rcond=None)[0]
    want = np.vander(out - t[0], 3, increasing=True) @ coef
    assert np.allclose(end_extension(t, p, 0.3, 2, out), want, atol=1e-10)
    # a span holding a single knot still fits through degree + 1 of them
    V = np.vander(t[:3] - t[0], 3, increasing=True)
    want = np.vander(out - t[0], 3, increasing=True) @ np.linalg.solve(V, p[:3])
    assert np.allclose(end_extension(t, p, 0.0, 2, out), want, atol=1e-8)


@pytest.mark.parametrize("order", [2, 3])
def test_end_fit_keeps_the_priors_null_space(order: int):
    """A polynomial of degree below the order is extended by itself, so it is kept exactly."""
    t = uneven_times(50, seed=11)
    curve = np.outer(t, [0.5, -0.2, 1.0]) + (order - 2) * np.outer(t**2, [0.4, -1.0, 0.2]) + 1.0
    assert np.allclose(smooth_positions(t, curve, 0.3, order, end_fit=2.0), curve, atol=1e-8)


def test_end_fit_is_the_same_backwards_in_time():
    t = uneven_times(40, seed=12)
    p = np.stack([np.sin(3 * t), np.cos(2 * t), t**3], 1)
    p += 0.01 * np.random.default_rng(13).normal(size=p.shape)
    forward = smooth_positions(t, p, 0.25, 3, end_fit=2.0)
    backward = smooth_positions(-t[::-1], p[::-1], 0.25, 3, end_fit=2.0)[::-1]
    assert np.allclose(forward, backward, atol=1e-9)


def test_end_fit_keeps_the_swirls_ends_and_still_removes_noise():
    """The simulated swirl (fastest at its ends, sideways): with the ends extended, the smoother moves
    the true path's end knots far less at the same τ, and still removes most of a wander added to it."""
    from evgs.sim.presets import preset
    from evgs.sim.trajectory import Trajectory as SimTrajectory

    c = preset("swirl_good")
    t = np.arange(76) / 25.0
    path = SimTrajectory(c.trajectory, c.distance, c.speed, c.duration, c.elevation_deg, c.azimuth_deg)
    truth = path.positions(t)
    natural = np.linalg.norm(smooth_positions(t, truth, 0.3, 3) - truth, axis=1)
    ends = np.linalg.norm(smooth_positions(t, truth, 0.3, 3, end_fit=2.0) - truth, axis=1)
    assert ends[[0, -1]].max() < 0.2 * natural[[0, -1]].min()
    assert np.sqrt((ends**2).mean()) < 0.6 * np.sqrt((natural**2).mean())
    wander = 0.03 * np.random.default_rng(14).normal(size=truth.shape)
    err = np.linalg.norm(smooth_positions(t, truth + wander, 0.3, 3, end_fit=2.0) - truth, axis=1)
    assert np.sqrt((err**2).mean()) < 0.5 * np.sqrt((np.linalg.norm(wander, axis=1) ** 2).mean())

"""A fixed-interval smoother over the tracked camera positions (``trajectory.smoothing_time``).

Tracking estimates each knot from a few frames' events on a map still being built, so the positions
wander at periods of 10–30 frames along the directions the events see least: the looming, and the
valley where a sideways step and a turn explain the events alike (docs/ablations.md §42, §57, §63). A
spacecraft's path is smooth at those periods: thrusters and orbital dynamics change its velocity slowly.
So before the final global BA the positions ``p̂`` are replaced by the minimiser of

    Σₖ ‖pₖ − p̂ₖ‖² + τ⁴ Σₖ wₖ ‖aₖ‖²,

the most probable path under a white-noise-on-acceleration prior, every tracked position trusted alike.
``aₖ`` is the second divided difference at interior knot ``k`` and ``wₖ`` its share of the time (the
mean of its two intervals over the mean interval: 1 on uniform frames). On uniform frames a sinusoid of
period ``2πτ`` keeps half its amplitude, slower motion nearly all of it, faster motion little, and a
constant velocity is kept exactly. Rotations stay as tracked: the events see the turn directly, and
smoothing it did not lower the drift (§63). The final global BA then refits the map to the smoothed path.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import spsolve

from evgs.slam.trajectory import Trajectory


def second_differences(t_s: np.ndarray) -> sp.csr_matrix:
    """(K−2, K) sparse operator: the acceleration at each interior knot from the positions at times
    ``t_s`` (seconds, strictly increasing), ``2 / (h₀ + h₁) · ((p₊ − p)/h₁ − (p − p₋)/h₀)``."""
    h = np.diff(np.asarray(t_s, np.float64))
    h0, h1 = h[:-1], h[1:]
    c = 2.0 / (h0 + h1)
    rows = np.repeat(np.arange(len(h0)), 3)
    cols = (np.arange(len(h0))[:, None] + np.arange(3)).ravel()
    vals = np.stack([c / h0, -c * (1 / h0 + 1 / h1), c / h1], 1).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(h0), len(t_s)))


def smooth_positions(t_s: np.ndarray, positions: np.ndarray, tau_s: float) -> np.ndarray:
    """The minimiser of the module's cost: (K, 3) positions at times ``t_s`` (seconds), smoothing time
    ``tau_s`` (seconds). Fewer than three knots or ``tau_s = 0`` return a copy."""
    p = np.array(positions, np.float64)
    if len(p) < 3 or tau_s == 0:
        return p
    D = second_differences(t_s)
    h = np.diff(t_s)
    share = 0.5 * (h[:-1] + h[1:]) / h.mean()
    A = (sp.identity(len(p)) + tau_s**4 * (D.T @ sp.diags(share) @ D)).tocsc()
    return np.asarray(spsolve(A, p)).reshape(p.shape)


@torch.no_grad()
def smooth_trajectory(traj: Trajectory, tau_s: float) -> float:
    """Replace the knots' positions by :func:`smooth_positions`' (rotations kept); the largest move, in
    the run's units."""
    traj.rebase()
    t_s = traj.t_us.numpy() * 1e-6
    before = traj.base[:, :3, 3].numpy().copy()
    after = smooth_positions(t_s, before, tau_s)
    traj.base[:, :3, 3] = torch.from_numpy(after)
    return float(np.linalg.norm(after - before, axis=1).max(initial=0.0))

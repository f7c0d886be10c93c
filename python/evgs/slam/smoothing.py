"""A fixed-interval smoother over the tracked camera positions (``trajectory.smoothing_time``).

Tracking estimates each knot from a few frames' events on a map still being built, so the positions
wander at periods of 10–30 frames along the directions the events see least: the looming, and the
valley where a sideways step and a turn explain the events alike (docs/ablations.md §42, §57, §63). A
spacecraft's path is smooth at those periods: thrusters and orbital dynamics change its velocity slowly.
So before the final global BA the positions ``p̂`` are replaced by the minimiser of

    Σₖ ‖pₖ − p̂ₖ‖² + τ²ᵐ Σₖ wₖ ‖dₖ‖²,

the most probable path under a white-noise prior on the m-th derivative (``trajectory.smoothing_order``:
2 = on acceleration, 3 = on jerk), every tracked position trusted alike. ``dₖ`` is the m-th derivative at
knot window ``k..k+m`` estimated from its divided difference (``m!`` times it) and ``wₖ`` the window's
share of the time (its span over m mean intervals: 1 on uniform frames). On uniform frames a sinusoid of
period ``2πτ`` keeps half its amplitude at either order, slower motion nearly all of it, faster motion
little, and a polynomial of degree below m is kept exactly. The higher order parts the two more sharply:
a turn five times slower than the wander loses (1/5)⁶ instead of (1/5)⁴ of what the wander loses, so
the swirl's sweep keeps its shape where the wander goes (§84). Rotations stay as tracked: the events see
the turn directly, and smoothing it did not lower the drift (§63). The final global BA then refits the
map to the smoothed path.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import spsolve

from evgs.slam.trajectory import Trajectory


def divided_differences(t_s: np.ndarray, order: int) -> sp.csr_matrix:
    """(K−order, K) sparse operator: the ``order``-th derivative over each window of ``order + 1`` knots
    at times ``t_s`` (seconds, strictly increasing), ``order!`` times the window's divided difference
    (exact for a polynomial of that degree, whatever the spacing)."""
    t = np.asarray(t_s, np.float64)
    D = sp.identity(len(t), format="csr")
    for j in range(1, order + 1):
        span = t[j:] - t[:-j]  # window k's span at this level: t[k+j] − t[k]
        D = sp.diags(j / span) @ (D[1:] - D[:-1])
    return D.tocsr()


def smooth_positions(t_s: np.ndarray, positions: np.ndarray, tau_s: float, order: int = 2) -> np.ndarray:
    """The minimiser of the module's cost: (K, 3) positions at times ``t_s`` (seconds), smoothing time
    ``tau_s`` (seconds), prior on the ``order``-th derivative. Fewer than ``order + 1`` knots or
    ``tau_s = 0`` return a copy."""
    p = np.array(positions, np.float64)
    if len(p) <= order or tau_s == 0:
        return p
    t = np.asarray(t_s, np.float64)
    D = divided_differences(t, order)
    share = (t[order:] - t[:-order]) / (order * np.diff(t).mean())
    A = (sp.identity(len(p)) + tau_s ** (2 * order) * (D.T @ sp.diags(share) @ D)).tocsc()
    return np.asarray(spsolve(A, p)).reshape(p.shape)


@torch.no_grad()
def smooth_trajectory(traj: Trajectory, tau_s: float, order: int = 2) -> float:
    """Replace the knots' positions by :func:`smooth_positions`' (rotations kept); the largest move, in
    the run's units."""
    traj.rebase()
    t_s = traj.t_us.numpy() * 1e-6
    before = traj.base[:, :3, 3].numpy().copy()
    after = smooth_positions(t_s, before, tau_s, order)
    traj.base[:, :3, 3] = torch.from_numpy(after)
    return float(np.linalg.norm(after - before, axis=1).max(initial=0.0))

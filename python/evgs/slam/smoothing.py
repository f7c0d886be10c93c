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

At the two ends the minimiser takes the m-th and higher derivatives to zero (the natural boundary), so
a path still turning there is bent: the swirl's sweep is fastest at its ends, and most of what the
smoother moved its truth was there (3.7 cm at the first and last frames, under 1.6 cm between). With
``trajectory.smoothing_end_fit`` = c the path is first extended past each end by the motion the prior
leaves free, the least-squares polynomial of degree m − 1 through the knots within c·τ of that end (as
seasonal adjustment extends a series by its forecast before filtering), smoothed with it, and the
extension dropped: the ends keep their local acceleration (order 3) instead of losing it, and the same
cost to the truth allows a longer τ (§85).
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


EXTENSION_TAUS = 5.0
"""How far (in τ) the path is extended past each end with ``end_fit``: the smoother's reach is a few τ,
so the extension's own far end no longer moves the knots (at 2.5 τ it still moved the swirl's truth
3 % more, at 5 τ under 0.1 %)."""


def end_extension(t: np.ndarray, p: np.ndarray, fit_s: float, degree: int, out_t: np.ndarray) -> np.ndarray:
    """(len(out_t), 3): the least-squares polynomial of ``degree`` through the knots within ``fit_s`` of
    ``t[0]`` (at least ``degree + 1`` of them), evaluated at ``out_t``; time is taken from ``t[0]``."""
    n = max(degree + 1, int(np.searchsorted(np.abs(t - t[0]), fit_s, side="right")))
    coef = np.polynomial.polynomial.polyfit(t[:n] - t[0], p[:n], degree)  # (degree + 1, 3)
    return np.polynomial.polynomial.polyval(out_t - t[0], coef).T


def extended(
    t: np.ndarray, p: np.ndarray, tau_s: float, order: int, end_fit: float
) -> tuple[np.ndarray, np.ndarray, int]:
    """The knots with ``P`` knots prepended and appended at the mean spacing, each end's continued by
    :func:`end_extension` (degree ``order − 1``: the prior's null space) fitted within ``end_fit · τ``;
    and ``P``."""
    dt = float(np.diff(t).mean())
    P = int(np.ceil(EXTENSION_TAUS * tau_s / dt))
    steps = dt * np.arange(1, P + 1)
    fit_s = end_fit * tau_s
    before = end_extension(t, p, fit_s, order - 1, t[0] - steps[::-1])
    after = end_extension(t[::-1], p[::-1], fit_s, order - 1, t[-1] + steps)
    return np.concatenate([t[0] - steps[::-1], t, t[-1] + steps]), np.concatenate([before, p, after]), P


def smooth_positions(
    t_s: np.ndarray, positions: np.ndarray, tau_s: float, order: int = 2, end_fit: float = 0.0
) -> np.ndarray:
    """The minimiser of the module's cost: (K, 3) positions at times ``t_s`` (seconds), smoothing time
    ``tau_s`` (seconds), prior on the ``order``-th derivative; with ``end_fit`` > 0 over the path
    extended past its ends (:func:`extended`). Fewer than ``order + 1`` knots or ``tau_s = 0`` return a
    copy."""
    p = np.array(positions, np.float64)
    if len(p) <= order or tau_s == 0:
        return p
    t = np.asarray(t_s, np.float64)
    if end_fit > 0:
        t_ext, p_ext, P = extended(t, p, tau_s, order, end_fit)
        return smooth_positions(t_ext, p_ext, tau_s, order)[P : P + len(p)]
    D = divided_differences(t, order)
    share = (t[order:] - t[:-order]) / (order * np.diff(t).mean())
    A = (sp.identity(len(p)) + tau_s ** (2 * order) * (D.T @ sp.diags(share) @ D)).tocsc()
    return np.asarray(spsolve(A, p)).reshape(p.shape)


@torch.no_grad()
def smooth_trajectory(traj: Trajectory, tau_s: float, order: int = 2, end_fit: float = 0.0) -> float:
    """Replace the knots' positions by :func:`smooth_positions`' (rotations kept); the largest move, in
    the run's units."""
    traj.rebase()
    t_s = traj.t_us.numpy() * 1e-6
    before = traj.base[:, :3, 3].numpy().copy()
    after = smooth_positions(t_s, before, tau_s, order, end_fit)
    traj.base[:, :3, 3] = torch.from_numpy(after)
    return float(np.linalg.norm(after - before, axis=1).max(initial=0.0))

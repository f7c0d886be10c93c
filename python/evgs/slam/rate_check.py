"""The tracked motion's speed, checked over the whole run before the final global BA.

The motion search sizes the start's speed on its first few frames, on a ladder of ×2 rungs, and where
the initialization holds its knots on the winner and tracking's velocity prior carries it on, the run
keeps that rung's speed: ``make run``'s orbit turns at 0.95 of the truth's for all its 40 frames, which
the Sim(3) alignment reads as a 5 % scale error (docs/ablations.md §76). Over a few frames a slower turn
and a deeper relief explain the events equally well (the bas-relief trade); over the whole run's
baseline they no longer do.

So with ``global_ba.rate_check`` = r the tracked knots' motion from the first knot is scaled by each of
1 − r, 1 − r/2, 1, 1 + r/2, 1 + r (:func:`~evgs.slam.trajectory.scaled_motion`: for a steady motion, the
same path at that speed), and each is scored as the motion search scores a hypothesis: the seeded map
refitted ``global_ba.rate_check_steps`` iterations to the held knots, on the fixed schedule (so that the
score changes smoothly with the factor), then its event term on fixed windows of all chunks. A single
score is noisy to a few per cent, and the scores rise more steeply below the best speed than above it
(a least-squares parabola through all five is pulled towards the faster end), so the factor applied is
the vertex of the parabola through the best factor and its two neighbours, within half a step of the
best (docs/ablations.md §80). With ``global_ba.rate_check_seedings`` = k each speed's score is the mean
of k refits, the first from the run's seeding, the others from seedings and random streams of their own
(:func:`replica_seed`), so that one refit's luck does not pick the speed (docs/ablations.md §91).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch

from evgs.slam.gaussians import Gaussians
from evgs.slam.motion_search import fit
from evgs.slam.optimize import StageReporter, fixed_window_loss
from evgs.slam.seeding import seeded_map
from evgs.slam.state import SlamState, StageRecord, stage_seed
from evgs.slam.trajectory import scaled_motion

# Fixed windows each factor is scored on: they are drawn from all of the run's chunks, so more than the
# search's 8.
SCORE_WINDOWS = 16


def rate_factors(r: float) -> np.ndarray:
    """The five speeds scored, as factors of the tracked one."""
    return 1.0 + r * np.array([-1.0, -0.5, 0.0, 0.5, 1.0])


def replica_seed(seed: int, j: int) -> int:
    """The seed of refit ``j`` of each speed: the run's own for ``j`` = 0, an independent stream of the
    rate check's for ``j`` > 0 (it draws that refit's seeding of the map and its windows)."""
    return seed if j == 0 else stage_seed(seed, "rate", j)


def parabola_vertex(factors: np.ndarray, scores: np.ndarray) -> float:
    """Where the parabola through the best-scoring factor and its two neighbours (``factors`` evenly
    spaced, ascending) is lowest; the best factor itself when it is at an end of the range."""
    i = int(np.argmin(scores))
    if i in (0, len(scores) - 1):
        return float(factors[i])
    lo, mid, hi = scores[i - 1 : i + 2]
    step = float(factors[i + 1] - factors[i])
    return float(factors[i] + 0.5 * step * (lo - hi) / (lo - 2 * mid + hi))


def check_rate(state: SlamState, seeded: Gaussians, reporter: StageReporter | None = None) -> StageRecord:
    """Score the tracked motion at each factor with ``seeded`` (the run's map as seeded) refitted to it,
    and with ``global_ba.rate_check_seedings`` − 1 other seedings, and scale ``state``'s trajectory by
    :func:`parabola_vertex` of the mean scores; the run's map is left as it is (the final global BA
    refits it to the new cameras)."""
    t0 = time.perf_counter()
    cfg, data = state.cfg, state.data
    gcfg = cfg.global_ba
    n = len(state.traj) - 1
    with torch.no_grad():
        knots = state.traj.knots().detach().clone()
    factors = rate_factors(gcfg.rate_check)
    seed, span = stage_seed(cfg.seed, "rate", 0), data.span(0, n)
    seeds = [replica_seed(cfg.seed, j) for j in range(gcfg.rate_check_seedings)]
    maps = [seeded] + [seeded_map(state, torch.Generator().manual_seed(s)) for s in seeds[1:]]
    scoring = state.with_relief_prior(gcfg.rate_check_depth_tv)
    starts = [dataclasses.replace(scoring, gaussians=g) for g in maps]
    scores = []
    for f in factors:
        motion, replicas = scaled_motion(knots, float(f)), []
        for s, start in zip(seeds, starts, strict=True):
            trial = fit(start, motion, reporter, gcfg.rate_check_steps, True, "rate", s)
            with torch.no_grad():
                replicas.append(fixed_window_loss(trial, span, seed, SCORE_WINDOWS))
        scores.append(float(np.mean(replicas)))
    best = parabola_vertex(factors, np.array(scores))
    with torch.no_grad():
        state.traj.base.copy_(scaled_motion(knots, best))
        state.traj.delta.zero_()
    tried = ", ".join(f"×{f:.3g} {s:.5f}" for f, s in zip(factors, scores, strict=True))
    record = StageRecord(
        "rate", cfg.data.start_frame + n, gcfg.rate_check_steps * len(factors) * len(seeds), min(scores),
        time.perf_counter() - t0, 0, False, len(state.gaussians), note=f"speed ×{best:.4f} (scores {tried})",
    )  # fmt: skip
    state.history.append(record)
    return record

"""The start of a run in branches (``init.branches``): each of the motion search's best hypotheses runs
the initialization and ``init.branch_frames`` tracked frames, and the best branch goes on: the one whose
map and trajectory explain fixed windows of those chunks best, or (``init.branch_score = "range"``) the
one whose map keeps the range meter's distance best.

Why: on the search's ten chunks an orbit, its mirror image (the turn about the image-plane axes
reversed, which a reversed relief explains as well) and the same orbit at half the rate (with twice the
relief) score within the refits' noise, and which one wins changes with the seed. Twenty-five frames on,
the map has a wider baseline, yet the events still favour the half rate or the mirror on three swirl_good
seeds of four, by a few per cent; the meter does not: a map with the wrong relief puts the surface under
it at the wrong depth as its ray sweeps the target, and on every seed tried the true branch's ratio of
range to first surface wanders least (docs/ablations.md §35, §47). On swirl_low none of the three best
motions turns enough, and without a meter there is nothing but the events; so it is off by default.

With ``init.branch_directions`` they are the search's best motion of each direction instead: with the
knots held through the initialization (``init.train_knots = false``) the map takes on the relief of
whichever rate it is given, and the range score kept swirl_good's half rate on one seed of three, while
the search's own sizing had the full rate first on all three (docs/ablations.md §72).

The branches start from the same seeded map and random state, so they differ by their hypothesis alone,
and they are compared on the same windows (:func:`evgs.slam.optimize.fixed_window_loss`) or samples. The
kept branch goes on as if it had been the only one; the others' time is recorded in a ``branch`` stage.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np
import torch

from evgs.slam import checkpoint
from evgs.slam.metric_scale import range_agreement
from evgs.slam.motion_search import Hypothesis
from evgs.slam.optimize import StageReporter, fixed_window_loss, range_penalty, range_unit
from evgs.slam.stages import initialize, start_from, step_chunk
from evgs.slam.state import SlamState, StageRecord, stage_seed

BRANCH_WINDOWS = 40  # windows the branches are compared on (8 scored the search's hypotheses: noisier)


def meter(state: SlamState) -> tuple[np.ndarray, np.ndarray]:
    """The sequence's range samples ``(t_us, metres)`` the range score needs; an error without them."""
    if state.data.ranges is None:
        raise ValueError("init.branch_score = 'range' needs the sequence's range meter (range.csv)")
    return state.data.ranges


@torch.no_grad()
def branch_score(state: SlamState, n: int) -> float:
    """Lower is better. ``init.branch_score = "events"``: the event term of ``state`` on fixed windows of
    chunks ``0..n-1`` (:func:`evgs.slam.optimize.window_event_score`), with the range meter's terms as
    every stage has them. ``"range"``: the spread of the meter against the map's first surface over the
    samples the branch has reached (:meth:`RangeAgreement.spread`; infinite where the map covers fewer
    than two of their rays)."""
    cfg, span = state.cfg, state.data.span(0, n)
    if cfg.init.branch_score == "range":
        spread = range_agreement(state, *meter(state), cfg.scale.min_alpha).spread()
        return spread if math.isfinite(spread) else math.inf
    loss = fixed_window_loss(state, span, stage_seed(cfg.seed, "branch", n), BRANCH_WINDOWS)
    unit = range_unit(state, cfg.scale.range_weight)
    return loss + float(range_penalty(state, span, unit, cfg.scale.range_weight, cfg.scale.rate_weight))


def branch_hypotheses(ranked: list[Hypothesis], n: int, directions: bool) -> list[Hypothesis]:
    """The first ``n`` of ``ranked`` (best first); with ``directions`` the first of each direction
    (:attr:`Hypothesis.direction`): the search's sizing picks the rate, the branches the direction."""
    if not directions:
        return ranked[:n]
    firsts: dict[str, Hypothesis] = {}
    for h in ranked:
        firsts.setdefault(h.direction, h)
    return list(firsts.values())[:n]


def run_branches(
    state: SlamState,
    hyps: list[Hypothesis],
    note: Callable[[StageRecord], None],
    reporter: StageReporter | None = None,
) -> SlamState:
    """Each of ``hyps`` from a copy of ``state`` (searched, not initialized): the initialization, then
    ``init.branch_frames`` chunks; returns the best branch, its position after them and a ``branch``
    record in its history. Branch ``i``'s stages reach ``note`` as ``branch<i>/<stage>``, its
    diagnostics are named ``branch<i>_<stage>_...``."""
    cfg, data = state.cfg, state.data
    if cfg.init.branch_score == "range":
        meter(state)  # before the branches' work, not after it
    n = min(data.n_chunks, state.num_init_chunks() + cfg.init.branch_frames)
    start = checkpoint.snapshot(state)
    runs: list[tuple[float, float, Hypothesis, SlamState]] = []
    for i, hyp in enumerate(hyps):
        t0 = time.perf_counter()
        branch = checkpoint.restore(start, cfg, data)
        branch.branch = label = f"branch{i}"

        def tagged(record: StageRecord, label: str = label) -> None:
            note(dataclasses.replace(record, stage=f"{label}/{record.stage}"))

        start_from(branch, hyp)
        tagged(initialize(branch, reporter))
        branch.position.initialized, branch.position.next_chunk = True, branch.num_init_chunks()
        while branch.position.next_chunk < n:
            step_chunk(branch, tagged, reporter)
        runs.append((branch_score(branch, n), time.perf_counter() - t0, hyp, branch))
    best = min(runs, key=lambda run: run[0])
    score, _, hyp, kept = best
    kept.branch = ""
    others = sum(seconds for _, seconds, _, b in runs if b is not kept)
    scores = ", ".join(f"{h.name} {s:.5f}" for s, _, h, _ in runs)
    what = "range spread" if cfg.init.branch_score == "range" else "loss"
    record = StageRecord(
        "branch", cfg.data.start_frame + n, 0, score, others, 0, False, len(kept.gaussians),
        note=f"kept {hyp.name} of {len(runs)} ({what} on chunks 0–{n - 1}: {scores})",
    )  # fmt: skip
    kept.history.append(record)
    note(record)
    return kept

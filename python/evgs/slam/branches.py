"""The start of a run in branches (``init.branches``): each of the motion search's best hypotheses runs
the initialization and ``init.branch_frames`` tracked frames, and the best branch goes on: the one whose
map and trajectory explain fixed windows of those chunks best, (``init.branch_score = "range"``) the
one whose map keeps the range meter's distance best, or (``"tracking"``) the one whose map predicted the
chunks it had not yet seen best: the mean loss of its tracked frames.

Why: on the search's ten chunks an orbit, its mirror image (the turn about the image-plane axes
reversed, which a reversed relief explains as well) and the same orbit at half the rate (with twice the
relief) score within the refits' noise, and which one wins changes with the seed. Twenty-five frames on,
the map has a wider baseline, yet the events still favour the half rate or the mirror on three swirl_good
seeds of four, by a few per cent; the meter does not: a map with the wrong relief puts the surface under
it at the wrong depth as its ray sweeps the target, and on every seed tried the true branch's ratio of
range to first surface wanders least (docs/ablations.md §35, §47). On swirl_low none of the three best
motions turns enough, and without a meter there is nothing but the events; so it is off by default.

The tracking score asks each map for the next view before that view reaches it (a local BA fits it
only after its frame is tracked): a map bent to a wrong motion explains the events it was fitted to as
well as the truth's does, but not the views ahead. On swirl_good the true orbit's branch tracked its 40
frames with an 11–21 % lower loss than the mirror's in every run looked at, where the range score kept
the mirror on one seed of three (docs/ablations.md §83). It does not tell a rate from its half (the
slower motion tracks with less loss), so it goes with ``init.branch_directions``, where the search sizes
the rate.

With ``init.branch_directions`` they are the search's best motion of each direction instead: with the
knots held through the initialization (``init.train_knots = false``) the map takes on the relief of
whichever rate it is given, and the range score kept swirl_good's half rate on one seed of three, while
the search's own sizing had the full rate first on all three (docs/ablations.md §72).

The branches start from the same seeded map and random state, so they differ by their hypothesis alone,
and they are compared on the same windows (:func:`evgs.slam.optimize.fixed_window_loss`) or samples. The
kept branch goes on as if it had been the only one; the others' time is recorded in a ``branch`` stage.

``init.branch_restarts`` then runs the kept branch's motion again from other random seedings of the map
(the windows the same): started on the true orbit, swirl_good's seeds end anywhere from 1.2 to 4.3 %,
and how well a seed's branch tracked its frames already ranks them; the restart that tracked best goes
on (docs/ablations.md §83; over 55 frames, not 40, it ranks swirl_good's seed 2 better, §89).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np
import torch

from evgs.slam import checkpoint
from evgs.slam.gaussians import Gaussians
from evgs.slam.metric_scale import range_agreement
from evgs.slam.motion_search import Hypothesis
from evgs.slam.optimize import StageReporter, fixed_window_loss, range_penalty, range_unit
from evgs.slam.seeding import seeding_generator
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
    than two of their rays). ``"tracking"``: the mean final loss of the frames tracked since the search
    (their pose's fit to the map as it stood when the frame arrived)."""
    cfg, span = state.cfg, state.data.span(0, n)
    if cfg.init.branch_score == "range":
        spread = range_agreement(state, *meter(state), cfg.scale.min_alpha).spread()
        return spread if math.isfinite(spread) else math.inf
    if cfg.init.branch_score == "tracking":
        losses = [r.loss for r in state.history if r.stage == "track"]
        return float(np.mean(losses)) if losses and all(map(math.isfinite, losses)) else math.inf
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


@dataclasses.dataclass
class Branch:
    """One branch's run from the search's state: its score, seconds, motion, seeding and end state."""

    score: float
    seconds: float
    hyp: Hypothesis
    seeding: int  # 0: the run's own seeded map; j > 0: restart j's
    state: SlamState


def run_branches(
    state: SlamState,
    hyps: list[Hypothesis],
    note: Callable[[StageRecord], None],
    reporter: StageReporter | None = None,
    reseed: Callable[[torch.Generator], Gaussians] | None = None,
) -> SlamState:
    """Each of ``hyps`` from a copy of ``state`` (searched, not initialized): the initialization, then
    ``init.branch_frames`` chunks; then, with ``init.branch_restarts`` = R > 1, the best of them R − 1
    times more, each from the map ``reseed`` seeds with its own generator (the windows stay the same).
    Returns the best branch, its position after them and a ``branch`` record in its history. Branch
    ``i``'s stages reach ``note`` as ``branch<i>/<stage>`` (restart ``j``'s as ``restart<j>/<stage>``),
    its diagnostics are named ``branch<i>_<stage>_...``."""
    cfg, data = state.cfg, state.data
    if cfg.init.branch_score == "range":
        meter(state)  # before the branches' work, not after it
    restarts = cfg.init.branch_restarts
    if restarts > 1 and reseed is None:
        raise ValueError("init.branch_restarts > 1: run_branches needs a reseed function")
    n = min(data.n_chunks, state.num_init_chunks() + cfg.init.branch_frames)
    start = checkpoint.snapshot(state)

    def run(hyp: Hypothesis, seeding: int, label: str) -> Branch:
        t0 = time.perf_counter()
        branch = checkpoint.restore(start, cfg, data)
        branch.branch = label
        if seeding:
            assert reseed is not None
            branch.seeding, branch.generator = seeding, seeding_generator(cfg.seed, seeding)
            branch.gaussians = reseed(branch.generator)

        def tagged(record: StageRecord) -> None:
            note(dataclasses.replace(record, stage=f"{label}/{record.stage}"))

        start_from(branch, hyp)
        tagged(initialize(branch, reporter))
        branch.position.initialized, branch.position.next_chunk = True, branch.num_init_chunks()
        while branch.position.next_chunk < n:
            step_chunk(branch, tagged, reporter)
        return Branch(branch_score(branch, n), time.perf_counter() - t0, hyp, seeding, branch)

    runs = [run(hyp, 0, f"branch{i}") for i, hyp in enumerate(hyps)]
    best = min(runs, key=lambda b: b.score)
    again = [run(best.hyp, j, f"restart{j}") for j in range(1, restarts)]
    kept = min([best, *again], key=lambda b: b.score)
    kept.state.branch = ""
    others = sum(b.seconds for b in [*runs, *again] if b is not kept)
    scores = ", ".join(f"{b.hyp.name} {b.score:.5f}" for b in runs)
    if again:
        scores += "; its restarts " + ", ".join(f"{b.score:.5f}" for b in again)
    first = state.num_init_chunks() if cfg.init.branch_score == "tracking" else 0
    what = {"range": "range spread", "tracking": "mean tracking loss"}.get(cfg.init.branch_score, "loss")
    which = f"{kept.hyp.name}, restart {kept.seeding}" if kept.seeding else kept.hyp.name
    record = StageRecord(
        "branch", cfg.data.start_frame + n, 0, kept.score, others, 0, False, len(kept.state.gaussians),
        note=f"kept {which} of {len(runs) + len(again)} ({what} on chunks {first}–{n - 1}: {scores})",
    )  # fmt: skip
    kept.state.history.append(record)
    note(record)
    return kept.state

"""Where the initialization starts: a search over constant-velocity motion hypotheses.

Optimised jointly from the identity, the init knots and the map settle on a near-static solution: a
sharper map explains the events of a small motion about as well, and the knots never travel to the
true one (docs/ablations.md §3, §7). Yet a map refitted to *fixed* knots scores the true motion clearly
best — the ±``init_depth_spread`` seeding bounds the relief that could trade against the motion. So
each hypothesis is scored by that refit: the seeded map trained for ``init.search_steps`` iterations
with the knots frozen, then its event loss on the same fixed windows, all on the first
``init.search_frames`` chunks (more than the init's: over a longer baseline an orbit and its mirror image
with the relief reversed no longer explain the events equally well).

The hypotheses are the motions of proximity operations with the target ahead of the camera, at
``init.search_rate`` per frame: orbits of the point ``(0, 0, init_depth)`` about the camera's x and y
axes, approach / retreat along the optical axis, sideways translations, each in both directions, and no
motion. A short joint fit from the best direction adds what the family leaves out (roll, mixtures) but
keeps its magnitude, which the refits then choose over × ``search_range``^(0, ±½, ±1), then ^±¼ around
the best. The joint initialization starts from the winner.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np
import torch
from torch import Tensor

from evgs.slam.lie import se3_exp
from evgs.slam.loss import event_loss
from evgs.slam.optimize import StageReporter, StageSpec, render_windows, run_stage
from evgs.slam.state import SlamState, stage_seed
from evgs.slam.trajectory import Trajectory

EVAL_WINDOWS = 8  # fixed windows every hypothesis is scored on


@dataclasses.dataclass(frozen=True)
class Hypothesis:
    name: str
    twist: Tensor  # per-frame se(3) twist (v, ω) in the first camera's frame

    def knots(self, n: int) -> Tensor:
        """Camera-to-world knots 0..n-1 under this constant velocity (knot 0 = identity)."""
        k = torch.arange(n, dtype=torch.float64)[:, None]
        return se3_exp(k * self.twist[None])

    def scaled(self, factor: float) -> Hypothesis:
        return Hypothesis(f"{self.name} ×{factor:.3g}", self.twist * factor)


def directions(rate: float, depth: float) -> Iterator[Hypothesis]:
    """Unit-rate hypotheses: ``rate`` rad per frame for orbits, ``rate × depth`` per frame for translations
    (the same image motion at the centre's depth)."""
    centre = torch.tensor([0.0, 0.0, depth], dtype=torch.float64)
    yield Hypothesis("still", torch.zeros(6, dtype=torch.float64))
    for axis, name in ((0, "x"), (1, "y")):
        for sign, s in ((1.0, "+"), (-1.0, "-")):
            w = torch.zeros(3, dtype=torch.float64)
            w[axis] = sign * rate
            # A rotation about the point `centre`: v = -ω × c (zero pitch screw through c).
            yield Hypothesis(f"orbit {s}{name}", torch.cat([-torch.linalg.cross(w, centre), w]))
    for axis, name in ((2, "z"), (0, "x"), (1, "y")):
        for sign, s in ((1.0, "+"), (-1.0, "-")):
            v = torch.zeros(6, dtype=torch.float64)
            v[axis] = sign * rate * depth
            yield Hypothesis(f"translate {s}{name}", v)


def search_chunks(state: SlamState) -> int:
    """Chunks the hypotheses are fitted and scored on: ``init.search_frames``, at least the init's."""
    return min(max(state.cfg.init.search_frames, state.num_init_chunks()), state.data.n_chunks)


def fit(state: SlamState, hyp: Hypothesis, reporter: StageReporter | None) -> SlamState:
    """A copy of ``state`` whose seeded map was optimised for ``init.search_steps`` iterations on
    ``hyp``'s frozen knots; ``state`` itself is left as it was. Every fit draws the same windows and
    random numbers, so scores differ by the hypothesis alone."""
    cfg, data = state.cfg, state.data
    m = search_chunks(state)
    trial = dataclasses.replace(
        state,
        traj=Trajectory(data.frames_us[: m + 1], hyp.knots(m + 1), cfg.trajectory.interpolation),
        gaussians=type(state.gaussians).from_state(state.gaussians.state()),
        generator=torch.Generator().manual_seed(stage_seed(cfg.seed, "search", m)),
        history=[],
    )
    spec = StageSpec(
        "search", m, cfg.init.search_steps, data.span(0, m), cfg.data.training_batch_size,
        stage_seed(cfg.seed, "search", m), [], range(m + 1), train_gaussians=True, lr_boost=cfg.init.lr_boost,
    )  # fmt: skip
    run_stage(trial, spec, reporter)
    return trial


def poll_directions(depth: float) -> list[tuple[str, Tensor]]:
    """Unit twists of the compass search, scaled to comparable image motion per unit."""
    out = []
    centre = torch.tensor([0.0, 0.0, depth], dtype=torch.float64)
    for axis, name, weight in ((0, "orbit x", 1.0), (1, "orbit y", 1.0), (2, "roll", 1.0)):
        w = torch.zeros(3, dtype=torch.float64)
        w[axis] = weight
        out.append((name, torch.cat([-torch.linalg.cross(w, centre), w])))
    for axis, name, weight in ((0, "x", 0.2), (1, "y", 0.2), (2, "z", 1.0)):
        v = torch.zeros(6, dtype=torch.float64)
        v[axis] = weight * depth
        out.append((f"move {name}", v))
    return out


def score(state: SlamState, hyp: Hypothesis, reporter: StageReporter | None) -> float:
    """Event loss on the fixed evaluation windows of the seeded map refitted to ``hyp``'s frozen knots."""
    cfg, data = state.cfg, state.data
    m = search_chunks(state)
    trial = fit(state, hyp, reporter)
    sampler = data.sampler(data.span(0, m), stage_seed(cfg.seed, "search", 0))
    losses = []
    with torch.no_grad():
        for _ in range(EVAL_WINDOWS):
            win = data.windows(sampler, 1, 1)
            gray = render_windows(trial, win, data.camera).color[..., 0]
            losses.append(float(event_loss(win.frames, gray[:1], gray[1:], cfg.loss).total))
    return float(np.mean(losses))


def search_motion(
    state: SlamState, reporter: StageReporter | None = None
) -> tuple[Hypothesis, list[tuple[str, float]]]:
    """The best-scoring hypothesis, and every (name, score) tried in order."""
    cfg = state.cfg.init
    depth = state.cfg.gaussians.init_depth
    tried: list[tuple[Hypothesis, float]] = []
    scores: dict[tuple[float, ...], float] = {}  # a compass sweep can come back to a scored twist

    def trial(h: Hypothesis) -> float:
        key = tuple(round(float(x), 12) for x in h.twist)
        if key not in scores:
            scores[key] = score(state, h, reporter)
            tried.append((h, scores[key]))
        return scores[key]

    def best_of(entries: list[tuple[Hypothesis, float]]) -> tuple[Hypothesis, float]:
        return min(entries, key=lambda hs: hs[1])

    for h in directions(cfg.search_rate, depth):
        trial(h)
    best, best_score = best_of(tried)
    if best.name == "still":
        return best, [(h.name, s) for h, s in tried]
    for e in (-1.0, -0.5, 0.5, 1.0):
        trial(best.scaled(cfg.search_range**e))
    best, best_score = best_of(tried)
    # Compass search in the basis of the hypotheses (orbit x/y, roll, translations), which the basis
    # motions alone miss: roll, mixtures and an orbit centre off init_depth, all of which the magnitude
    # would otherwise absorb. Sideways translations move the whole image, so their steps are smaller.
    rate = float(best.twist[3:].norm()) or float(best.twist[:3].norm()) / depth
    step = 0.25 * rate
    polls = 0
    while polls < cfg.search_polls:
        improved = False
        for name, direction in poll_directions(depth):
            for sign in (1.0, -1.0):
                if polls >= cfg.search_polls:
                    break
                h = Hypothesis(f"{best.name} {'+-'[sign < 0]}{name}", best.twist + sign * step * direction)
                n = len(tried)
                s = trial(h)
                polls += len(tried) - n
                if s < best_score:
                    best, best_score = h, s
                    improved = True
        if not improved:
            step *= 0.5
    return best, [(h.name, s) for h, s in tried]

"""Where the initialization starts: a search over constant-velocity motion hypotheses.

Optimised jointly from the identity, the init knots and the map settle on a near-static solution: a
sharper map explains the events of a small motion about as well, and the knots never travel to the
true one (docs/ablations.md §3, §7). A map refitted to *fixed* knots separates the motions much better
— the ±``init_depth_spread`` seeding bounds the relief that could trade against the motion. So each
hypothesis is scored by such a refit: the seeded map trained for ``init.search_steps`` iterations with
the knots frozen on the first ``init.search_frames`` chunks (more than the init's: over a longer
baseline an orbit and its mirror image with the relief reversed no longer explain the events equally
well), then its event term on fixed windows of those chunks (eq. 8 without the SSIM term, which favours
small motions: :func:`evgs.slam.optimize.window_event_score`) — and, with ``init.search_holdout`` > 0,
of as many chunks after them, the velocity carried on. On the fitted chunks alone a wrong motion with a
map bent to it can do as well as the truth, and the search over-estimates the motion 1.5–2×; on the
chunks ahead alone, too little motion does best; the mean of both, with the basis at two rates, finds
docking_good's approach but small orbits about the wrong axis on swirl (docs/ablations.md §8). So it is
an option, off by default.

The hypotheses are the motions of proximity operations with the target ahead of the camera, at
``init.search_rate`` per frame: orbits of the point ``(0, 0, init_depth)`` (or of a point behind the
seeded slab, ``init.search_orbit_depth``, as a target's centre lies behind the faces the camera sees)
about the camera's x and y axes (``init.search_tilt``: also about those axes tilted towards the optical
axis, as an orbit seen from an elevation is), approach / retreat along the optical axis, sideways
translations, each in both directions, and no motion (``init.search_half_rate``: each also at half that rate;
``init.search_families``: the orbits or the translations alone, where the scenario rules the other out).
The best orbits and the best translations (``init.search_sized`` of each) are sized over ×
``search_range``^(±½, ±1): each family's best at its own size, so that an approach slower than the
nominal rate is not left behind orbits (docking_good). With ``init.search_veer``, the best two sizes of
the winning family's best (an orbit or a translation) have their translation veered ± that angle towards
each axis across it, and the best of all then ± half the angle: the basis moves along one axis, while a
descent moves forward and sideways at once, and a swirl orbits and approaches at once (docs/ablations.md
§15, §17, §21). With ``init.search_meter_advance`` every hypothesis instead advances along the optical
axis as fast as the range meter closes over the searched chunks
(:func:`evgs.slam.range_prior.meter_advance`): the events see that advance least of all, the meter
directly, and the basis orbits have none (docs/ablations.md §41). The joint initialization starts from
the winner.

With ``init.search_finalists`` = k > 0 the k best are then refitted for ``init.search_final_steps``
iterations and ranked by that score, ahead of the rest. Which of an orbit, its mirror and its double
rate explains the events best can turn between 60 and 120 refit steps (docs/ablations.md §74); the
finalists' longer refits are the very ones a search refitting everything that long would run, so they
rank the same for a fraction of its cost, as long as its winner is among the short refits' k best.
``init.search_final_depth_tv`` gives the finalists' refits their own relief prior (``loss.depth_tv``):
given the steps to settle, it breaks the tie between a turn and a slower one with the relief deepened
to match (the bas-relief trade), which the dim light's silhouettes leave open; in the short refits it
bends the ranking towards other axes (docs/ablations.md §43, §78).

With ``init.search_polls`` > 0 a compass search in the same basis plus roll then adds what the family
leaves out (roll, mixtures, an orbit centre off ``init_depth``), from the best sized direction or, with
``init.search_starts``, from several (two basis orbits can tie while only one leads to the truth once
roll is added; docs/ablations.md §10). It is off by default: its steps are as small as the score's
noise, so on an approach it adds a spurious rotation that tracking carries on (docs/ablations.md §11).

Two measured options, off by default (docs/ablations.md §9): ``init.search_smooth`` refits on a fixed
schedule without densification or pruning, so that the score changes smoothly with the motion (by
default scores of motions 2 % apart differ by up to 10 %; swirl_good's config turns it on, where it
ranks the turn's full rate above its half on every seed, §82); ``init.search_range_weight`` adds the range
meter's term (:mod:`evgs.slam.range_prior`) to the score. ``scale.rate_weight`` adds the meter's closing
rate to it as to every stage: it needs no map, so it sizes an approach even where the refitted maps leave
the image centre empty (docking_low, docs/ablations.md §28).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from evgs.slam.lie import se3_exp
from evgs.slam.optimize import (
    StageReporter,
    StageSpec,
    fixed_window_loss,
    range_penalty,
    range_unit,
    run_stage,
)
from evgs.slam.range_prior import meter_advance
from evgs.slam.state import SlamState, stage_seed
from evgs.slam.trajectory import Trajectory

EVAL_WINDOWS = 8  # fixed windows every hypothesis is scored on, in the fitted chunks and in those ahead
Family = Literal["still", "orbit", "translate", ""]  # a basis motion's kind ("" off the basis: compass steps)


@dataclasses.dataclass(frozen=True)
class Hypothesis:
    name: str
    twist: Tensor  # per-frame se(3) twist (v, ω) in the first camera's frame
    family: Family = ""

    def knots(self, n: int) -> Tensor:
        """Camera-to-world knots 0..n-1 under this constant velocity (knot 0 = identity)."""
        k = torch.arange(n, dtype=torch.float64)[:, None]
        return se3_exp(k * self.twist[None])

    @property
    def direction(self) -> str:
        """The name without its rate factors: the same motion at another rate shares it."""
        return re.sub(r" ×[^ ]+", "", self.name)

    def scaled(self, factor: float) -> Hypothesis:
        return Hypothesis(f"{self.name} ×{factor:.3g}", self.twist * factor, self.family)

    def advancing(self, per_frame: float) -> Hypothesis:
        """This motion with its advance along the optical axis (the body-frame ``v_z``, constant under
        ``knots``) set to ``per_frame`` map units: the rest is left to the events. The name says so, once."""
        twist = self.twist.clone()
        twist[2] = per_frame
        name = re.sub(r" \(meter advance [^)]*\)", "", self.name)  # keeps a later "×f" of the rate
        return Hypothesis(f"{name} (meter advance {per_frame:.3g})", twist, self.family)


def directions(
    rate: float, depth: float, tilt_deg: float = 0.0, orbit_depth: float | None = None
) -> Iterator[Hypothesis]:
    """Unit-rate hypotheses: ``rate`` rad per frame for orbits of the point ``(0, 0, orbit_depth)``
    (default ``depth``), ``rate × depth`` per frame for translations (the same image motion at the
    centre's depth). With ``tilt_deg`` each orbit also with its axis tilted by ± that towards the optical
    axis: an orbit about an axis seen at an elevation (the orbit preset's 20°) turns the camera about its
    x or y axis and rolls it at once."""
    centre = torch.tensor([0.0, 0.0, depth if orbit_depth is None else orbit_depth], dtype=torch.float64)
    yield Hypothesis("still", torch.zeros(6, dtype=torch.float64), "still")
    tilts = [0.0] + ([tilt_deg, -tilt_deg] if tilt_deg else [])
    for axis, name in ((0, "x"), (1, "y")):
        for sign, s in ((1.0, "+"), (-1.0, "-")):
            for tilt in tilts:
                w = torch.zeros(3, dtype=torch.float64)
                w[axis] = sign * rate * np.cos(np.radians(tilt))
                w[2] = rate * np.sin(np.radians(tilt))
                # A rotation about the point `centre`: v = -ω × c (zero pitch screw through c).
                label = f"orbit {s}{name}" + (f" tilt {tilt:+g}°" if tilt else "")
                yield Hypothesis(label, torch.cat([-torch.linalg.cross(w, centre), w]), "orbit")
    for axis, name in ((2, "z"), (0, "x"), (1, "y")):
        for sign, s in ((1.0, "+"), (-1.0, "-")):
            v = torch.zeros(6, dtype=torch.float64)
            v[axis] = sign * rate * depth
            yield Hypothesis(f"translate {s}{name}", v, "translate")


def veered(h: Hypothesis, angle_deg: float) -> list[Hypothesis]:
    """``h``'s translation turned by ± ``angle_deg`` towards each of two axes across it, at the same
    speed and rotation: the polls of one step of a search over the translation's direction."""
    v, w = h.twist[:3], h.twist[3:]
    d = v / v.norm()
    least = int(torch.argmin(d.abs()))  # the basis axis least aligned with d spans the plane across it
    e1 = torch.linalg.cross(d, torch.eye(3, dtype=d.dtype)[least])
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(d, e1)
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    out = []
    for e, name in ((e1, "a"), (e2, "b")):
        for sign in (1.0, -1.0):
            label = f"{h.name} veer {name}{'+-'[sign < 0]}{angle_deg:g}°"
            out.append(Hypothesis(label, torch.cat([v.norm() * (c * d + sign * s * e), w]), h.family))
    return out


def search_chunks(state: SlamState) -> tuple[int, int]:
    """Chunks the hypotheses are fitted on (``init.search_frames``, at least the init's) and, after them,
    the chunks they are also scored on (``init.search_holdout``; fewer if the sequence ends, at least
    one unless it is 0)."""
    cfg, n = state.cfg.init, state.data.n_chunks
    m = min(max(cfg.search_frames, state.num_init_chunks()), n - (cfg.search_holdout > 0))
    return m, min(cfg.search_holdout, n - m)


def fit(
    state: SlamState,
    knots: Tensor,
    reporter: StageReporter | None,
    steps: int | None = None,
    smooth: bool | None = None,
    stage: str = "search",
    seed: int | None = None,
) -> SlamState:
    """A copy of ``state`` whose map was optimised for ``steps`` iterations (default
    ``init.search_steps``) on the frozen ``knots``, which cover the first ``len(knots) − 1`` chunks (a
    hypothesis' first ``init.search_frames`` + 1; the truth's, in ``benches/slam_oracle.py``; the
    tracked ones, in :mod:`evgs.slam.rate_check`); ``state`` itself is left as it was. ``smooth``
    (default ``init.search_smooth``) fits on the fixed schedule. Every fit of a given length draws the
    same windows and random numbers, so scores differ by the knots alone; ``seed`` (default the run's)
    gives them other streams."""
    cfg, data = state.cfg, state.data
    m = len(knots) - 1
    stream = stage_seed(cfg.seed if seed is None else seed, stage, m)
    trial = dataclasses.replace(
        state,
        traj=Trajectory(data.frames_us[: m + 1], knots, cfg.trajectory.interpolation),
        gaussians=type(state.gaussians).from_state(state.gaussians.state()),
        generator=torch.Generator().manual_seed(stream),
        history=[],
    )
    steps = cfg.init.search_steps if steps is None else steps
    smooth = cfg.init.search_smooth if smooth is None else smooth
    spec = StageSpec(
        stage, m, steps, data.span(0, m), cfg.data.training_batch_size, stream, [],
        range(m + 1), train_gaussians=True, lr_boost=cfg.init.lr_boost, adaptive=not smooth,
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


def score(
    state: SlamState, hyp: Hypothesis, reporter: StageReporter | None, steps: int | None = None
) -> float:  # fmt: skip
    """Event loss of the seeded map refitted ``steps`` iterations (:func:`fit`) to ``hyp``'s frozen knots
    on fixed windows of the fitted chunks — with ``init.search_holdout``, the mean of that and of the
    same on the chunks after them, where the constant velocity carries on.
    In the fitted chunks a wrong motion with a map bent to it can explain the events as well as the
    truth, but it does not predict the next ones; ahead, an unmodelled change of speed or a part of the
    target not yet mapped favours too little motion, which the fitted chunks do not."""
    cfg, data = state.cfg, state.data
    m, holdout = search_chunks(state)
    trial = fit(state, hyp.knots(m + 1), reporter, steps)
    spans = [data.span(0, m)]
    if holdout:  # the fitted knots, carried on over the chunks ahead
        n = m + holdout
        trial.traj = Trajectory(data.frames_us[: n + 1], hyp.knots(n + 1), cfg.trajectory.interpolation)
        spans.append(data.span_with_min(m, n))
    weight, rate_weight = cfg.init.search_range_weight, cfg.scale.rate_weight
    unit, seed = range_unit(trial, weight), stage_seed(cfg.seed, "search", 0)
    with torch.no_grad():
        means = [
            fixed_window_loss(trial, span, seed, EVAL_WINDOWS)
            + float(range_penalty(trial, span, unit, weight, rate_weight))
            for span in spans
        ]
    return float(np.mean(means))


class Scorer:
    """Scores each twist once (a compass sweep can come back to a scored twist) and keeps every
    (hypothesis, score) tried in order. With an ``advance`` every hypothesis is scored, and kept, with
    its advance along the optical axis set to it (:meth:`Hypothesis.advancing`); the approaches of
    several sizes then coincide and are scored once."""

    def __init__(
        self, state: SlamState, reporter: StageReporter | None, advance: float | None = None
    ) -> None:
        self.state, self.reporter, self.advance = state, reporter, advance
        self.tried: list[tuple[Hypothesis, float]] = []
        self._scores: dict[tuple[float, ...], float] = {}

    def __call__(self, h: Hypothesis) -> float:
        if self.advance is not None:
            h = h.advancing(self.advance)
        key = tuple(round(float(x), 12) for x in h.twist)
        if key not in self._scores:
            self._scores[key] = score(self.state, h, self.reporter)
            self.tried.append((h, self._scores[key]))
        return self._scores[key]

    def best(self) -> tuple[Hypothesis, float]:
        return min(self.tried, key=lambda hs: hs[1])


def compass(
    trial: Scorer, start: Hypothesis, step: float, polls: int, moves: list[tuple[str, Tensor]]
) -> tuple[Hypothesis, float]:
    """Compass search from ``start``: ± ``step`` along each direction, halving the step after a sweep
    without improvement, until ``polls`` new hypotheses were scored."""
    best, best_score = start, trial(start)
    n0 = len(trial.tried)
    while len(trial.tried) - n0 < polls:
        improved = False
        for name, direction in moves:
            for sign in (1.0, -1.0):
                if len(trial.tried) - n0 >= polls:
                    break
                h = Hypothesis(f"{best.name} {'+-'[sign < 0]}{name}", best.twist + sign * step * direction)
                s = trial(h)
                if s < best_score:
                    best, best_score = h, s
                    improved = True
        if not improved:
            step *= 0.5
    return best, best_score


@dataclasses.dataclass(frozen=True)
class SearchResult:
    ranked: list[Hypothesis]  # every hypothesis scored, the best first (the finalists ahead of the rest)
    score: float  # the best's
    tried: list[tuple[str, float]]  # every (name, score) in order
    finals: list[tuple[str, float]]  # the finalists' (name, score) after their longer refits, the best first
    steps: int  # map iterations spent on refits

    @property
    def best(self) -> Hypothesis:
        return self.ranked[0]


def search_motion(state: SlamState, reporter: StageReporter | None = None) -> SearchResult:
    """The best-scoring hypothesis, and what the search tried."""
    cfg = state.cfg.init
    depth = state.cfg.gaussians.init_depth
    # The basis orbits do not approach, and the events see an advance along the optical axis least of
    # all (docs/ablations.md §34, §41); where a range meter closes in, it says how fast.
    advance = None
    if cfg.search_meter_advance:
        advance = meter_advance(state.cfg, state.data, search_chunks(state)[0])
    trial = Scorer(state, reporter, advance)
    # Each direction at the nominal rate (and at half of it), and the best directions of each family then
    # sized over the ladder, before they are compared with each other and with no motion: at twice its
    # true rate the true direction can lose to wrong ones (docking_good's approach to every orbit, while
    # at its own rate it beats them all).
    still, *moves = directions(cfg.search_rate, depth, cfg.search_tilt, cfg.search_orbit_depth or depth)
    moves = [h for h in moves if cfg.search_families in ("all", h.family)]
    trial(still)
    sized = [min((h, h.scaled(0.5)), key=trial) if cfg.search_half_rate else h for h in moves]
    starts, rungs = [], {}
    for family in ("orbit", "translate"):
        for h in sorted((h for h in sized if h.family == family), key=trial)[: cfg.search_sized]:
            ladder = sorted([h] + [h.scaled(cfg.search_range**e) for e in (-1.0, -0.5, 0.5, 1.0)], key=trial)
            starts.append(ladder[0])
            rungs.setdefault(family, ladder[:2])
    if cfg.search_veer > 0 and trial.best()[0].family in rungs:
        # Veered at the two best sizes: a part across the basis motion changes the speed that explains the
        # events best (descent: the basis approach wins at its nominal rate, the true direction at half of
        # it). Scoring is all a veer does: the best of everything scored is the winner.
        for rung in rungs[trial.best()[0].family]:
            for h in veered(rung, cfg.search_veer):
                trial(h)
        for h in veered(trial.best()[0], cfg.search_veer / 2):
            trial(h)
    if cfg.search_polls > 0 and trial.best()[0].family != "still":
        # Compass search in the basis of the hypotheses (orbit x/y, roll, translations), which the basis
        # motions alone miss: roll, mixtures and an orbit centre off init_depth, all of which the
        # magnitude would otherwise absorb. Sideways translations move the whole image: smaller steps.
        # From several sized directions (``init.search_starts``): two basis orbits whose axes differ by
        # 90° can tie while only one of them leads to the truth once roll is added (the orbit preset).
        for start in sorted(starts, key=trial)[: cfg.search_starts]:
            rate = float(start.twist[3:].norm()) or float(start.twist[:3].norm()) / depth
            compass(trial, start, 0.25 * rate, cfg.search_polls, poll_directions(depth))
    ranked = sorted(trial.tried, key=lambda hs: hs[1])
    # The finalists refitted longer: their ranking among themselves is the longer refits', and the
    # rest keep theirs behind them (the two scores are not comparable with each other).
    k, final_state = cfg.search_finalists, state.with_relief_prior(cfg.search_final_depth_tv)
    finals = sorted(
        ((h, score(final_state, h, reporter, cfg.search_final_steps)) for h, _ in ranked[:k]),
        key=lambda hs: hs[1],
    )
    ranked = finals + ranked[len(finals) :]
    tried = [(h.name, s) for h, s in trial.tried]
    steps = cfg.search_steps * len(tried) + cfg.search_final_steps * len(finals)
    return SearchResult([h for h, _ in ranked], ranked[0][1], tried, [(h.name, s) for h, s in finals], steps)

"""The event-loss step and the optimisation loop every stage runs (paper §3.2–3.5).

One step: B windows from the Rust sampler, their event frames, the poses at each window's first and
last event from the continuous trajectory, one batched render of the 2B views, ``Ê = L(Î_end) −
L(Î_start)``, the loss of eq. 8 (plus the brightness anchor and, in global BAs, a total-variation prior
on the renders), backward, Adam on the trainable pose increments and (when mapping) the Gaussians,
then the guards and the densification schedule.

Economy: early iterations may render at ``1/coarse_factor`` resolution, and a stage ends early once the
mean loss of the last ``patience`` iterations improves on the block before by less than
``min_rel_change`` (at the coarse level this moves on to full resolution instead).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from evgs.config import LossConfig
from evgs.data.sequence import Camera
from evgs.render import RenderResult, render
from evgs.slam.gaussians import make_optimizer
from evgs.slam.guards import blocker_mask, clamp_colors_
from evgs.slam.loss import LossTerms, depth_variation, event_loss, event_term, total_variation, valid_mask
from evgs.slam.state import SlamState, StageRecord
from evgs.slam.strategy import DefaultStrategy, reset_opacity
from evgs.slam.trajectory import KnotMotion
from evgs.slam.windows import Windows, scaled_camera


@dataclass(frozen=True)
class StageSpec:
    stage: str  # "init", "track", "map", "gba", "final"
    frame: int  # newest frame of the stage (names diagnostics)
    iterations: int
    span: tuple[int, int]  # event index range the windows come from
    batch: int  # windows per iteration
    seed: int  # the window sampler's
    trainable_knots: Sequence[int]  # knots whose pose increments are optimised
    recent_knots: Sequence[int]  # cameras the near-camera guard protects
    train_gaussians: bool
    masked: bool = False  # tracking's border / low-alpha mask
    knot_motion: KnotMotion = "pose"  # "position" / "rotation": the trainable knots change only that
    anchored: bool = False  # brightness anchor term
    lr_boost: float = 1.0  # every Adam rate starts this many times higher, decaying to 1× at the end
    tv_weight: float = 0.0  # weight of the renders' total variation (a prior on the map's appearance)
    max_window: int = 0  # longest sampled window in events (0 = data.max_n_winsize)
    # Every ``replay_every``-th iteration draws its window from this event range instead (the chunks
    # before a local BA's window, their knots held), so the map keeps explaining the views it left.
    replay_span: tuple[int, int] | None = None
    replay_every: int = 0
    # False: a fixed schedule, no densification, pruning or early switches, so the result is a smooth
    # function of the fixed knots (the motion search compares refits of nearby motions)
    adaptive: bool = True
    # False: economy's convergence stop never ends the stage (the coarse level still hands over on it)
    early_stop: bool = True


@dataclass
class StepResult:
    out: RenderResult
    terms: LossTerms
    total: Tensor
    camera: Camera


class Convergence:
    """Relative change of the mean loss between two consecutive blocks of ``patience`` iterations."""

    def __init__(self, patience: int, min_rel_change: float):
        self.patience, self.min_rel_change = patience, min_rel_change
        self.losses: list[float] = []

    def update(self, loss: float) -> bool:
        self.losses.append(loss)
        p = self.patience
        if p <= 0 or len(self.losses) < 2 * p:
            return False
        prev, cur = float(np.mean(self.losses[-2 * p : -p])), float(np.mean(self.losses[-p:]))
        return prev - cur < self.min_rel_change * abs(prev)


def window_times(win: Windows) -> np.ndarray:
    """(2B,) µs of the views a batch renders: every window's start, then every window's end."""
    return np.concatenate([win.t_start, win.t_end])


def render_windows(state: SlamState, win: Windows, camera: Camera) -> RenderResult:
    """One render of the 2B views at :func:`window_times`."""
    viewmats = state.traj.viewmats_at(window_times(win))
    return render(
        **state.gaussians.render_inputs(), viewmats=viewmats, camera=camera,
        background=state.cfg.gaussians.background,
    )  # fmt: skip


@torch.no_grad()
def fixed_windows(
    state: SlamState, span: tuple[int, int], seed: int, windows: int
) -> Iterator[tuple[Windows, Tensor]]:
    """``windows`` single windows of the event index range ``span``, drawn by a sampler seeded with
    ``seed`` (the same windows whatever the state), each with ``state``'s gray renders (2, H, W) at its
    start and end (no gradient)."""
    data = state.data
    sampler = data.sampler(span, seed)
    for _ in range(windows):
        win = data.windows(sampler, 1, 1)
        yield win, render_windows(state, win, data.camera).color[..., 0]


def window_event_score(frames: Tensor, gray: Tensor, cfg: LossConfig) -> float:
    """Eq. 8 without its SSIM term, ``(1 − λ)·L_event``, of one window's event frame (1, H, W) and its
    renders ``gray`` (2, H, W) at its start and end: what states with different motions are compared on.

    The SSIM term compares a window's two renders with each other, not with the events: between motions
    it rewards the one whose renders change least, the smaller. With it the motion search ranked
    swirl_good's turn at half its rate first (seed 2, by 1 %); on the event term the full rate wins on
    all three seeds (docs/ablations.md §75)."""
    return (1 - cfg.lambda_ssim) * float(event_term(frames, gray[:1], gray[1:], cfg))


def fixed_window_loss(state: SlamState, span: tuple[int, int], seed: int, windows: int) -> float:
    """Mean :func:`window_event_score` of ``state``'s map and trajectory on :func:`fixed_windows`, so that
    states built on the same data (motion hypotheses, branches) compare on equal terms."""
    losses = [
        window_event_score(win.frames, gray, state.cfg.loss)
        for win, gray in fixed_windows(state, span, seed, windows)
    ]
    return float(np.mean(losses))


def range_unit(state: SlamState, weight: float) -> float | None:
    """The range meter's metres per map unit at this point of the run (None without a meter, or when
    its term has weight 0 and is not needed)."""
    if state.range_prior is None or weight == 0:
        return None
    return state.range_prior.unit(state.gaussians, state.traj)


def range_penalty(
    state: SlamState, span: tuple[int, int], unit: float | None, weight: float, rate_weight: float
) -> Tensor | float:
    """The range meter's terms (:mod:`evgs.slam.range_prior`) over the samples in the chunks of the event
    index range ``span``: ``weight`` × the map's depth against the range (at ``unit``; none without
    one), ``rate_weight`` × the closing rate; 0 without a meter."""
    prior = state.range_prior
    if prior is None:
        return 0.0
    t_lo, t_hi = state.data.time_span(span)
    total: Tensor | float = 0.0
    if weight and unit is not None:
        total = total + weight * prior.penalty(state.gaussians, state.traj, t_lo, t_hi, unit)
    if rate_weight:
        total = total + rate_weight * prior.rate_penalty(state.traj, t_lo, t_hi)
    return total


def loss_step(
    state: SlamState, spec: StageSpec, win: Windows, factor: int, unit: float | None = None
) -> StepResult:
    """Forward pass and loss of one batch (no backward); ``unit``: the range meter's (:func:`range_unit`)."""
    cfg = state.cfg
    camera = scaled_camera(state.data.camera, factor)
    out = render_windows(state, win, camera)
    b = len(win.starts)
    gray = out.color[..., 0]
    mask = None
    if spec.masked:
        t = cfg.tracking
        mask = valid_mask(out.alpha[:b], out.alpha[b:], t.mask_border // factor, t.mask_alpha)
    terms = event_loss(win.frames, gray[:b], gray[b:], cfg.loss, mask)
    total = terms.total
    if spec.tv_weight > 0:
        total = total + spec.tv_weight * total_variation(gray)
    if cfg.loss.depth_tv > 0 and spec.train_gaussians:
        total = total + cfg.loss.depth_tv * depth_variation(out.depth, out.alpha)
    if spec.anchored:
        total = total + state.anchor.penalty(out.color, out.alpha)
    total = total + range_penalty(state, spec.span, unit, cfg.scale.range_weight, cfg.scale.rate_weight)
    w = cfg.trajectory.smoothness
    if w > 0 and len(spec.trainable_knots):
        total = total + w * state.traj.acceleration_penalty(cfg.gaussians.bounding_size).float()
    return StepResult(out, terms, total, camera)


def lr_boost(spec: StageSpec, it: int) -> float:
    """``spec.lr_boost`` at the first iteration, decaying exponentially to 1 at the last."""
    if spec.lr_boost == 1.0 or spec.iterations <= 1:
        return 1.0
    return spec.lr_boost ** (1.0 - it / (spec.iterations - 1))


def set_lr_boost(optimizers: list[torch.optim.Optimizer | None], boost: float) -> None:
    """Every group's rate = its rate at creation (remembered as ``base_lr``) × ``boost``."""
    for opt in optimizers:
        if opt is None:
            continue
        for group in opt.param_groups:
            group["lr"] = group.setdefault("base_lr", group["lr"]) * boost


def set_gaussians_trainable(state: SlamState, on: bool) -> None:
    for p in state.gaussians.params.values():
        p.requires_grad_(on)


def prune_blockers(
    state: SlamState,
    spec: StageSpec,
    strategy: DefaultStrategy,
    opt: torch.optim.Optimizer | None,
    step: StepResult,
) -> int:
    """The near-camera / large-footprint guard (``guards.near_margin`` 0 and ``max_footprint`` ≥ 1 = off)."""
    g = state.cfg.guards
    with torch.no_grad():
        recent = state.traj.knots()[list(spec.recent_knots)]
    # The footprint test needs this step's radii, which no longer align after a refinement.
    radii = step.out.radii if step.out.radii.shape[1] == len(state.gaussians) else None
    mask = blocker_mask(
        state.gaussians, recent, step.camera, near_margin=g.near_margin * state.cfg.gaussians.bounding_size,
        radii=radii, max_footprint=g.max_footprint, footprint_min_opacity=g.footprint_min_opacity,
    )  # fmt: skip
    n = int(mask.sum())
    if n and n < len(state.gaussians):
        strategy.remove(state.gaussians, opt, mask)
    return n if n < len(state.gaussians) else 0


def run_stage(state: SlamState, spec: StageSpec, reporter: StageReporter | None = None) -> StageRecord:
    """Optimise for up to ``spec.iterations`` iterations; the trajectory is rebased at the end."""
    cfg, data, traj = state.cfg, state.data, state.traj
    econ = cfg.economy
    sampler = data.sampler(spec.span, spec.seed, spec.max_window)
    replay_sampler = None
    if spec.replay_span is not None and spec.replay_every > 0:
        replay_sampler = data.sampler(spec.replay_span, spec.seed + 1, spec.max_window)
    traj.set_trainable(list(spec.trainable_knots), spec.knot_motion)
    pose_opt = (
        torch.optim.Adam([traj.delta], lr=cfg.trajectory.pose_lr) if len(spec.trainable_knots) else None
    )
    set_gaussians_trainable(state, spec.train_gaussians)
    g_opt, strategy = None, DefaultStrategy(cfg.strategy, cfg.gaussians.bounding_size)
    if spec.train_gaussians:
        g_opt = make_optimizer(state.gaussians, cfg.gaussians)
        if cfg.strategy.reset_at_stage_start:
            reset_opacity(state.gaussians, g_opt, cfg.strategy.reset_opacity)
    coarse_end = int(econ.coarse_fraction * spec.iterations) if econ.coarse_factor > 1 else 0
    stopper = Convergence(econ.patience, econ.min_rel_change)
    unit = range_unit(state, cfg.scale.range_weight)
    t0, n_events, blockers, stopped, loss, step = time.perf_counter(), 0, 0, False, float("nan"), None
    it = -1
    for it in range(spec.iterations):
        factor = econ.coarse_factor if it < coarse_end else 1
        replayed = replay_sampler is not None and (it + 1) % spec.replay_every == 0
        win = data.windows(replay_sampler if replayed else sampler, spec.batch, factor)
        if pose_opt is not None:
            pose_opt.zero_grad(set_to_none=True)
        if g_opt is not None:
            g_opt.zero_grad(set_to_none=True)
        set_lr_boost([pose_opt, g_opt], lr_boost(spec, it))
        step = loss_step(state, spec, win, factor, unit)
        step.total.backward()
        if pose_opt is not None:
            pose_opt.step()
        if g_opt is not None:
            grad2d = step.out.grad2d_norm()
            if grad2d is not None:
                strategy.accumulate(grad2d, step.out.radii, step.camera.width, step.camera.height)
            g_opt.step()
            clamp_colors_(state.gaussians, cfg.guards.max_color)
            if spec.adaptive and it > 0 and it % cfg.strategy.refine_every == 0:  # radii still align
                blockers += prune_blockers(state, spec, strategy, g_opt, step)
            if spec.adaptive:
                strategy.step(state.gaussians, g_opt, it, state.generator)
        loss = float(step.total.detach())
        n_events += win.n_events
        if reporter is not None:
            reporter.advance(state, spec, it, loss, n_events, time.perf_counter() - t0)
        # Only the stage's own windows judge convergence: the replayed ones fit other views.
        if spec.adaptive and not replayed and stopper.update(loss):
            if factor > 1:  # the coarse level has converged: go on at full resolution
                coarse_end, stopper = it + 1, Convergence(econ.patience, econ.min_rel_change)
            elif spec.early_stop and it + 1 >= econ.min_fraction * spec.iterations and spec.lr_boost == 1.0:
                stopped = True  # (a decaying schedule runs to its end: it plans on the small final rates)
                break
    if spec.train_gaussians and spec.adaptive and step is not None:
        blockers += prune_blockers(state, spec, strategy, g_opt, step)
    set_gaussians_trainable(state, True)
    traj.rebase()
    record = StageRecord(
        spec.stage, spec.frame, it + 1, loss, time.perf_counter() - t0, n_events, stopped,
        len(state.gaussians), blockers,
    )  # fmt: skip
    state.history.append(record)
    if reporter is not None:
        reporter.stage_end(state, spec, record)
    return record


class StageReporter(Protocol):
    """Receives every iteration's progress (progress bars, diagnostics); tests pass None."""

    def advance(
        self, state: SlamState, spec: StageSpec, it: int, loss: float, events: int, seconds: float
    ) -> None: ...

    def stage_end(self, state: SlamState, spec: StageSpec, record: StageRecord) -> None: ...

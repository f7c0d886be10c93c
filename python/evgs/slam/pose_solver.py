"""Tracking by Levenberg–Marquardt on the six pose coordinates of the new knot (``tracking.solver = "lm"``).

Why not Adam, as the reference does: Adam moves every coordinate by about ``pose_lr`` per step whatever
the gradient says, so a tracker with a CPU budget of tens of steps can correct the constant-velocity
prediction by at most ``steps × pose_lr`` (1.5e-3 rad for 15 steps at 1e-4: a quarter of a frame's
rotation on an orbit) and dithers by ``pose_lr`` around the optimum. Gauss–Newton sees the curvature and
takes the whole step at once; the damping keeps it safe where the linearisation is poor.

One iteration: windows from the sampler, residuals ``r = Ê − E`` of the masked pixels at the current
increment and their Jacobian ``J`` from the rasterizer's forward-mode pose pass (:func:`linearised`,
``tracking.lm_jacobian = "analytic"``, the default), or, with ``"central"``, the residuals at the
increment and at ``±ε`` along each of the six coordinates (central differences, all 13 variants in one
batched render, no backward pass; twelve more renders per step, and spikes where a splat crosses its
alpha or extent cut-off, docs/ablations.md §69), the damped normal equations
``(JᵀWJ + λ·diag JᵀWJ) Δ = −JᵀWr`` (``W`` = IRLS weights for the L1 loss, 1 for MSE), and one more render
of the trial increment on the same windows: accepted (λ shrinks) if the loss falls, rejected (λ grows)
otherwise. Only the event term of eq. 8 is minimised: the SSIM term regularises the map's brightness,
which tracking does not change.

``tracking.lm_windows`` = n > 0 draws n windows once per tracked frame (at each resolution level) and
runs every iteration on them instead of on fresh ones: the steps then descend one objective, where with
fresh windows the optimum moves with each window's noise from step to step (swirl_good: ATE 2.22 → 1.96 %
on two windows at 8.4 s per frame, docs/ablations.md §61).

``tracking.velocity_prior`` = w adds ``w · δᵀ D δ`` for the increment ``δ`` from the constant-velocity
prediction, ``D`` the diagonal of the data rows' own Gauss–Newton matrix ``H``: the pull is as firm,
relative to the data, along every coordinate. Without it, tracking an orbit takes slightly too small a
step each frame (the loss is shallow along the orbit) and the local BA bends the map to match, until the
estimate turns at a third of the true rate. The prior holds the initialization's errors and a true
change of rate just as firmly (the swirl's turn slowing down and reversing), so it is off by default and
on in the orbit, descent and docking_low configs, whose velocity is steady (docs/ablations.md §10–11,
§17). ``tracking.velocity_prior_floor`` raises each of ``D``'s entries to at least that fraction of the
largest translation's (rotation's) entry (:func:`prior_curvature`; the orbit configs, §34);
``tracking.velocity_prior_frames`` limits the prior to the first tracked frames (:func:`prior_weight`;
the swirl_good config, §35).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from evgs.config import TrackingConfig
from evgs.render import render, render_pose_jvp
from evgs.slam.lie import se3_exp, se3_inverse
from evgs.slam.loss import event_mask, pointwise_error, predicted_events, valid_mask
from evgs.slam.optimize import StageReporter, StageSpec, range_unit, window_times
from evgs.slam.range_prior import closing_residuals, huber, huber_weights
from evgs.slam.state import SlamState, StageRecord
from evgs.slam.windows import Windows, scaled_camera

# The views' tangents in the knot's increment: central differences of the float64 pose interpolation,
# all twelve in one batched pass (truncation and rounding errors ~1e-10, far below the float32 renders');
# torch.func.jacfwd took 40 % of an LM step to differentiate it, twelve separate calls 20 %.
VIEW_STEP = 1e-6
MAX_STEP = 100.0  # longest accepted step per coordinate, in central-difference steps (0.1 rad at 1e-3)
# On fixed windows (tracking.lm_windows) keep the analytic linearisation of the step that was accepted, or
# of the increment a rejected step failed to leave, instead of rendering it again (the tests turn it off
# to check that the kept one is the very linearisation a fresh pass gives).
KEEP_LINEARISATION = True


@dataclass
class Residuals:
    """What V trial increments of the knot predict for one batch of B windows."""

    events: Tensor  # (V, B, h, w) ``Ê − E``
    alpha: Tensor  # (V, 2, B, h, w) rendered alpha at the window starts and ends
    ranges: Tensor | None  # (V, S) the range meter's relative errors (NaN = unused), None without samples
    rates: Tensor | None  # (V, S − 1) the meter's closing-rate errors (NaN = a jump), None without pairs
    jacobian: Tensor | None = None  # (6, B, h, w) ``∂Ê/∂δ`` at variant 0 (:func:`linearised`), else None


def trial_knots(knots: Tensor, knot: int, deltas: Tensor) -> Tensor:
    """(V, K, 4, 4): the knots (K, 4, 4) with ``knot`` moved on its right by each increment of ``deltas``
    (V, 6), built in one batch (a tenth of the time of one set at a time)."""
    trials = knots.expand(len(deltas), *knots.shape).clone()
    trials[:, knot] = knots[knot] @ se3_exp(deltas)
    return trials


def meter_residuals(
    state: SlamState, trials: Tensor, span: tuple[int, int], unit: float | None
) -> tuple[Tensor | None, Tensor | None]:  # fmt: skip
    """The range meter's residuals ``(ranges, rates)`` (metres per map unit ``unit``) of V trial knot
    sets (V, K, 4, 4) at its samples in the chunks of the event index range ``span``; None where there are
    none."""
    traj, cfg, prior = state.traj, state.cfg, state.range_prior
    ranges = rates = None
    if prior is None:
        return ranges, rates
    t_lo, t_hi = state.data.time_span(span)
    t_r, metres = prior.samples(t_lo, t_hi, traj)
    if len(t_r) and unit is not None:
        range_views = se3_inverse(traj.pose_at(t_r, trials)).reshape(-1, 4, 4).float()
        q = prior.residuals(state.gaussians, range_views, np.tile(metres, len(trials)), unit)
        ranges = q.reshape(len(trials), len(t_r))
    t_r, metres, steady = prior.rate_samples(t_lo, t_hi, traj)
    if steady.any() and cfg.scale.rate_weight:
        poses = traj.pose_at(t_r, trials)
        # the axes of the increment itself (variant 0): the meter does not see where the camera points
        rates = closing_residuals(poses, poses[0, :, :3, 2], metres, prior.seed_unit)
        rates[:, ~torch.from_numpy(steady)] = float("nan")  # a jump: not used (meter_rows)
    return ranges, rates


def residuals(
    state: SlamState, knot: int, deltas: Tensor, win: Windows, factor: int, span: tuple[int, int],
    unit: float | None,
) -> Residuals:  # fmt: skip
    """The residuals of V trial increments (V, 6) of ``knot``, the other knots as they are; the range
    meter's (metres per map unit ``unit``) at its samples in the chunks of the event index range ``span``."""
    traj, cfg = state.traj, state.cfg
    with torch.no_grad():
        knots = traj.knots()
        times = window_times(win)
        trials = trial_knots(knots, knot, deltas)
        viewmats = se3_inverse(traj.pose_at(times, trials)).reshape(-1, 4, 4).float()
        out = render(
            **state.gaussians.render_inputs(), viewmats=viewmats,
            camera=scaled_camera(state.data.camera, factor), background=cfg.gaussians.background,
        )  # fmt: skip
        ranges, rates = meter_residuals(state, trials, span, unit)
    b = len(win.starts)
    gray = out.color[..., 0].reshape(len(deltas), 2, b, *out.color.shape[1:3])
    alpha = out.alpha.reshape(len(deltas), 2, b, *out.alpha.shape[1:3])
    return Residuals(predicted_events(gray[:, 0], gray[:, 1], cfg.loss) - win.frames, alpha, ranges, rates)


def linearised(
    state: SlamState, knot: int, delta: Tensor, variants: Tensor, win: Windows, factor: int,
    span: tuple[int, int], unit: float | None,
) -> Residuals:  # fmt: skip
    """The residuals at the increment ``delta`` and their analytic Jacobian ``∂Ê/∂δ`` (tracking.lm_jacobian
    = "analytic"): the renders are differentiated along the windows' view tangents (:data:`VIEW_STEP`)
    by the rasterizer's forward-mode pass (one pass instead of twelve renders), and ``Ê`` by the chain
    rule. The range meter's few residuals keep their central differences at ``delta + variants``."""
    traj, cfg = state.traj, state.cfg
    with torch.no_grad():
        knots = traj.knots()
        times = window_times(win)

        steps = VIEW_STEP * torch.eye(6, dtype=torch.float64)
        batch = trial_knots(knots, knot, torch.cat([delta[None], delta + steps, delta - steps]))
        views = se3_inverse(traj.pose_at(times, batch))  # (13, 2B, 4, 4): the increment, then ± each step
        tangents = ((views[1:7] - views[7:13]) / (2 * VIEW_STEP)).transpose(0, 1)  # (2B, 6, 4, 4)
        out = render_pose_jvp(
            **state.gaussians.render_inputs(), viewmats=views[0].float(), tangents=tangents.float(),
            camera=scaled_camera(state.data.camera, factor), background=cfg.gaussians.background,
        )  # fmt: skip
        ranges, rates = meter_residuals(state, trial_knots(knots, knot, delta + variants), span, unit)
    b, (h, w) = len(win.starts), out.color.shape[1:3]
    gray = out.color[..., 0].reshape(2, b, h, w)
    d_gray = out.d_color[..., 0].reshape(2, b, h, w, 6).permute(0, 4, 1, 2, 3)  # (2, 6, B, h, w)
    with torch.enable_grad():  # Ê is elementwise in the two renders: one backward gives both slopes
        ends = [g.clone().requires_grad_() for g in gray]
        events = predicted_events(ends[0], ends[1], cfg.loss)
        slopes = torch.autograd.grad(events.sum(), ends)
    jacobian = slopes[0] * d_gray[0] + slopes[1] * d_gray[1]
    alpha = out.alpha.reshape(1, 2, b, h, w)
    return Residuals((events.detach() - win.frames)[None], alpha, ranges, rates, jacobian)


def meter_cost(weight: float, q: Tensor | None, used: Tensor | None) -> float:
    """``weight`` × one of the range meter's terms for one row of residuals ``q`` (0 without residuals
    or used samples; NaN, so the step is rejected, if a used sample lost its coverage)."""
    if q is None or used is None or not bool(used.any()):
        return 0.0
    return weight * float(huber(q[used].double()).mean())


def meter_rows(
    q: Tensor, eps: Tensor, weight: float, rows: int
) -> tuple[Tensor, Tensor, float, Tensor]:  # fmt: skip
    """Gauss–Newton ``(H, g)`` of one of the range meter's terms from its residuals ``q`` (13, S) at the
    variants of :func:`lm_track`, scaled to the data rows' ``rows·cost``; its cost at the increment; the
    samples used (those the variants all cover)."""
    used = ~torch.isnan(q).any(0)
    if not bool(used.any()):
        return torch.zeros(6, 6, dtype=torch.float64), torch.zeros(6, dtype=torch.float64), 0.0, used
    qu = q[:, used].double()
    jq = (qu[1:7] - qu[7:13]) / (2 * eps[:, None])
    wq = huber_weights(qu[0]) * rows * weight / qu.shape[1]
    return (jq * wq) @ jq.T, (jq * wq) @ qu[0], meter_cost(weight, q[0], used), used


def prior_curvature(diag: Tensor, weight: float, floor: float) -> Tensor:
    """(6, 6) curvature of the pull towards the constant-velocity prediction: ``weight`` × the data's
    curvature ``diag`` (6,) per coordinate (v, ω), each raised to at least ``floor`` × the largest of its
    kind. The events see a compact target's roll about the optical axis and the advance along it far less
    than its turn and sideways motion: their image motion scales with the target's radius in the image,
    not with the focal length (the orbit's first tracked frame: the advance's curvature 1/77 of the best
    translation's, the roll's 1/9 of the best rotation's; docking_low 1/90 and 1/48). Held only as firmly
    as the data see them, they wander frame to frame: on the orbit the roll's share of the turn scatters
    by ±10° and drifts, and the gaze ends 10–13° off the orbit's centre (docs/ablations.md §34). The
    floor holds them at constant velocity instead. That removes the scatter; the slow drift is the local
    BAs', which move the knots with Adam: the orbit configs set both it and ``mapping.train_poses = false``
    (ATE 0.48 → 0.22 %, drift 4.8 → 2.1°, §34)."""
    d = diag.clone()
    if floor > 0:
        for kind in (slice(0, 3), slice(3, 6)):
            d[kind] = d[kind].clamp(min=floor * float(d[kind].max()))
    return weight * torch.diag(d)


def prior_weight(tc: TrackingConfig, tracked: int) -> float:
    """The velocity prior's weight on the ``tracked``-th frame after the initialization (1 = the first):
    ``tracking.velocity_prior`` up to ``tracking.velocity_prior_frames`` (0 = every frame), then 0.

    The initialization's map has seen a few chunks' baseline; on a narrow view a turn and the map's
    relief trade off (bas-relief), so it cannot tell a slower turn from a deeper target and tracking on
    it turns too slowly (the swirl: half the true rate, docs/ablations.md §14). Held at the
    initialization's velocity while the local BAs give the map a wider baseline, tracking then follows the
    swirl's slowing turn on its own, though it lags on the way back (seed 0: ATE 10.15 → 2.21 %). It
    holds a wrong start just as firmly: only swirl_good's config sets it, where the branches pick the
    start (§35, §39); a prior that lingers, even weakly, carries the turn past its reversal (§57)."""
    frames = tc.velocity_prior_frames
    return tc.velocity_prior if frames == 0 or tracked <= frames else 0.0


def lm_track(state: SlamState, spec: StageSpec, reporter: StageReporter | None = None) -> StageRecord:
    """Optimise the single trainable knot of ``spec`` by Levenberg–Marquardt; rebases at the end."""
    cfg, data, traj = state.cfg, state.data, state.traj
    tc, econ, kind, sc = cfg.tracking, cfg.economy, cfg.loss.event_loss, cfg.scale
    (knot,) = spec.trainable_knots
    prior_w = prior_weight(tc, knot - state.num_init_chunks())
    sampler = data.sampler(spec.span, spec.seed, spec.max_window)
    traj.set_trainable([knot])
    # Rotations move a pixel by f·ε; translations by f·ε/depth: matched at the scene's scale.
    eps = torch.tensor([tc.lm_step * cfg.gaussians.bounding_size] * 3 + [tc.lm_step] * 3, dtype=torch.float64)
    variants = torch.cat([torch.zeros(1, 6, dtype=torch.float64), torch.diag(eps), -torch.diag(eps)])
    delta, lam, unit = (
        torch.zeros(6, dtype=torch.float64),
        tc.lm_damping,
        range_unit(state, sc.range_weight),
    )
    coarse_end = int(econ.coarse_fraction * spec.iterations) if econ.coarse_factor > 1 else 0
    t0, n_events, loss, stopped, it = time.perf_counter(), 0, float("nan"), False, -1
    fixed: dict[int, Windows] = {}  # tracking.lm_windows: this frame's windows at each resolution level
    # With KEEP_LINEARISATION the trial is linearised too: one forward-mode pass per step instead of that
    # pass and a plain render (their colours are the same to the bit).
    keep = KEEP_LINEARISATION and bool(tc.lm_windows) and tc.lm_jacobian == "analytic"
    kept: tuple[int, Residuals] | None = None
    for it in range(spec.iterations):
        factor = econ.coarse_factor if it < coarse_end else 1
        if not tc.lm_windows:
            win = data.windows(sampler, spec.batch, factor)
        elif factor in fixed:
            win = fixed[factor]
        else:
            win = fixed[factor] = data.windows(sampler, tc.lm_windows, factor)
        if kept is not None and kept[0] == factor:
            res = kept[1]
        elif tc.lm_jacobian == "analytic":
            res = linearised(state, knot, delta, variants, win, factor, spec.span, unit)
        else:
            res = residuals(state, knot, delta + variants, win, factor, spec.span, unit)
        if keep:
            kept = (factor, res)
        mask = valid_mask(res.alpha[0, 0], res.alpha[0, 1], tc.mask_border // factor, tc.mask_alpha)
        if cfg.loss.event_mask_threshold >= 0:
            mask &= event_mask(win.frames, cfg.loss.event_mask_threshold)
        n_events += win.n_events
        if int(mask.sum()) < 6:  # nothing to constrain the pose with at this level
            continue
        r0 = res.events[0][mask].double()  # (P,)
        if res.jacobian is not None:
            jac = res.jacobian[:, mask].double()  # (6, P)
        else:
            r = res.events[:, mask].double()  # (13, P)
            jac = (r[1:7] - r[7:13]) / (2 * eps[:, None])
        w = 1.0 / r0.abs().clamp(min=cfg.data.event_contrast) if kind == "l1" else torch.ones_like(r0)
        hess = (jac * w) @ jac.T
        grad = (jac * w) @ r0
        cost0 = float(pointwise_error(r0, kind).mean())
        # hess and grad are of rows·cost: P·cost (MSE) or 2P·cost (L1 by IRLS: |r| ≈ r²/2|r₀| + const).
        rows = len(r0) * (2 if kind == "l1" else 1)
        meters = []  # the range meter's rows: same views, increments
        for weight, name in ((sc.range_weight, "ranges"), (sc.rate_weight, "rates")):
            if (q := getattr(res, name)) is not None:
                h, g, c, used = meter_rows(q, eps, weight, rows)
                hess, grad, cost0 = hess + h, grad + g, cost0 + c
                meters.append((weight, name, used))
        # The pull towards the constant-velocity prediction (delta = 0); zero when the prior is off.
        prior_h = prior_curvature(hess.diagonal(), prior_w, tc.velocity_prior_floor)
        hess, grad = hess + prior_h, grad + prior_h @ delta
        cost0 += float(delta @ prior_h @ delta) / rows
        step = -torch.linalg.solve(hess + lam * torch.diag(hess.diagonal()) + 1e-12 * torch.eye(6), grad)
        cost1 = float("inf")  # a non-finite or implausibly long step (a near-singular system) is rejected
        trial = None
        if bool(torch.isfinite(step).all()) and float((step.abs() / eps).max()) <= MAX_STEP:
            if keep:
                trial = linearised(state, knot, delta + step, variants, win, factor, spec.span, unit)
            else:
                trial = residuals(state, knot, (delta + step)[None], win, factor, spec.span, unit)
            cost1 = float(pointwise_error(trial.events[0][mask].double(), kind).mean())
            for weight, name, used in meters:
                q = getattr(trial, name)
                cost1 += meter_cost(weight, None if q is None else q[0], used)
            cost1 += float((delta + step) @ prior_h @ (delta + step)) / rows
        if cost1 < cost0:
            delta, lam, loss = delta + step, max(lam / 3, 1e-7), cost1
            if keep and trial is not None:
                kept = (factor, trial)
            converged = bool((step.abs() < tc.lm_tolerance * eps).all())
        else:
            lam, loss, converged = lam * 4, cost0, lam > 1e6
        if reporter is not None:
            reporter.advance(state, spec, it, loss, n_events, time.perf_counter() - t0)
        if converged and factor == 1 and it + 1 >= econ.min_fraction * spec.iterations:
            stopped = True
            break
        if converged and factor > 1:  # the coarse level has converged: go on at full resolution
            coarse_end = it + 1
    with torch.no_grad():
        traj.delta[knot] = delta
    traj.rebase()
    record = StageRecord(
        spec.stage,
        spec.frame,
        it + 1,
        loss,
        time.perf_counter() - t0,
        n_events,
        stopped,
        len(state.gaussians),
    )
    state.history.append(record)
    if reporter is not None:
        reporter.stage_end(state, spec, record)
    return record

"""Tracking by Levenberg–Marquardt on the six pose coordinates of the new knot (``tracking.solver = "lm"``).

Why not Adam, as the reference does: Adam moves every coordinate by about ``pose_lr`` per step whatever
the gradient says, so a tracker with a CPU budget of tens of steps can correct the constant-velocity
prediction by at most ``steps × pose_lr`` (1.5e-3 rad for 15 steps at 1e-4: a quarter of a frame's
rotation on an orbit) and dithers by ``pose_lr`` around the optimum. Gauss–Newton sees the curvature and
takes the whole step at once; the damping keeps it safe where the linearisation is poor.

One iteration: windows from the sampler, residuals ``r = Ê − E`` of the masked pixels at the current
increment and at ``±ε`` along each of the six coordinates (central differences, all 13 variants in one
batched render, no backward pass), ``J``, the damped normal equations ``(JᵀWJ + λ·diag JᵀWJ) Δ = −JᵀWr``
(``W`` = IRLS weights for the L1 loss, 1 for MSE), and one more render of the trial increment on the same
windows: accepted (λ shrinks) if the loss falls, rejected (λ grows) otherwise. Only the event term of
eq. 8 is minimised: the SSIM term regularises the map's brightness, which tracking does not change.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from evgs.render import render
from evgs.slam.lie import se3_exp, se3_inverse
from evgs.slam.loss import event_mask, pointwise_error, predicted_events, valid_mask
from evgs.slam.optimize import StageReporter, StageSpec
from evgs.slam.state import SlamState, StageRecord
from evgs.slam.windows import Windows, scaled_camera

MAX_STEP = 100.0  # longest accepted step per coordinate, in central-difference steps (0.1 rad at 1e-3)


def residual_images(
    state: SlamState, knot: int, deltas: Tensor, win: Windows, factor: int
) -> tuple[Tensor, Tensor]:
    """Residuals ``Ê − E`` (V, B, h, w) and rendered alpha (V, 2, B, h, w) (window start, end) for V trial
    increments (V, 6) of ``knot``, the other knots as they are."""
    traj, cfg = state.traj, state.cfg
    with torch.no_grad():
        knots = traj.knots()
        times = np.concatenate([win.t_start, win.t_end])
        poses = []
        for d in deltas:
            trial = knots.clone()
            trial[knot] = knots[knot] @ se3_exp(d)
            poses.append(traj.pose_at(times, trial))
        viewmats = se3_inverse(torch.cat(poses)).float()
        out = render(
            **state.gaussians.render_inputs(), viewmats=viewmats,
            camera=scaled_camera(state.data.camera, factor), background=cfg.gaussians.background,
        )  # fmt: skip
    b = len(win.starts)
    gray = out.color[..., 0].reshape(len(deltas), 2, b, *out.color.shape[1:3])
    alpha = out.alpha.reshape(len(deltas), 2, b, *out.alpha.shape[1:3])
    resid = predicted_events(gray[:, 0], gray[:, 1], cfg.loss) - win.frames
    return resid, alpha


def lm_track(state: SlamState, spec: StageSpec, reporter: StageReporter | None = None) -> StageRecord:
    """Optimise the single trainable knot of ``spec`` by Levenberg–Marquardt; rebases at the end."""
    cfg, data, traj = state.cfg, state.data, state.traj
    tc, econ, kind = cfg.tracking, cfg.economy, cfg.loss.event_loss
    (knot,) = spec.trainable_knots
    sampler = data.sampler(spec.span, spec.seed)
    traj.set_trainable([knot])
    # Rotations move a pixel by f·ε; translations by f·ε/depth: matched at the scene's scale.
    eps = torch.tensor([tc.lm_step * cfg.gaussians.bounding_size] * 3 + [tc.lm_step] * 3, dtype=torch.float64)
    variants = torch.cat([torch.zeros(1, 6, dtype=torch.float64), torch.diag(eps), -torch.diag(eps)])
    delta, lam = torch.zeros(6, dtype=torch.float64), tc.lm_damping
    coarse_end = int(econ.coarse_fraction * spec.iterations) if econ.coarse_factor > 1 else 0
    t0, n_events, loss, stopped, it = time.perf_counter(), 0, float("nan"), False, -1
    for it in range(spec.iterations):
        factor = econ.coarse_factor if it < coarse_end else 1
        win = data.windows(sampler, spec.batch, factor)
        resid, alpha = residual_images(state, knot, delta + variants, win, factor)
        mask = valid_mask(alpha[0, 0], alpha[0, 1], tc.mask_border // factor, tc.mask_alpha)
        if cfg.loss.event_mask_threshold >= 0:
            mask &= event_mask(win.frames, cfg.loss.event_mask_threshold)
        n_events += win.n_events
        if int(mask.sum()) < 6:  # nothing to constrain the pose with at this level
            continue
        r = resid[:, mask].double()  # (13, P)
        jac = (r[1:7] - r[7:13]) / (2 * eps[:, None])  # (6, P)
        r0 = r[0]
        w = 1.0 / r0.abs().clamp(min=cfg.data.event_contrast) if kind == "l1" else torch.ones_like(r0)
        hess = (jac * w) @ jac.T
        grad = (jac * w) @ r0
        cost0 = float(pointwise_error(r0, kind).mean())
        step = -torch.linalg.solve(hess + lam * torch.diag(hess.diagonal()) + 1e-12 * torch.eye(6), grad)
        cost1 = float("inf")  # a non-finite or implausibly long step (a near-singular system) is rejected
        if bool(torch.isfinite(step).all()) and float((step.abs() / eps).max()) <= MAX_STEP:
            trial_resid, _ = residual_images(state, knot, (delta + step)[None], win, factor)
            cost1 = float(pointwise_error(trial_resid[0][mask].double(), kind).mean())
        if cost1 < cost0:
            delta, lam, loss = delta + step, max(lam / 3, 1e-7), cost1
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

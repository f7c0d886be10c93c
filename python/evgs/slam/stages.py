"""The four stages of the paper's §3 as optimisation problems for :func:`run_stage`.

Knot ``k`` sits at frame ``k`` (of the frames the run uses) and chunk ``k`` holds the events between
knots ``k`` and ``k+1``. Knot 0 is never optimised: it fixes the gauge (the map's frame), which the
event loss cannot observe.

- motion search (optional): the constant-velocity motion the initialization starts from;
- initialization: chunks ``0..m-1``, knots ``1..m`` and the Gaussians jointly;
- tracking of chunk ``k``: knot ``k+1`` appended by constant velocity, then only it moves;
- mapping (local BA): the last ``mapping.window`` chunks, their knots (unless ``mapping.train_poses`` is
  false) and the Gaussians, after adding Gaussians where the newest view is still uncovered (low alpha)
  but events fired; with ``mapping.replay_every`` some iterations replay the tracked chunks before the
  window, their knots held;
- global BA: windows from all chunks so far, every knot but the first and the Gaussians.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from evgs.render import render
from evgs.slam.depth import median_depth
from evgs.slam.motion_search import Hypothesis, SearchResult, search_motion
from evgs.slam.optimize import StageReporter, StageSpec, run_stage
from evgs.slam.pose_solver import lm_track
from evgs.slam.state import SlamState, StageRecord, stage_seed
from evgs.slam.strategy import DefaultStrategy, gaussians_from_view


def _seq_frame(state: SlamState, knot: int) -> int:
    return state.cfg.data.start_frame + knot


def search(state: SlamState, reporter: StageReporter | None = None) -> tuple[SearchResult, StageRecord]:
    """The constant-velocity hypotheses ranked by :mod:`evgs.slam.motion_search`, recorded in the state's
    history; the knots are left as they are."""
    t0 = time.perf_counter()
    found = search_motion(state, reporter)
    record = StageRecord(
        "search", _seq_frame(state, state.num_init_chunks()), found.steps, found.score,
        time.perf_counter() - t0, 0, False, len(state.gaussians),
        note=f"best of {len(found.tried)} motions"
        + (f", {len(found.finals)} refitted longer" if found.finals else "")
        + f": {found.best.name}; then {runners_up(found)}",
    )  # fmt: skip
    state.history.append(record)
    return found, record


def runners_up(found: SearchResult, n: int = 2) -> str:
    """The next ``n`` motions of the search's ranking with their scores (a finalist's from its longer
    refit): how close the start's choice was, which decides a run (docs/ablations.md §81)."""
    scores = dict(found.tried) | dict(found.finals)
    return ", ".join(f"{h.name} {scores[h.name]:.5f}" for h in found.ranked[1 : n + 1]) or "none"


def start_from(state: SlamState, hyp: Hypothesis) -> None:
    """Set the init knots to ``hyp``'s constant velocity."""
    with torch.no_grad():
        state.traj.base.copy_(hyp.knots(state.num_init_chunks() + 1))


def initialize(state: SlamState, reporter: StageReporter | None = None) -> StageRecord:
    m = state.num_init_chunks()
    cfg = state.cfg
    spec = StageSpec(
        "init", _seq_frame(state, m), cfg.init.num_opti_steps_for_init, state.data.span(0, m),
        cfg.data.training_batch_size, stage_seed(cfg.seed, "init", m),
        range(1, m + 1) if cfg.init.train_knots else range(0), range(m + 1),
        train_gaussians=True, lr_boost=cfg.init.lr_boost,
        knot_motion="pose" if cfg.init.train_knot_rotation else "position",
    )  # fmt: skip
    record = run_stage(state, spec, reporter)
    set_brightness_reference(state)
    return record


@torch.no_grad()
def render_knots(state: SlamState, knots: list[int]):
    """Full-resolution renders at the given knots (no gradient)."""
    viewmats = state.traj.viewmats_at(state.traj.t_us[knots].numpy())
    return render(
        **state.gaussians.render_inputs(), viewmats=viewmats, camera=state.data.camera,
        background=state.cfg.gaussians.background,
    )  # fmt: skip


def set_brightness_reference(state: SlamState) -> None:
    """Anchor the surface brightness to its value over the initialization views."""
    out = render_knots(state, list(range(len(state.traj))))
    state.anchor.set_reference(out.color, out.alpha)


def track(
    state: SlamState, k: int, reporter: StageReporter | None = None, pose: torch.Tensor | None = None
) -> StageRecord:
    """Track chunk ``k``; the new knot starts at ``pose`` (default: constant-velocity prediction)."""
    cfg = state.cfg
    state.traj.append(int(state.data.frames_us[k + 1]), pose)
    span_frames = cfg.tracking.span_frames
    span = state.data.span_with_min(max(k + 1 - span_frames, 0), k + 1)
    spec = StageSpec(
        "track", _seq_frame(state, k + 1), cfg.tracking.num_opti_steps, span,
        cfg.data.training_batch_size, stage_seed(cfg.seed, "track", k), [k + 1], [k, k + 1],
        train_gaussians=False, masked=True,
        # Longer windows than data.max_n_winsize where the span needs them: every window then ends at the
        # span's last event, so each one reaches the new knot.
        max_window=span[1] - span[0] if span_frames > 1 else 0,
    )  # fmt: skip
    if cfg.tracking.solver == "lm":
        return lm_track(state, spec, reporter)
    return run_stage(state, spec, reporter)


def add_gaussians_from_newest_view(state: SlamState, k: int) -> int:
    """New Gaussians at low-alpha, event-carrying pixels of knot ``k+1``'s view (chunk ``k``'s events);
    back-projected at ``mapping.new_gaussian_depth`` or else the view's median rendered depth."""
    cfg, data = state.cfg, state.data
    if cfg.mapping.max_new_gaussians == 0:  # the orbit configs: no render needed
        return 0
    out = render_knots(state, [k + 1])
    depth = cfg.mapping.new_gaussian_depth or median_depth(out.depth[0], out.alpha[0])
    if depth is None:
        return 0
    s, e = data.chunks[k]
    events = data.frames_of(s[None], e[None])[0]
    uncovered = (out.alpha[0] < cfg.mapping.new_gaussian_alpha) & (
        events.abs() > cfg.strategy.event_threshold
    )
    if not bool(uncovered.any()):
        return 0
    with torch.no_grad():
        pose = state.traj.knots()[k + 1]
    extra = gaussians_from_view(
        out.alpha[0], pose, data.camera, depth, max_new=cfg.mapping.max_new_gaussians,
        max_alpha=cfg.mapping.new_gaussian_alpha, opacity=cfg.gaussians.init_opacity,
        color=cfg.gaussians.init_color, generator=state.generator, events=events,
        event_threshold=cfg.strategy.event_threshold,
    )  # fmt: skip
    DefaultStrategy(cfg.strategy, cfg.gaussians.bounding_size).add(state.gaussians, None, extra)
    return len(extra["means"])


def replay_span(state: SlamState, first: int) -> tuple[int, int] | None:
    """The events of the tracked chunks before ``first``, which a local BA replays every
    ``mapping.replay_every``-th iteration (``run_stage`` decides whether it does), when they fill a
    window; else None. The initialization's chunks are left out: their knots come from a few frames'
    baseline and are the run's least certain."""
    start = state.num_init_chunks()
    if first <= start:
        return None
    span = state.data.span(start, first)
    return span if span[1] - span[0] >= state.cfg.data.min_n_winsize else None


def map_window(state: SlamState, k: int, reporter: StageReporter | None = None) -> StageRecord:
    cfg = state.cfg
    added = add_gaussians_from_newest_view(state, k)
    first = max(0, k + 1 - cfg.mapping.window)
    posed = range(max(first, 1), k + 2) if cfg.mapping.train_poses else range(0)
    spec = StageSpec(
        "map", _seq_frame(state, k + 1), cfg.mapping.num_opti_steps_for_BA, state.data.span(first, k + 1),
        cfg.data.training_batch_size, stage_seed(cfg.seed, "map", k), posed, range(first, k + 2),
        train_gaussians=True, anchored=True, replay_span=replay_span(state, first),
        replay_every=cfg.mapping.replay_every,
    )  # fmt: skip
    record = run_stage(state, spec, reporter)
    record.added = added
    return record


def step_chunk(
    state: SlamState, note: Callable[[StageRecord], None], reporter: StageReporter | None = None
) -> None:
    """The next chunk: tracking, then a local BA every ``mapping.every`` frames and a global BA every
    ``global_ba.every`` frames (not at the last chunk: the final one follows); ``note`` gets each
    stage's record as it ends."""
    cfg, pos = state.cfg, state.position
    k = pos.next_chunk
    note(track(state, k, reporter))
    pos.since_mapping += 1
    if pos.since_mapping >= cfg.mapping.every:
        note(map_window(state, k, reporter))
        pos.since_mapping = 0
    if cfg.global_ba.every > 0 and (k + 1) % cfg.global_ba.every == 0 and k + 1 < state.data.n_chunks:
        note(global_ba(state, final=False, reporter=reporter))
    pos.next_chunk += 1


def global_ba(state: SlamState, final: bool, reporter: StageReporter | None = None) -> StageRecord:
    cfg = state.cfg
    n = len(state.traj) - 1  # chunks covered by the trajectory
    stage = "final" if final else "gba"
    iters = cfg.global_ba.num_opti_steps_final if final else cfg.global_ba.num_opti_steps
    spec = StageSpec(
        stage, _seq_frame(state, n), iters, state.data.span(0, n), cfg.data.training_batch_size,
        stage_seed(cfg.seed, stage, n), range(1, n + 1), range(n + 1), train_gaussians=True, anchored=True,
        lr_boost=cfg.global_ba.lr_boost, tv_weight=cfg.global_ba.tv_weight,
        max_window=cfg.global_ba.max_n_winsize, early_stop=cfg.global_ba.final_early_stop or not final,
        knot_motion="rotation" if final and cfg.global_ba.final_hold_positions else "pose",
    )  # fmt: skip
    return run_stage(state, spec, reporter)

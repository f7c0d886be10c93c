"""The SLAM loop over a sequence: the start (motion search, initialization, optionally in branches),
then per chunk tracking, local BA every ``mapping.every`` frames and global BA every
``global_ba.every`` frames, and a final global BA. Before it, in this order: with
``global_ba.rate_check`` the tracked motion's speed is checked over the whole run
(:mod:`evgs.slam.rate_check`); with a range meter the map's first-surface scale is read
(:func:`~evgs.slam.metric_scale.read_surface_scale`; none with ``scale.surface_read = "end"``); with
``trajectory.smoothing_time`` the tracked positions are smoothed (:mod:`evgs.slam.smoothing`), so that
the final global BA refits the map to the smoothed path.

The state is snapshotted at every frame boundary and written to ``checkpoints/`` every
``output.checkpoint_every`` frames; Ctrl-C (KeyboardInterrupt) writes the last boundary's snapshot, so
``evgs run --resume`` repeats at most the interrupted frame and ends exactly where an uninterrupted run
would.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from functools import partial

import torch

from evgs import cpu_dispatch
from evgs.config import Config
from evgs.eval.plots import plot_range_agreement
from evgs.slam import checkpoint
from evgs.slam.branches import branch_hypotheses, run_branches
from evgs.slam.guards import BrightnessAnchor
from evgs.slam.metric_scale import apply_scale, estimate_scale, range_agreement, read_surface_scale
from evgs.slam.optimize import StageReporter
from evgs.slam.range_prior import RangePrior
from evgs.slam.rate_check import check_rate
from evgs.slam.run_dir import RunDir
from evgs.slam.seeding import initial_gaussians, seeded_map, seeding_generator
from evgs.slam.smoothing import smooth_trajectory
from evgs.slam.stages import global_ba, initialize, search, start_from, step_chunk
from evgs.slam.state import SlamState, StageRecord
from evgs.slam.trajectory import Trajectory, random_knots
from evgs.slam.windows import EventData


def new_state(cfg: Config, data: EventData, first: int = 0) -> SlamState:
    """Random Gaussians in the bounding box and near-identity knots at the initialization frames; the
    Gaussians seeded from chunks ``first`` on (``benches/slam_oracle.py --start``; a run starts at 0)."""
    generator = seeding_generator(cfg.seed, 0)
    m = min(cfg.init.num_frames, data.n_chunks)
    gaussians = initial_gaussians(cfg.gaussians, data, m, generator, first=first)
    knots = random_knots(m + 1, cfg.trajectory.init_pose_noise, generator)
    traj = Trajectory(data.frames_us[: m + 1], knots, cfg.trajectory.interpolation)
    anchor = BrightnessAnchor(cfg.guards.brightness_weight)
    return SlamState(cfg, data, traj, gaussians, generator, anchor, range_prior=RangePrior.for_run(cfg, data))


def describe(record: StageRecord) -> str:
    early = ", converged" if record.stopped_early else ""
    extra = f", +{record.added} new" if record.added else ""
    extra += f", {record.pruned_blockers} blockers pruned" if record.pruned_blockers else ""
    extra += f", {record.note}" if record.note else ""
    return (
        f"{record.stage} frame {record.frame}: {record.iterations} it{early}, loss {record.loss:.5f}, "
        f"{record.n_gaussians} Gaussians{extra}, {record.seconds:.1f} s"
    )


def write_metric_scale(state: SlamState, run: RunDir, log: Callable[[str], None] | None) -> None:
    """Make the state metric as ``[scale]`` says; when the data cannot give the scale, the outputs stay in
    map units with the reason in the log and ``metrics.json`` (a finished run is not thrown away)."""
    try:
        est = estimate_scale(state, state.cfg.scale)
    except ValueError as e:
        state.metric = {"metric_scale_failed": str(e)}
        message = f"warning: outputs stay in map units: {e}"
    else:
        if est is None:
            return
        # The final checkpoint keeps map units: a resumed run rescales the same way.
        apply_scale(state, est.scale)
        state.metric = {
            "metric_scale": est.scale,
            "metric_scale_source": est.source,
            "range_samples": est.samples,
        }
        message = f"metric scale ({est.source}): {est.scale:.4g} m per map unit"
    say(run, log, message)


def say(run: RunDir, log: Callable[[str], None] | None, message: str) -> None:
    """A line for the run's log and for ``log`` (the console), if given."""
    run.log(message)
    if log is not None:
        log(message)


def check_range_meter(state: SlamState, run: RunDir, log: Callable[[str], None] | None) -> None:
    """With a range meter: how the map's distance from the cameras keeps to the meter's over the run,
    a check that needs no ground truth, whatever ``scale.source`` is (``diagnostics/range_meter.png``;
    ``metrics.json``: ``range_map_drift``, and ``range_map_ratio``, the median of range over the map's
    first surface, which is 1 when the map agrees with a trajectory made metric by the closing rate)."""
    if state.data.ranges is None:
        return
    try:
        agreement = range_agreement(state, *state.data.ranges, state.cfg.scale.min_alpha)
    except ValueError:  # no sample inside the run: nothing to compare
        return
    drift, unit, covered = agreement.drift(), agreement.median_ratio(), int(agreement.covered.sum())
    state.metric |= {"range_map_ratio": unit, "range_map_drift": drift, "range_map_samples": covered}
    if covered < 2:
        message = (
            f"range meter against the map: the map covers the principal ray at {covered} of the "
            f"{len(agreement.t_us)} samples, too few to compare"
        )
    else:
        t = (agreement.t_us - agreement.t_us[0]) / 1e6
        path = run.diagnostics / "range_meter.png"
        plot_range_agreement(t, agreement.ranges, agreement.depth, unit, drift, path)
        message = (
            f"range meter against the map's first surface: {drift:+.1%} from the run's first fifth to its "
            "last (0: the map keeps the meter's distance; docs/ablations.md §47)"
        )
    say(run, log, message)


def adopt(state: SlamState, other: SlamState) -> None:
    """Make ``state`` (the caller's object) carry ``other``'s contents."""
    for f in dataclasses.fields(state):
        setattr(state, f.name, getattr(other, f.name))


def start(state: SlamState, note: Callable[[StageRecord], None], reporter: StageReporter | None) -> None:
    """The motion search (``init.motion_search``), then the initialization of its best motion — or of its
    ``init.branches`` best, each carried on for ``init.branch_frames`` frames, the best branch kept."""
    cfg = state.cfg
    hyps = []
    if cfg.init.motion_search:
        found, record = search(state, reporter)
        note(record)
        hyps = branch_hypotheses(found.ranked, cfg.init.branches, cfg.init.branch_directions)
    if len(hyps) > 1 or cfg.init.branch_restarts > 1:
        adopt(state, run_branches(state, hyps, note, reporter, reseed=partial(seeded_map, state)))
        return
    if hyps:
        start_from(state, hyps[0])
    note(initialize(state, reporter))
    state.position.initialized, state.position.next_chunk = True, state.num_init_chunks()


def pin_threads(cfg: Config) -> None:
    """Pin torch's CPU thread count to ``cfg.torch_threads``: its reductions split by thread count, so
    only a fixed count repeats a run bit for bit on any machine (the Rust core is invariant already)."""
    torch.set_num_threads(cfg.torch_threads)


def run_slam(
    state: SlamState,
    run: RunDir,
    reporter: StageReporter | None = None,
    log: Callable[[str], None] | None = None,
) -> SlamState:
    """Run (or continue, from ``state.position``) to the end; write the outputs into ``run``.

    Pins torch's threads for the process (:func:`pin_threads`), fresh or resumed."""
    cfg, n_chunks = state.cfg, state.data.n_chunks
    pin_threads(cfg)
    if (why := cpu_dispatch.unpinned()) is not None:
        say(run, log, f"warning: {why}")

    def note(record: StageRecord) -> None:
        say(run, log, describe(record))

    last = checkpoint.snapshot(state)
    since_saved = 0

    def boundary(force: bool = False) -> None:
        nonlocal last, since_saved
        last = checkpoint.snapshot(state)
        since_saved += 1
        if force or since_saved >= cfg.output.checkpoint_every:
            checkpoint.save(run.checkpoint_path, last)
            run.write_trajectory(state)
            since_saved = 0

    try:
        if not state.position.initialized:
            start(state, note, reporter)
            boundary(force=True)
        while state.position.next_chunk < n_chunks:
            step_chunk(state, note, reporter)
            boundary()
        if not state.position.finished:
            if cfg.global_ba.rate_check > 0:
                note(check_rate(state, seeded_map(state), reporter))
            state.surface_scale = read_surface_scale(state)  # before the smoother: the map fits these cameras
            tc = cfg.trajectory
            tau, order = tc.smoothing_time, tc.smoothing_order
            if tau > 0:
                moved = smooth_trajectory(state.traj, tau, order, tc.smoothing_end_fit)
                fit = tc.smoothing_end_fit
                ends = f", ends extended by a fit over {fit:g} τ" if fit else ""
                say(run, log, f"smoothed the tracked positions (τ = {tau:g} s, order {order}{ends}): "
                              f"moved {moved:.4f} at most")  # fmt: skip
            # Under its own relief prior if the config says so: the copy shares the map and the
            # trajectory, which the stage edits in place.
            final = state.with_relief_prior(cfg.global_ba.final_depth_tv)
            note(global_ba(final, final=True, reporter=reporter))
            state.position.finished = True
            boundary(force=True)
    except KeyboardInterrupt:
        checkpoint.save(run.checkpoint_path, last)
        run.log(f"interrupted; checkpoint at chunk {last['position']['next_chunk']} written")
        raise
    write_metric_scale(state, run, log)
    check_range_meter(state, run, log)
    run.write_outputs(state)
    return state

"""Map quality measured apart from pose estimation (a diagnostic benchmark, not a test).

    PYTHONPATH=python python benches/slam_oracle.py [--seq synthetic/orbit_ambient] [--track 6]
        [--start 0] [--track-from K] [--rates 1,0.5,0.25] [--set K=V]

0. With ``--rates``: the motion search's refit (``init.search_steps`` on the seeded map, the knots
   frozen) on the truth's own first knots, its motion scaled by each rate, scored as the search scores
   a hypothesis; beside it the cosine between the measured and the predicted event frames and the
   squared error's best gain ``⟨E, Ê⟩ / ‖Ê‖²`` (below 1: the prediction is stronger than the events).
   Where a smaller rate scores better, the search cannot find the truth (docs/ablations.md §43).

1. Initialization with the ground-truth knots, frozen (translations scaled by ``init_depth`` / the
   distance to the first frame's range sample, so the map sits where a real run would put it): the map
   learns from correct poses only. ``--start A`` trains it on chunks ``A`` to ``A + m`` instead of the
   first ``m`` (the poses relative to frame ``A``), to ask the same questions of a later stretch of the
   sequence. ``--track-from K`` tracks from chunk ``K`` instead of the map's last one, the knots after
   ``K`` dropped: with a map trained over the whole way (``--set init.num_frames=75``) it asks whether a
   map from the truth's poses holds tracking on the swirl's way back (docs/ablations.md §58). The
   velocity prior's frames count from the map's last chunk, so set ``tracking.velocity_prior=0`` to
   track as a run does after them.
2. The map's event loss on the init chunks, beside the loss of predicting no events.
3. The loss along the true motion of each new chunk: the new knot at ``a`` times the true step from the
   previous knot (``a = 0`` no motion, ``a = 1`` the truth). A map that generalises has its minimum at 1;
   a minimum below 1 means tracking on it under-estimates the motion.
4. Tracking of ``--track`` new chunks from the constant-velocity prediction, the map frozen: the
   rotation / translation error of each new knot against the truth (the error compounds through the
   prediction, so its growth per frame is the tracker's bias on this map).

Options after ``--set`` are config overrides, as for ``evgs run``.
"""

from __future__ import annotations

import evgs  # noqa: F401  first, as in `evgs run`: it pins numpy's and torch's CPU code paths

# isort: split
import argparse
import dataclasses
import time

import numpy as np
import torch
from evgs.config import load_config
from evgs.data.sequence import Sequence
from evgs.render import render
from evgs.slam.lie import se3_exp, se3_inverse, se3_log
from evgs.slam.loss import pointwise_error, predicted_events
from evgs.slam.motion_search import EVAL_WINDOWS, fit, search_chunks
from evgs.slam.optimize import StageSpec, fixed_windows, run_stage, window_event_score
from evgs.slam.pipeline import new_state, pin_threads
from evgs.slam.stages import set_brightness_reference, track
from evgs.slam.state import SlamState, stage_seed
from evgs.slam.trajectory import Trajectory, scaled_motion
from evgs.slam.windows import EventData
from rich.console import Console
from rich.table import Table

STEPS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5)


def gt_knots(seq: Sequence, data: EventData, init_depth: float, origin: int = 0) -> torch.Tensor:
    """GT camera-to-world poses at the frames, relative to frame ``origin``, in map units (the range
    sample nearest that frame is ``init_depth``)."""
    gt = seq.poses_gt()
    ranges = seq.range_samples()
    if gt is None or ranges is None:
        raise SystemExit(f"{seq.root}: needs poses_gt.txt and range.csv (a simulated sequence)")
    t, T = gt
    G = torch.as_tensor(T[np.searchsorted(t, data.frames_us)])
    rel = se3_inverse(G[origin]) @ G
    near = int(np.argmin(np.abs(ranges[0] - data.frames_us[origin])))
    rel[:, :3, 3] *= init_depth / float(ranges[1][near])
    return rel


def landscape(state: SlamState, rel: torch.Tensor, k: int, windows: int = 3) -> np.ndarray:
    """Mean event loss (the configured L1/MSE) of chunk ``k`` with knot ``k+1`` at each of :data:`STEPS`."""
    data, cfg = state.data, state.cfg
    sampler = data.sampler(data.span_with_min(k, k + 1), 7)
    wins = [data.windows(sampler, 1, 1) for _ in range(windows)]
    step = se3_log(se3_inverse(rel[k]) @ rel[k + 1])
    out = []
    for a in STEPS:
        knots = rel[: k + 2].clone()
        knots[k + 1] = rel[k] @ se3_exp(a * step)
        traj = Trajectory(data.frames_us[: k + 2], knots)
        losses = []
        for w in wins:
            vm = traj.viewmats_at(np.concatenate([w.t_start, w.t_end]))
            with torch.no_grad():
                r = render(**state.gaussians.render_inputs(), viewmats=vm, camera=data.camera, background=0.0)
            d = w.frames[0] - predicted_events(r.color[0, ..., 0], r.color[1, ..., 0], cfg.loss)
            losses.append(float(pointwise_error(d, cfg.loss.event_loss).mean()))
        out.append(np.mean(losses))
    return np.array(out)


def search_refits(state: SlamState, rel: torch.Tensor, rates: list[float]) -> Table:
    """Step 0: the search's refit and score on the truth's knots at each rate (``state`` untouched)."""
    data, cfg = state.data, state.cfg
    m, _ = search_chunks(state)
    seed, span = stage_seed(cfg.seed, "search", 0), data.span(0, m)
    table = Table(title=f"the search's refit on the truth's first {m} chunks, its motion × rate")
    for col in ("rate", "score", "cos(E, Ê)", "best gain"):
        table.add_column(col, justify="right")
    for rate in rates:
        trial = fit(state, scaled_motion(rel[: m + 1], rate), None)
        losses, ee, pp, ep = [], 0.0, 0.0, 0.0
        for win, gray in fixed_windows(trial, span, seed, EVAL_WINDOWS):  # as fixed_window_loss scores
            losses.append(window_event_score(win.frames, gray, cfg.loss))
            e, p = win.frames.double(), predicted_events(gray[:1], gray[1:], cfg.loss).double()
            ee, pp, ep = ee + float((e * e).sum()), pp + float((p * p).sum()), ep + float((e * p).sum())
        score = float(np.mean(losses))
        table.add_row(f"{rate:g}", f"{score:.5f}", f"{ep / np.sqrt(ee * pp):.3f}", f"{ep / pp:.3f}")
    return table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seq", default="synthetic/orbit_ambient")
    ap.add_argument("--track", type=int, default=6, help="new chunks to track after the init")
    ap.add_argument("--start", type=int, default=0, help="first chunk of the map's training (0: the init's)")
    ap.add_argument("--track-from", type=int, default=-1, help="first chunk to track (-1: the map's last)")
    ap.add_argument("--rates", default="", help="comma-separated rates for step 0 (none: skipped)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    console = Console()
    cfg = load_config(f"configs/{args.seq}.toml", args.overrides)
    seq = Sequence.load(f"data/{args.seq}")
    cfg = dataclasses.replace(cfg, seq=str(seq.root))
    data = EventData.from_sequence(seq, cfg.data)
    pin_threads(cfg)  # as run_slam does
    start = args.start
    state = new_state(cfg, data, first=start)  # seeded in front of the start frame's camera
    m = state.num_init_chunks()
    e = start + m  # the map's last chunk: tracking starts after it
    first = e if args.track_from < 0 else args.track_from
    if start < 0 or not 1 <= first <= e or first + args.track > data.n_chunks or (start and args.rates):
        raise SystemExit(
            f"--start {start}, --track-from {first}: needs 0 <= start, 1 <= track-from <= start + {m}, "
            f"track-from + --track <= {data.n_chunks} chunks, and --rates only from the start"
        )
    rel = gt_knots(seq, data, cfg.gaussians.init_depth, origin=start)

    def truth_until(n: int) -> Trajectory:
        """The truth's knots up to chunk ``n``."""
        return Trajectory(data.frames_us[: n + 1], rel[: n + 1], cfg.trajectory.interpolation)

    if args.rates:
        console.print(search_refits(state, rel, [float(r) for r in args.rates.split(",")]))
    state.traj = truth_until(e)
    spec = StageSpec(
        "init", e, cfg.init.num_opti_steps_for_init, data.span(start, e), cfg.data.training_batch_size,
        stage_seed(cfg.seed, "init", e), [], range(start, e + 1), train_gaussians=True,
        lr_boost=cfg.init.lr_boost,
    )  # fmt: skip
    t0 = time.perf_counter()
    record = run_stage(state, spec)
    set_brightness_reference(state)
    console.print(
        f"map from GT poses: {record.iterations} it, {time.perf_counter() - t0:.0f} s, "
        f"{len(state.gaussians)} Gaussians"
    )
    inside = landscape(state, rel, e - 1)
    table = Table(title="event loss along the true motion (÷ minimum); a = fraction of the true step")
    table.add_column("chunk")
    for a in STEPS:
        table.add_column(f"a={a:g}", justify="right")
    table.add_column("argmin", justify="right")
    tracked = range(first, first + args.track)
    for k, vals in [(e - 1, inside)] + [(k, landscape(state, rel, k)) for k in tracked]:
        name = f"{k} (init)" if k < e else str(k)
        table.add_row(name, *(f"{v / vals.min():.3f}" for v in vals), f"{STEPS[int(vals.argmin())]:g}")
    console.print(table)
    errors = Table(title=f"tracking on the frozen map ({cfg.tracking.solver}), error of each new knot")
    for col in ("knot", "rotation °", "translation (map units)", "true step °"):
        errors.add_column(col, justify="right")
    if first < e:
        state.traj = truth_until(first)
    for k in tracked:
        track(state, k)
        with torch.no_grad():
            err = se3_log(se3_inverse(rel[k + 1]) @ state.traj.knots()[k + 1])
            true_step = se3_log(se3_inverse(rel[k]) @ rel[k + 1])
        errors.add_row(
            str(k + 1), f"{np.degrees(float(err[3:].norm())):.3f}", f"{float(err[:3].norm()):.4f}",
            f"{np.degrees(float(true_step[3:].norm())):.3f}",
        )  # fmt: skip
    console.print(errors)


if __name__ == "__main__":
    main()

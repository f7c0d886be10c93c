"""``evgs eval RUN_DIR...``: metrics, figures and reports per run, and one comparison table."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

import polars as pl

from evgs.io_util import atomic_path

if TYPE_CHECKING:
    from evgs.eval.run import RunEvaluation

# Columns of the printed comparison table (the CSV has every summary column).
TABLE_COLUMNS = ["run", "frames", "ate_rmse", "drift_deg", "psnr_db", "lpips", "ssim", "depth_err_pct",
                 "rpe_trans_rmse", "elope_score"]  # fmt: skip


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval",
        help="evaluate SLAM runs against ground truth (ATE, drift, RPE, PSNR/SSIM/LPIPS, depth, ELOPE score)",
        description="Evaluate run directories: writes <run>/eval/ (metrics.json, figures) and "
        "<run>/report.md + report.html, and prints one comparison table.",
    )
    p.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR")
    p.add_argument("--csv", type=Path, metavar="OUT", help="write the comparison table as CSV")
    p.add_argument("--export-tum", type=Path, metavar="DIR", help="export GT and aligned estimate (TUM)")
    p.add_argument("--export-kitti", type=Path, metavar="DIR", help="export GT and aligned estimate (KITTI)")
    p.add_argument(
        "--elope-submission",
        type=Path,
        metavar="OUT",
        help="write the ELOPE challenge JSON for the ELOPE runs (velocities of the Sim(3)-aligned "
        "estimate, so ground truth is needed, as in the paper)",
    )
    p.add_argument("--no-images", action="store_true", help="skip rendering and image metrics")
    p.add_argument(
        "--no-depth", action="store_true", help="skip the map's depth against the simulated scene's"
    )
    p.add_argument(
        "--image-poses",
        choices=["estimate", "gt"],
        default="estimate",
        help="render the map for the image metrics from the estimated poses (default: the run's own view, "
        "pose errors count) or from the ground-truth viewpoints mapped through the Sim(3) (the map alone)",
    )
    p.add_argument("--no-report", action="store_true", help="metrics only: no figures or reports")
    p.add_argument("--se3", action="store_true", help="align with SE(3) instead of Sim(3) (scale fixed to 1)")
    p.add_argument("--rpe-delta-m", type=float, default=1.0, help="path length per RPE pair (GT units)")
    elope = p.add_mutually_exclusive_group()
    elope.add_argument(
        "--elope",
        dest="elope",
        action="store_true",
        default=None,
        help="compute the ELOPE score (default: only for sequences whose source is ELOPE)",
    )
    elope.add_argument("--no-elope", dest="elope", action="store_false")
    p.set_defaults(func=run)


def comparison_table(evals: list[RunEvaluation]) -> pl.DataFrame:
    return pl.DataFrame([ev.summary() for ev in evals])


def run(args: argparse.Namespace) -> int:
    # Imported here: torch and matplotlib would slow down every other `evgs` command's start-up.
    from evgs.eval.elope import sequence_id, submission_velocities, write_submission
    from evgs.eval.export import export_run
    from evgs.eval.plots import plot_run
    from evgs.eval.report import write_report
    from evgs.eval.run import evaluate_run, save_metrics

    evals = []
    for run_dir in args.runs:
        ev = evaluate_run(
            run_dir, images=not args.no_images, elope=args.elope, with_scale=not args.se3,
            rpe_delta_m=args.rpe_delta_m, image_poses=args.image_poses, depth=not args.no_depth,
        )  # fmt: skip
        save_metrics(ev, run_dir / "eval" / "metrics.json")
        if not args.no_report:
            write_report(ev, plot_run(ev, run_dir / "eval"), run_dir)
        for d, fmt in ((args.export_tum, "tum"), (args.export_kitti, "kitti")):
            if d is not None:
                export_run(ev, d, fmt)
        for note in ev.notes:
            print(f"{ev.label}: {note}")
        evals.append(ev)
    table = comparison_table(evals)
    cfg = {"tbl_rows": -1, "tbl_cols": -1, "tbl_width_chars": 200, "float_precision": 4}
    with pl.Config(**cfg, tbl_hide_dataframe_shape=True):
        print(table.select([c for c in TABLE_COLUMNS if c in table.columns]))
    if args.csv is not None:
        with atomic_path(args.csv) as tmp:
            table.write_csv(tmp)
    if args.elope_submission is not None:
        entries = {
            sequence_id(ev.sequence.name): submission_velocities(ev.assoc.t, ev.traj.p_est)
            for ev in evals
            if ev.elope_score is not None
        }
        if not entries:
            raise ValueError("--elope-submission: none of the runs is an ELOPE run (use --elope to force)")
        write_submission(args.elope_submission, entries)
    return 0

"""``evgs bench slam``: simulate (cached), run and evaluate the synthetic presets over several seeds, and
print one table (also written as CSV and Markdown)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from evgs.cli import UserError


def register(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmark suites (slam: the synthetic presets over seeds)")
    suites = bench.add_subparsers(dest="suite", metavar="SUITE")
    suites.required = True
    from evgs.bench.slam import DEFAULT_PRESETS  # light: no torch

    p = suites.add_parser(
        "slam",
        help="run the SLAM suite on the synthetic presets and print one table",
        description="For every preset and seed: simulate data/synthetic/<preset> if missing, run evgs run "
        "with configs/synthetic/<preset>.toml in its own process, evaluate it (Sim(3) ATE, drift, "
        "PSNR/SSIM/LPIPS), then print and write runs.csv, summary.csv and summary.md (mean ± sample "
        "standard deviation over seeds, with the issue's targets).",
    )
    p.add_argument("--presets", nargs="+", default=list(DEFAULT_PRESETS), metavar="PRESET",
                   help=f"synthetic presets (default: {' '.join(DEFAULT_PRESETS)})")  # fmt: skip
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], metavar="SEED", help="default: 0 1 2")
    p.add_argument("--frames", type=int, metavar="N", help="at most N frames per run (data.num_frames)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override passed to every run (repeatable)")  # fmt: skip
    p.add_argument("--out", type=Path, metavar="DIR", help="suite directory (default: runs/bench-<UTC time>)")
    p.add_argument("--data-root", type=Path, default=Path("data"), metavar="DIR",
                   help="sequences are DIR/synthetic/<preset> (default: data)")  # fmt: skip
    p.add_argument("--resume", action="store_true",
                   help="continue the suite in --out: finished runs are only re-evaluated (e.g. to add "
                        "the image metrics after --no-images), interrupted ones resume from their "
                        "checkpoints")  # fmt: skip
    p.add_argument("--no-images", action="store_true", help="skip rendering and image metrics")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from evgs.bench.slam import plan_runs, run_suite

    if args.resume and args.out is None:
        raise UserError("--resume continues a suite: give its directory with --out")
    out = args.out or Path("runs") / time.strftime("bench-%Y%m%d-%H%M%S", time.gmtime())
    if not args.resume and out.exists() and any(out.iterdir()):
        raise UserError(f"{out}: not empty; continue that suite with --resume or choose another --out")
    specs = plan_runs(args.presets, args.seeds, args.frames, args.overrides, out, args.data_root)
    rows, _, table = run_suite(specs, out, args.seeds, resume=args.resume, images=not args.no_images)
    print(table)
    print(f"written: {out / 'runs.csv'}, {out / 'summary.csv'}, {out / 'summary.md'}")
    failed = sum(r["status"] != "ok" for r in rows)
    return 1 if failed else 0

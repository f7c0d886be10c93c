"""``evgs import <dataset> RAW_PATH``: convert a data set's raw download to the canonical layout."""

from __future__ import annotations

import argparse
import importlib
import sys
from functools import partial
from pathlib import Path
from types import ModuleType

from rich.console import Console
from rich.progress import Progress

from evgs.data.importers import ADAPTERS, parse_frames, select_frames, write_imported

# Arguments every dataset shares; the rest are the adapter's ``load`` keywords.
_COMMON = {"command", "dataset", "func", "raw_path", "out", "frames"}


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "import",
        help="convert a data set's raw download to the canonical sequence layout",
        description="Convert a data set's raw download to the canonical sequence layout "
        "(sequence.toml, events.parquet, frames.csv, poses_gt.txt, ...).",
    )
    datasets = parser.add_subparsers(dest="dataset", metavar="DATASET", required=True)
    for name, module_name in ADAPTERS.items():
        module = importlib.import_module(module_name)
        p = datasets.add_parser(name, help=module.DESCRIPTION, description=module.__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
        p.add_argument("raw_path", type=Path, metavar="RAW_PATH", help=module.RAW_PATH_HELP)
        p.add_argument("--out", type=Path, help=f"output folder (default data/{name}/<sequence>)")
        p.add_argument(
            "--frames", metavar="A:B", help="keep frames A..B-1 only (Python slice; re-indexed from 0)"
        )
        module.add_arguments(p)
        p.set_defaults(func=partial(_run, module, name))


def _run(module: ModuleType, dataset: str, args: argparse.Namespace) -> int:
    frames = parse_frames(args.frames) if args.frames else None
    options = {k: v for k, v in vars(args).items() if k not in _COMMON}
    with Progress(console=Console(stderr=True), transient=True) as progress:
        seq = module.load(args.raw_path, progress, **options)
        if frames is not None:
            seq = select_frames(seq, *frames)
        out = args.out or Path("data") / dataset / seq.name
        written = write_imported(seq, out, progress)
    for note in seq.notes:
        print(f"note: {note}", file=sys.stderr)
    ev = seq.events
    poses = "no" if seq.poses_gt is None else str(len(seq.poses_gt[0]))
    print(
        f"{written.root}: {len(ev)} events over {ev.duration_us / 1e6:.3f} s, "
        f"{len(seq.frames_us)} frames, {poses} ground-truth poses, "
        f"{'no' if seq.images is None else len(seq.images)} images"
    )
    return 0

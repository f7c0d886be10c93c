"""``evgs run``: the SLAM pipeline on one sequence, into a fresh run directory (or ``--resume`` one)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from evgs.cli import UserError
from evgs.config import CONFIG_DIR, DEFAULT_CONFIG, Config, add_config_arguments, load_config

DATA_DIR = Path("data")
SEENIC_FOLDERS = {  # evgs name → SEENIC folder (Zenodo record 7370076); the paper used the slow runs
    "orbit_ambient": "hubble-orbit-slow-ambient",
    "approach_ambient": "hubble-approach-slow-ambient",
    "orbit_centre": "hubble-orbit-slow-centre",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run event-only SLAM (initialization, tracking, mapping, global BA) on a sequence",
        description="Run the SLAM pipeline on a sequence and write runs/<seq>/<timestamp>/ (config.toml, "
        "traj_est.txt, gaussians.ply, metrics.json, diagnostics/, checkpoints/, log.txt). With ground "
        "truth, prints the trajectory error (ATE RMSE after Sim(3) alignment, rotation drift).",
    )
    p.add_argument(
        "--seq",
        metavar="DATASET/NAME|DIR",
        help="e.g. synthetic/orbit_ambient (simulated when missing), seenic/orbit_ambient (read from "
        "data/seenic/...), or a sequence folder; default: the config's seq. Its config is "
        "configs/DATASET/NAME.toml when that exists",
    )
    add_config_arguments(p)
    p.add_argument("--out", type=Path, metavar="DIR", help="runs directory (default: output.runs_dir)")
    p.add_argument("--resume", type=Path, metavar="RUN_DIR", help="continue an interrupted run")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def config_for(seq: str | None, config: str | None) -> Path:
    """``--config`` if given, else ``configs/<seq>.toml``, else the data set's ``_dataset.toml``, else
    the default."""
    if config is not None:
        return Path(config)
    if seq is not None and not Path(seq).is_dir():
        for cand in (CONFIG_DIR / f"{seq}.toml", CONFIG_DIR / Path(seq).parent / "_dataset.toml"):
            if cand.is_file():
                return cand
    return DEFAULT_CONFIG


def sequence_folder(seq: str | None, cfg: Config) -> Path:
    """The folder of ``--seq`` (or the config's ``seq``), simulating built-in synthetic sequences."""
    if seq is None:
        folder = Path(cfg.seq)
        parts = folder.parts[-2:] if folder.parts[:1] == (DATA_DIR.name,) else ()
    elif Path(seq).is_dir():
        return Path(seq)
    else:
        parts = Path(seq).parts
        if len(parts) != 2:
            raise UserError(f"--seq {seq}: expected DATASET/NAME (e.g. synthetic/orbit_ambient) or a folder")
        folder = DATA_DIR / seq
    if (folder / "sequence.toml").is_file():
        return folder
    if len(parts) == 2 and parts[0] == "synthetic":
        from evgs.sim import ensure_sequence  # the simulator (renderer, Rust ESIM) is only needed here

        return ensure_sequence(f"synthetic/{parts[1]}", DATA_DIR)
    if len(parts) == 2 and parts[0] == "seenic":
        raw = SEENIC_FOLDERS.get(parts[1], f"hubble-<orbit|approach>-slow-<lighting> folder for {parts[1]}")
        raise UserError(
            f"{folder}: no such sequence. Download SEENIC from Zenodo (https://zenodo.org/records/7370076), "
            f"unpack the folder {raw}/ (events.csv, cam-poses.csv), then run: "
            f"evgs import seenic PATH/TO/{raw} --out {folder}"
        )
    raise UserError(f"{folder}: not a sequence folder (no sequence.toml)")


def run(args: argparse.Namespace) -> int:
    # Imported here: torch and the pipeline would slow down every other command's start-up.
    from rich.console import Console

    from evgs.data.sequence import Sequence
    from evgs.slam import checkpoint
    from evgs.slam.pipeline import new_state, run_slam
    from evgs.slam.progress import RunReporter
    from evgs.slam.run_dir import RunDir, trajectory_error
    from evgs.slam.windows import EventData

    console = Console(stderr=True)
    if args.resume is not None:
        if args.seq or args.config or args.overrides or args.out:
            raise UserError(
                "--resume continues with the run's own config.toml: drop --seq/--config/--set/--out"
            )
        run_dir = RunDir(args.resume)
        cfg = run_dir.config()
        snap = checkpoint.load(run_dir.checkpoint_path)
        seq = Sequence.load(cfg.seq)
        state = checkpoint.restore(snap, cfg, EventData.from_sequence(seq, cfg.data))
        run_dir.log(f"resumed at chunk {state.position.next_chunk}")
    else:
        cfg = load_config(config_for(args.seq, args.config), args.overrides)
        folder = sequence_folder(args.seq, cfg)
        cfg = dataclasses.replace(cfg, seq=str(folder.resolve()))
        seq = Sequence.load(folder)
        data = EventData.from_sequence(seq, cfg.data)
        uses = {
            "scale.source = 'range'": cfg.scale.source == "range",
            "scale.range_weight > 0": cfg.scale.range_weight > 0,
            "scale.rate_weight > 0": cfg.scale.rate_weight > 0,
            "init.search_range_weight > 0": cfg.init.search_range_weight > 0,
            "init.search_meter_advance = true": cfg.init.search_meter_advance and cfg.init.motion_search,
        }
        for key in (k for k, on in uses.items() if on and data.ranges is None):
            raise UserError(f"{folder}: {key} needs range.csv (a range meter); change {key.split()[0]}")
        run_dir = RunDir.create(args.out or Path(cfg.output.runs_dir), seq.name, cfg)
        state = new_state(cfg, data)
        run_dir.log(f"run of {seq.root} ({len(data.events)} events, {data.n_chunks} chunks)")
    console.print(f"run directory: {run_dir.root}")
    try:
        with RunReporter(run_dir.diagnostics, show=not args.quiet, console=console) as reporter:
            run_slam(state, run_dir, reporter, log=None if args.quiet else console.print)
    except KeyboardInterrupt:
        console.print(f"interrupted: continue with  evgs run --resume {run_dir.root}")
        raise
    if "metric_scale_failed" in state.metric:
        console.print(f"warning: outputs stay in map units: {state.metric['metric_scale_failed']}")
    error = trajectory_error(run_dir.root)
    run_dir.write_metrics(state, error)
    if "ate_rmse" in error:
        console.print(f"ATE RMSE (Sim(3)) {error['ate_rmse']:.4g}, rotation drift {error['drift_deg']:.2f}°")
        if (
            "metric_scale" in state.metric and "scale" in error
        ):  # metric outputs: the alignment should not need to rescale
            console.print(
                f"metric scale ({state.metric['metric_scale_source']}): the Sim(3) alignment rescales the "
                f"estimate by {error['scale']:.4g} (scale error {abs(error['scale'] - 1) * 100:.1f} %)"
            )
    console.print(f"done: {run_dir.root}")
    return 0

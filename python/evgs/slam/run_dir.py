"""The run directory (``runs/<seq>/<timestamp>/``) and the files a run leaves in it.

``config.toml`` (resolved config; ``seq`` is the sequence folder), ``traj_est.txt`` (TUM, camera-to-
world knots at frame timestamps), ``gaussians.ply`` (3DGS layout), ``metrics.json`` (the pipeline's
statistics and, with ground truth, the trajectory error), ``diagnostics/``, ``checkpoints/``,
``log.txt``. Every file is written atomically.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from evgs import cpu_dispatch
from evgs.config import Config, config_from_snapshot, save_config
from evgs.data.tum import write_tum
from evgs.eval.run import evaluate_run, read_run_config, resolve_sequence
from evgs.io_util import atomic_path
from evgs.slam import checkpoint
from evgs.slam.gaussians import save_ply
from evgs.slam.range_prior import meter_jumps, valid_samples
from evgs.slam.state import SlamState


@dataclass(frozen=True)
class RunDir:
    root: Path

    @property
    def config_path(self) -> Path:
        return self.root / "config.toml"

    @property
    def checkpoint_path(self) -> Path:
        return self.root / "checkpoints" / checkpoint.CHECKPOINT_NAME

    @property
    def diagnostics(self) -> Path:
        return self.root / "diagnostics"

    @classmethod
    def create(cls, runs_dir: str | Path, seq_name: str, cfg: Config) -> RunDir:
        """A fresh ``runs_dir/<seq_name>/<UTC timestamp>`` (suffixed ``-2``, ``-3`` … if taken)."""
        base = Path(runs_dir) / seq_name / time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        root, i = base, 1
        while root.exists():
            i += 1
            root = base.with_name(f"{base.name}-{i}")
        root.mkdir(parents=True)
        for sub in ("diagnostics", "checkpoints"):
            (root / sub).mkdir()
        save_config(cfg, root / "config.toml")
        return cls(root)

    def config(self) -> Config:
        """The run's config snapshot; keys a later evgs added take their defaults (said in the log)."""
        cfg, filled = config_from_snapshot(read_run_config(self.root), str(self.config_path))
        if filled:
            names = ", ".join(filled)
            self.log(f"keys missing from config.toml (added after this run), at their defaults: {names}")
        return cfg

    def log(self, line: str) -> None:
        """Append a time-stamped line to ``log.txt``."""
        with open(self.root / "log.txt", "a") as f:
            f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S', time.gmtime())} {line}\n")

    def write_trajectory(self, state: SlamState) -> None:
        t_us, T_wc = state.traj.poses_numpy()
        write_tum(self.root / "traj_est.txt", t_us / 1e6, T_wc)

    def write_outputs(self, state: SlamState) -> None:
        self.write_trajectory(state)
        save_ply(self.root / "gaussians.ply", state.gaussians)

    def write_metrics(self, state: SlamState, extra: dict) -> dict:
        """Pipeline statistics plus ``extra`` (e.g. the trajectory error) to ``metrics.json``."""
        doc = pipeline_metrics(state) | extra
        with atomic_path(self.root / "metrics.json") as tmp:
            tmp.write_text(json.dumps(_finite(doc), indent=1, allow_nan=False))
        return doc


def trajectory_error(root: Path) -> dict:
    """ATE RMSE after Sim(3) alignment, rotation drift and friends from ``evgs.eval`` (no image or depth
    metrics: those belong to ``evgs eval``); empty without ground truth."""
    cfg = read_run_config(root)
    if resolve_sequence(root, cfg).poses_gt() is None:
        return {}
    try:
        ev = evaluate_run(root, images=False, depth=False)
    except ValueError as e:  # e.g. fewer than 3 poses overlap the ground truth
        return {"trajectory_error": f"not computed: {e}"}
    keys = (
        "ate_rmse", "drift_deg", "rot_err_rmse_deg", "gaze_err_rmse_deg", "scale", "rpe_trans_rmse",
        "rpe_rot_rmse_deg",
    )  # fmt: skip
    summary = ev.traj.summary()
    return {k: summary[k] for k in keys}


def range_meter_jumps(state: SlamState) -> int:
    """Pairs of consecutive range samples the closing rate leaves out (the meter's ray crossed an edge)."""
    if state.data.ranges is None:
        return 0
    return int(meter_jumps(valid_samples(*state.data.ranges)[1]).sum())


def pipeline_metrics(state: SlamState) -> dict:
    h = state.history
    return {
        "frames": len(state.traj),
        "gaussians": len(state.gaussians),
        "iterations": sum(r.iterations for r in h),
        "seconds": sum(r.seconds for r in h),
        "torch_threads": torch.get_num_threads(),  # the count the seconds (and the bits) came from
        "cpu_dispatch": cpu_dispatch.in_effect(),  # and the CPU code paths
        "events_processed": sum(r.events for r in h),
        "stopped_early_stages": sum(r.stopped_early for r in h),
        "pruned_blockers": sum(r.pruned_blockers for r in h),
        "added_gaussians": sum(r.added for r in h),
        "undistort_dropped_events": state.data.dropped,
        "range_meter_jumps": range_meter_jumps(state),
        "final_loss": h[-1].loss if h else float("nan"),
        "stages": [asdict(r) for r in h],
    } | state.metric


def _finite(v: object) -> object:
    """JSON without NaN/inf (null instead)."""
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_finite(x) for x in v]
    if isinstance(v, float | np.floating) and not math.isfinite(v):
        return None
    return float(v) if isinstance(v, np.floating) else v

"""Evaluate one SLAM run directory (``config.toml`` with ``seq``, ``traj_est.txt``, ``gaussians.ply``)
against its sequence's ground truth: trajectory metrics, image metrics, the map's depth (simulated
sequences) and the ELOPE score."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import tomllib

from evgs.data.sequence import Sequence
from evgs.data.tum import read_tum
from evgs.eval.associate import Association, associate
from evgs.eval.elope import elope_score, velocities
from evgs.eval.images import ImageMetrics, evaluate_images
from evgs.eval.trajectory import TrajectoryMetrics, evaluate_trajectory
from evgs.io_util import atomic_path

if TYPE_CHECKING:
    from evgs.eval.depth import DepthMetrics  # torch and the renderer load only when depth is evaluated

# Where the map is rendered from for the image metrics (see evgs.eval.render_gt).
ImagePoses = Literal["estimate", "gt"]


@dataclass
class RunEvaluation:
    run_dir: Path
    sequence: Sequence
    config: dict
    assoc: Association
    traj: TrajectoryMetrics
    frames: np.ndarray  # (N,) sequence frame index of each associated pose, −1 when not a frame time
    images: ImageMetrics | None = None
    image_frames: np.ndarray | None = None  # frames the image metrics were computed on
    depth: DepthMetrics | None = None  # the map's depth against the simulated scene's
    elope_score: float | None = None
    notes: list[str] = field(default_factory=list)  # why something was skipped, what was dropped

    @property
    def label(self) -> str:
        """``<seq>/<timestamp>`` for ``runs/<seq>/<timestamp>/``."""
        return f"{self.run_dir.parent.name}/{self.run_dir.name}"

    @property
    def frame_range(self) -> str:
        f = self.frames[self.frames >= 0]
        return f"{f.min()}-{f.max()}" if f.size else "–"

    def velocities(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t_i, v_gt, v_est)`` of eq. 18 on the Sim(3)-aligned estimate."""
        t = self.assoc.t
        return t[:-1], velocities(t, self.traj.p_gt), velocities(t, self.traj.p_est)

    def summary(self) -> dict[str, object]:
        row: dict[str, object] = {
            "run": self.label,
            "sequence": self.sequence.name,
            "frames": self.frame_range,
            "poses": len(self.assoc.t),
            "dropped": self.assoc.dropped,
        }
        row.update(self.traj.summary())
        img = self.images.summary() if self.images is not None else {}
        for k in ("psnr_db", "ssim", "lpips"):
            row[k] = img.get(k, float("nan"))
        depth = self.depth.summary() if self.depth is not None else {}
        for k in ("depth_l1_m", "depth_err_pct", "depth_coverage", "depth_spill"):
            row[k] = depth.get(k, float("nan"))
        row["elope_score"] = self.elope_score if self.elope_score is not None else float("nan")
        return row


def read_run_config(run_dir: Path) -> dict:
    path = run_dir / "config.toml"
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir}: not a run directory (no config.toml)")
    with open(path, "rb") as f:
        try:
            return tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise ValueError(f"{path}: {e}") from None


def resolve_sequence(run_dir: Path, config: dict) -> Sequence:
    """The sequence named by ``seq`` in the run's config: absolute, relative to the working directory, or
    relative to the run directory."""
    seq = config.get("seq")
    if not isinstance(seq, str):
        raise ValueError(f"{run_dir / 'config.toml'}: missing string key 'seq' (the sequence folder)")
    for cand in (Path(seq), run_dir / seq):
        if (cand / "sequence.toml").is_file():
            return Sequence.load(cand)
    raise FileNotFoundError(f"{run_dir / 'config.toml'}: seq = {seq!r} is not a sequence folder")


def frame_indices(t_s: np.ndarray, frames_us: np.ndarray) -> np.ndarray:
    """Sequence frame of each timestamp (within 1 µs), −1 where none matches."""
    t_us = np.round(np.asarray(t_s) * 1e6).astype(np.int64)
    idx = np.clip(np.searchsorted(frames_us, t_us), 0, len(frames_us) - 1)
    prev = np.maximum(idx - 1, 0)
    best = np.where(np.abs(frames_us[prev] - t_us) < np.abs(frames_us[idx] - t_us), prev, idx)
    return np.where(np.abs(frames_us[best] - t_us) <= 1, best, -1)


def _check_increasing(t: np.ndarray, path: Path) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise ValueError(f"{path}: pose {bad[0] + 2}: timestamps must be strictly increasing")


def is_elope(seq: Sequence) -> bool:
    return "elope" in str(seq.meta.get("source", "")).lower()


def evaluate_run(
    run_dir: str | Path,
    *,
    images: bool = True,
    elope: bool | None = None,
    with_scale: bool = True,
    rpe_delta_m: float = 1.0,
    image_poses: ImagePoses = "estimate",
    depth: bool = True,
) -> RunEvaluation:
    """Evaluate a run. ``elope=None`` computes the ELOPE score only for ELOPE sequences (their ``z`` is
    the altitude); ``images`` renders ``gaussians.ply`` at the ground-truth frames when possible, from
    the estimated poses or the ground-truth viewpoints (``image_poses``, see ``evgs.eval.render_gt``);
    ``depth`` compares the map's depth with the scene's when the sequence was simulated
    (``evgs.eval.depth``)."""
    if image_poses not in ("estimate", "gt"):
        raise ValueError(f"image_poses must be 'estimate' or 'gt', got {image_poses!r}")
    run_dir = Path(run_dir)
    config = read_run_config(run_dir)
    seq = resolve_sequence(run_dir, config)
    gt = seq.poses_gt()
    if gt is None:
        raise ValueError(f"{seq.root}: sequence has no poses_gt.txt: nothing to evaluate against")
    traj_path = run_dir / "traj_est.txt"
    if not traj_path.is_file():
        raise FileNotFoundError(f"{run_dir}: no traj_est.txt")
    t_est, T_est = read_tum(traj_path)
    _check_increasing(t_est, traj_path)
    _check_increasing(gt[0], seq.root / "poses_gt.txt")
    assoc = associate(t_est, T_est, gt[0] / 1e6, gt[1])
    ev = RunEvaluation(
        run_dir=run_dir,
        sequence=seq,
        config=config,
        assoc=assoc,
        traj=evaluate_trajectory(assoc.T_gt, assoc.T_est, with_scale=with_scale, rpe_delta_m=rpe_delta_m),
        frames=frame_indices(assoc.t, seq.frames_us()),
    )
    if assoc.dropped:
        ev.notes.append(f"{assoc.dropped} estimated poses outside the ground-truth time span were dropped")
    if is_elope(seq) if elope is None else elope:
        ev.elope_score = elope_score(assoc.t, ev.traj.p_est, ev.traj.p_gt)
    if images:
        _evaluate_images(ev, image_poses)
    if depth:
        _evaluate_depth(ev)
    return ev


def _evaluate_images(ev: RunEvaluation, image_poses: ImagePoses) -> None:
    """Fill ``ev.images`` or explain in ``ev.notes`` why image metrics were not computed."""
    rows = np.flatnonzero(ev.frames >= 0)
    gts = [(r, ev.sequence.image(int(ev.frames[r]))) for r in rows]
    gts = [(r, img) for r, img in gts if img is not None]
    ply = ev.run_dir / "gaussians.ply"
    if not gts:
        ev.notes.append("image metrics skipped: the sequence has no ground-truth images at the run's frames")
        return
    if not ply.is_file():
        ev.notes.append("image metrics skipped: the run has no gaussians.ply")
        return
    try:
        from evgs.eval.render_gt import render_at_gt_frames, render_map
    except ImportError as e:
        ev.notes.append(f"image metrics skipped: renderer unavailable ({e})")
        return
    r_idx = np.array([r for r, _ in gts])
    f_idx = ev.frames[r_idx]
    gt_imgs = np.stack([img for _, img in gts])
    if image_poses == "estimate":
        renders = render_map(ply, ev.sequence, ev.assoc.T_est[r_idx])
    else:
        renders = render_at_gt_frames(ply, ev.sequence, ev.traj.sim3, f_idx)
    ev.images = evaluate_images(renders, gt_imgs)
    ev.image_frames = f_idx
    view = "estimated poses" if image_poses == "estimate" else "ground-truth viewpoints"
    ev.notes.append(f"image metrics rendered from the {view}")


def _evaluate_depth(ev: RunEvaluation) -> None:
    """Fill ``ev.depth`` for a simulated sequence, or say in ``ev.notes`` why not (silent for the others:
    no scene to compare with is the normal case for recorded data)."""
    if "simulator" not in ev.sequence.meta:
        return
    ply = ev.run_dir / "gaussians.ply"
    frames = ev.frames[ev.frames >= 0]
    if not len(frames):
        ev.notes.append("depth metrics skipped: no estimated pose at a frame time")
        return
    if not ply.is_file():
        ev.notes.append("depth metrics skipped: the run has no gaussians.ply")
        return
    from evgs.eval.depth import evaluate_depth, simulated_scene

    scene = simulated_scene(ev.sequence)
    if scene is None:
        target = ev.sequence.meta["simulator"].get("target")
        ev.notes.append(f"depth metrics skipped: the simulated target {target!r} cannot be rebuilt")
        return
    ev.depth = evaluate_depth(ply, ev.sequence, scene, ev.traj.sim3, frames)


def save_metrics(ev: RunEvaluation, path: Path) -> None:
    """The summary plus per-frame series as JSON (NaN → null)."""

    def clean(v: object) -> object:
        if isinstance(v, float) and not np.isfinite(v):
            return None
        return v

    doc = {k: clean(v) for k, v in ev.summary().items()}
    doc["sim3"] = {"scale": ev.traj.sim3.s, "R": ev.traj.sim3.R.tolist(), "t": ev.traj.sim3.t.tolist()}
    doc["per_frame"] = {
        "t": ev.assoc.t.tolist(),
        "frame": ev.frames.tolist(),
        "ate_error": ev.traj.ate_errors.tolist(),
        "orientation_error_deg": ev.traj.orientation_error_deg.tolist(),
    }
    if ev.images is not None and ev.image_frames is not None:
        doc["images"] = {
            "frame": ev.image_frames.tolist(),
            "psnr_db": [clean(float(v)) for v in ev.images.psnr],
            "ssim": ev.images.ssim.tolist(),
            "lpips": ev.images.lpips.tolist(),
        }
    if ev.depth is not None:
        doc["depth"] = {
            "frame": ev.depth.frames.tolist(),
            "l1_m": [clean(float(v)) for v in ev.depth.l1_m],
            "rel": [clean(float(v)) for v in ev.depth.rel],
            "coverage": ev.depth.coverage.tolist(),
            "spill": [clean(float(v)) for v in ev.depth.spill],
        }
    doc["notes"] = ev.notes
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1, allow_nan=False))

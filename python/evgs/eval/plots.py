"""Figures in the style of the paper's appendix, as PNG files (matplotlib ``Figure`` objects, no pyplot
state, so plotting works headless and from threads)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

from evgs.io_util import atomic_path

if TYPE_CHECKING:
    from collections.abc import Sequence

    from evgs.eval.depth import DepthView
    from evgs.eval.run import RunEvaluation

_AXES = ("x", "y", "z")
_EST = {"color": "tab:red", "label": "estimate"}
_GT = {"color": "black", "linestyle": "--", "label": "ground truth"}


def _save(fig: Figure, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    return path


def plot_trajectory_3d(p_gt: np.ndarray, p_est: np.ndarray, path: Path, title: str = "") -> Path:
    """3-D positions, ground truth vs Sim(3)-aligned estimate (start marked)."""
    fig = Figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    ax.plot(*p_gt.T, **_GT)
    ax.plot(*p_est.T, **_EST)
    ax.scatter(*p_gt[0], color="black", marker="o", label="start")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.set_title(title or "Trajectory")
    ax.legend(loc="upper left")
    return _save(fig, path)


def plot_translation(t: np.ndarray, p_gt: np.ndarray, p_est: np.ndarray, path: Path) -> Path:
    """Translation per axis vs time."""
    fig = Figure(figsize=(7, 6))
    axs = fig.subplots(3, 1, sharex=True)
    for a, ax in enumerate(axs):
        ax.plot(t, p_gt[:, a], **_GT)
        ax.plot(t, p_est[:, a], **_EST)
        ax.set_ylabel(_AXES[a])
        ax.grid(alpha=0.3)
    axs[0].legend(loc="best")
    axs[0].set_title("Translation evolution (Sim(3)-aligned)")
    axs[-1].set_xlabel("time [s]")
    return _save(fig, path)


def plot_ypr(t: np.ndarray, ypr_gt: np.ndarray, ypr_est: np.ndarray, path: Path) -> Path:
    """Yaw, pitch and roll (intrinsic Z-Y-X, degrees) vs time."""
    fig = Figure(figsize=(7, 6))
    axs = fig.subplots(3, 1, sharex=True)
    for a, (ax, name) in enumerate(zip(axs, ("yaw", "pitch", "roll"), strict=True)):
        ax.plot(t, ypr_gt[:, a], **_GT)
        ax.plot(t, ypr_est[:, a], **_EST)
        ax.set_ylabel(f"{name} [°]")
        ax.grid(alpha=0.3)
    axs[0].legend(loc="best")
    axs[0].set_title("Roll, pitch, yaw evolution (first-pose aligned)")
    axs[-1].set_xlabel("time [s]")
    return _save(fig, path)


def plot_orientation_error(t: np.ndarray, err_deg: np.ndarray, path: Path) -> Path:
    """Per-frame orientation error (eq. 16–17) with the drift at the last frame marked."""
    fig = Figure(figsize=(7, 3.5))
    ax = fig.add_subplot()
    ax.plot(t, err_deg, color="tab:blue")
    ax.scatter([t[-1]], [err_deg[-1]], color="tab:red", zorder=3)
    ax.annotate(f"drift {err_deg[-1]:.3f}°", (t[-1], err_deg[-1]), textcoords="offset points",
                xytext=(-10, 8), ha="right")  # fmt: skip
    ax.set_xlabel("time [s]")
    ax.set_ylabel("orientation error [°]")
    ax.set_title(f"Orientation error evolution — drift @ end frame: {err_deg[-1]:.3f}°")
    ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_velocity(
    t: np.ndarray, v_gt: np.ndarray, v_est: np.ndarray, path: Path, score: float | None
) -> Path:
    """Velocity per axis by first differences (eq. 18), with the ELOPE score in the title if known."""
    fig = Figure(figsize=(7, 6))
    axs = fig.subplots(3, 1, sharex=True)
    for a, ax in enumerate(axs):
        ax.plot(t, v_gt[:, a], **_GT)
        ax.plot(t, v_est[:, a], **_EST)
        ax.set_ylabel(f"v{_AXES[a]}")
        ax.grid(alpha=0.3)
    axs[0].legend(loc="best")
    axs[0].set_title("Velocity" + (f" — score: {score:.4f}" if score is not None else ""))
    axs[-1].set_xlabel("time [s]")
    return _save(fig, path)


def plot_range_agreement(
    t: np.ndarray, ranges: np.ndarray, depth: np.ndarray, unit: float, drift: float, path: Path
) -> Path:
    """The range meter against the map's first surface on the principal ray (``depth``, NaN where the map
    does not cover it) vs time, the map read at ``unit`` (the median ratio); below, their ratio over it."""
    fig = Figure(figsize=(7, 5))
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    top.plot(t, ranges, color="black", label="range meter")
    top.plot(t, depth * unit, color="tab:red", label=f"map's first surface × {unit:.4g} (median ratio)")
    top.set_ylabel("distance [m]")
    top.legend(loc="best")
    top.set_title(f"Range meter against the map — drift {drift:+.1%} from the first fifth to the last")
    bottom.plot(t, ranges / (depth * unit), color="tab:blue")
    bottom.axhline(1.0, color="gray", linewidth=0.8)
    bottom.set_ylabel("ratio / median")
    bottom.set_xlabel("time [s]")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_depth_error(frames: np.ndarray, rel: np.ndarray, coverage: np.ndarray, path: Path) -> Path:
    """The map's depth against the scene's per frame (median relative error, signed), with the share of
    the target the map covers below: a map that sits ever nearer the cameras shows as a falling line."""
    fig = Figure(figsize=(7, 4.5))
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    top.plot(frames, rel * 100.0, color="tab:red")
    top.axhline(0.0, color="gray", linewidth=0.8)
    top.set_ylabel("depth error [%]")
    top.set_title("Map depth against the scene (median of D_map / D_gt − 1; < 0: nearer the camera)")
    bottom.plot(frames, coverage * 100.0, color="tab:blue")
    bottom.set_ylabel("coverage [%]")
    bottom.set_ylim(0, 100)
    bottom.set_xlabel("frame")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    return _save(fig, path)


def plot_depth_views(views: Sequence[DepthView], path: Path) -> Path:
    """One row per frame: the scene's depth, the map's (same colour scale, metres; blank where the map's
    opacity is below 0.5) and their relative error where both see a surface (red: the map nearer the
    camera, blue: farther)."""
    fig = Figure(figsize=(11, 3.2 * len(views)))
    axs = fig.subplots(len(views), 3, squeeze=False)
    for row, v in zip(axs, views, strict=True):
        gt = np.where(np.isfinite(v.gt_m), v.gt_m, np.nan)
        lo, hi = np.nanpercentile(np.concatenate([gt.ravel(), v.map_m.ravel()]), [1, 99])
        err = 100.0 * (v.map_m / gt - 1.0)
        for ax, img, title, kw in (
            (row[0], gt, f"frame {v.frame}: scene depth [m]", {"cmap": "viridis", "vmin": lo, "vmax": hi}),
            (row[1], v.map_m, "map depth [m]", {"cmap": "viridis", "vmin": lo, "vmax": hi}),
            (row[2], err, "map / scene − 1 [%]", {"cmap": "RdBu", "vmin": -25.0, "vmax": 25.0}),
        ):
            fig.colorbar(ax.imshow(img, **kw), ax=ax, fraction=0.035)
            ax.set_title(title)
            ax.set_axis_off()
    return _save(fig, path)


def plot_run(ev: RunEvaluation, out_dir: Path) -> dict[str, Path]:
    """All figures of a :class:`evgs.eval.run.RunEvaluation` into ``out_dir``; returns name → path."""
    tr = ev.traj
    t = ev.assoc.t - ev.assoc.t[0]
    tv, v_gt, v_est = ev.velocities()
    figures = {
        "trajectory": plot_trajectory_3d(tr.p_gt, tr.p_est, out_dir / "trajectory_3d.png", ev.sequence.name),
        "translation": plot_translation(t, tr.p_gt, tr.p_est, out_dir / "translation.png"),
        "rpy": plot_ypr(t, tr.ypr_gt_deg, tr.ypr_est_deg, out_dir / "rpy.png"),
        "orientation_error": plot_orientation_error(
            t, tr.orientation_error_deg, out_dir / "orientation_error.png"
        ),
        "velocity": plot_velocity(tv - ev.assoc.t[0], v_gt, v_est, out_dir / "velocity.png", ev.elope_score),
    }
    if ev.depth is not None:
        d = ev.depth
        figures["depth_error"] = plot_depth_error(d.frames, d.rel, d.coverage, out_dir / "depth_error.png")
        if d.views:
            figures["depth_views"] = plot_depth_views(d.views, out_dir / "depth_views.png")
    return figures

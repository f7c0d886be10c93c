"""The suite's numbers: trajectory extent, per-preset aggregation over seeds, the issue's targets, and the
CSV / Markdown tables (pure functions of row dicts, so they are testable without running SLAM)."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evgs.io_util import atomic_path

Row = dict[str, object]

# Per-run columns of runs.csv, in order. ``status`` is "ok" or "failed" (``error`` says why).
RUN_COLUMNS = [
    "preset", "seed", "lighting", "status", "error", "run_dir", "frames", "ate_rmse", "extent", "ate_pct",
    "drift_deg", "gaze_err_rmse_deg", "ate_x", "ate_y", "ate_z", "rpe_trans_rmse", "rpe_rot_rmse_deg",
    "psnr_db", "ssim", "lpips", "s_per_frame", "wall_s", "peak_rss_gib", "metric_scale", "sim3_scale",
    "scale_err_pct", "range_map_drift_pct", "depth_err_pct",
]  # fmt: skip


@dataclass(frozen=True)
class Metric:
    key: str
    header: str
    fmt: str


# Aggregated metrics (mean and sample standard deviation over a preset's successful runs).
METRICS = [
    Metric("frames", "Frames", ".0f"),
    Metric("ate_rmse", "ATE RMSE", ".4g"),
    Metric("ate_pct", "ATE %", ".2f"),
    Metric("drift_deg", "Drift °", ".2f"),
    Metric("gaze_err_rmse_deg", "Gaze °", ".2f"),
    Metric("ate_x", "ATE x", ".4g"),
    Metric("ate_y", "ATE y", ".4g"),
    Metric("ate_z", "ATE z", ".4g"),
    Metric("psnr_db", "PSNR dB", ".2f"),
    Metric("ssim", "SSIM", ".3f"),
    Metric("lpips", "LPIPS", ".3f"),
    Metric("s_per_frame", "s/frame", ".2f"),
    Metric("peak_rss_gib", "Peak GiB", ".2f"),
    Metric("scale_err_pct", "Scale err %", ".1f"),
    Metric("range_map_drift_pct", "Map drift %", ".1f"),
    Metric("depth_err_pct", "Depth err %", ".1f"),
]


@dataclass(frozen=True)
class Target:
    """A goal of issue 8 on the mean of one metric; ``applies`` selects the presets it is meant for."""

    key: str
    header: str
    holds: Callable[[float], bool]
    applies: Callable[[Row], bool] = lambda preset: True


def _good_light(preset: Row) -> bool:
    return preset["lighting"] == "good"


TARGETS = [
    Target("ate_pct", "ATE ≤ 1 %", lambda v: v <= 1.0),
    Target("drift_deg", "Drift ≤ 5°", lambda v: v <= 5.0),
    Target("s_per_frame", "≤ 10 s/frame", lambda v: v <= 10.0),
    Target("peak_rss_gib", "≤ 4 GiB", lambda v: v <= 4.0),
    Target("psnr_db", "PSNR ≥ 20 dB", lambda v: v >= 20.0, _good_light),
]
TARGETS_LINE = (
    "Targets (issue 8): ATE ≤ 1 % of the trajectory extent and final drift ≤ 5° on every preset; ≤ 10 s "
    "per frame; peak memory ≤ 4 GiB; PSNR ≥ 20 dB on the good-light presets."
)
DEFINITIONS = (
    "ATE: RMSE of positions after Sim(3) alignment (per axis x, y, z too); extent: the largest distance "
    "between two ground-truth positions of the evaluated frames; drift: rotation error of the last frame "
    "after aligning the first poses; s/frame: the run's own stage time per frame; peak: the run process's "
    "maximum RSS; scale err: |Sim(3) scale − 1| of runs with metric outputs; depth err: the map's median "
    "depth over the simulated scene's from the ground-truth viewpoints, minus 1 (< 0: nearer the cameras). "
    "Values: mean ± sample standard "
    "deviation over the successful runs of each preset. A target passes (✓) when every run of the preset "
    "succeeded and the mean meets it; – = not applicable or not measured."
)


def trajectory_extent(positions: np.ndarray, chunk: int = 1024) -> float:
    """The largest distance between two of the (N, 3) positions: rotation-invariant, unlike a bounding
    box diagonal. Exact, in row blocks so long trajectories need O(chunk · N) memory."""
    p = np.asarray(positions, np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"positions must be (N, 3), got {p.shape}")
    best = 0.0
    for s in range(0, len(p), chunk):
        d2 = np.sum((p[s : s + chunk, None, :] - p[None, :, :]) ** 2, axis=-1)
        best = max(best, float(d2.max()))
    return math.sqrt(best)


def ate_percent(ate_rmse: float, extent: float) -> float:
    """ATE as a percentage of the trajectory extent (NaN for a trajectory that does not move)."""
    return 100.0 * ate_rmse / extent if extent > 0 else math.nan


def _values(rows: Sequence[Row], key: str) -> np.ndarray:
    return np.array([float(r.get(key, math.nan)) for r in rows], np.float64)  # type: ignore[arg-type]


def _mean_std(v: np.ndarray) -> tuple[float, float]:
    v = v[np.isfinite(v)]
    if not v.size:
        return math.nan, math.nan
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else math.nan


def summarize(rows: Sequence[Row]) -> list[Row]:
    """One row per preset (in first-appearance order): run counts, ``<metric>_mean`` / ``<metric>_std``
    over the successful runs, and ``target_<metric>`` = "pass", "fail" or "n/a"."""
    out = []
    for preset in dict.fromkeys(r["preset"] for r in rows):
        runs = [r for r in rows if r["preset"] == preset]
        ok = [r for r in runs if r["status"] == "ok"]
        row: Row = {"preset": preset, "lighting": runs[0]["lighting"], "runs": len(runs), "ok": len(ok)}
        for m in METRICS:
            row[f"{m.key}_mean"], row[f"{m.key}_std"] = _mean_std(_values(ok, m.key))
        for t in TARGETS:
            mean = float(row[f"{t.key}_mean"])  # type: ignore[arg-type]
            if not t.applies(row):
                verdict = "n/a"
            elif len(ok) < len(runs):
                verdict = "fail"
            elif math.isnan(mean):
                verdict = "n/a"
            else:
                verdict = "pass" if t.holds(mean) else "fail"
            row[f"target_{t.key}"] = verdict
        out.append(row)
    return out


def summary_columns() -> list[str]:
    stats = [f"{m.key}_{s}" for m in METRICS for s in ("mean", "std")]
    return ["preset", "lighting", "runs", "ok", *stats, *(f"target_{t.key}" for t in TARGETS)]


def _cell(mean: float, std: float, fmt: str) -> str:
    if math.isnan(mean):
        return "–"
    return f"{mean:{fmt}}" if math.isnan(std) else f"{mean:{fmt}} ± {std:{fmt}}"


_MARK = {"pass": "✓", "fail": "✗", "n/a": "–"}


def markdown(summary: Sequence[Row], runs: Sequence[Row], seeds: Sequence[int]) -> str:
    """``summary.md``: the targets, the definitions, the table, and every failed run with its reason."""
    header = ["Preset", "Runs ok", *(m.header for m in METRICS), *(t.header for t in TARGETS)]
    lines = [
        f"{TARGETS_LINE}",
        "",
        f"Seeds: {' '.join(map(str, seeds))}. {DEFINITIONS}",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]
    for s in summary:
        cells = [str(s["preset"]), f"{s['ok']}/{s['runs']}"]
        cells += [_cell(float(s[f"{m.key}_mean"]), float(s[f"{m.key}_std"]), m.fmt) for m in METRICS]  # type: ignore[arg-type]
        cells += [_MARK[str(s[f"target_{t.key}"])] for t in TARGETS]
        lines.append("| " + " | ".join(cells) + " |")
    failed = [r for r in runs if r["status"] != "ok"]
    if failed:
        lines += ["", "Failed runs:", ""]
        lines += [f"- {r['preset']} seed {r['seed']}: {r['error']}" for r in failed]
    return "\n".join(lines) + "\n"


def write_csv(path: Path, rows: Sequence[Row], columns: Sequence[str]) -> None:
    """Rows as CSV (atomically); NaN is written as an empty cell."""

    def cell(v: object) -> object:
        return "" if isinstance(v, float) and math.isnan(v) else v

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, columns, extrasaction="raise")
        w.writeheader()
        w.writerows({c: cell(r.get(c, math.nan)) for c in columns} for r in rows)

"""The SLAM benchmark suite: every (preset, seed) run of ``evgs run`` in its own process, evaluated, and
aggregated into one table (``runs.csv``, ``summary.csv``, ``summary.md`` in the suite directory).

Layout of a suite directory ``OUT``: ``OUT/<preset>/seed<N>/`` holds one run slot: the child's output
(``<sequence>/<timestamp>/``, the usual run directory), ``child.log`` (its stdout and stderr) and
``child.json`` (exit code, wall time, peak RSS). A separate process per run gives each run its own peak
memory and turns a crash into a failed row instead of the suite's end.

The peak: ``wait4``'s ``ru_maxrss`` is the larger of the child's own high-water mark and that of the
memory image its ``exec`` replaced, which was this process's (the kernel keeps both), and this process
grows as it evaluates runs. So where ``ru_maxrss`` does not exceed this process's high-water mark at the
spawn, the peak is the child's ``VmHWM`` (Linux ``/proc``), polled while it runs (:func:`wait_with_peak`).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import evgs
from evgs.bench.table import (
    RUN_COLUMNS,
    Row,
    ate_percent,
    markdown,
    summarize,
    summary_columns,
    trajectory_extent,
    write_csv,
)
from evgs.cli import UserError
from evgs.config import CONFIG_DIR, load_config
from evgs.io_util import atomic_path

DEFAULT_PRESETS = ("docking_good", "docking_low", "swirl_good", "swirl_low", "orbit", "descent")
# Keys the suite sets itself (from --seeds and --frames); a --set of them would be silently overridden.
SUITE_KEYS = {"seed": "--seeds", "data.num_frames": "--frames"}


@dataclass(frozen=True)
class RunSpec:
    preset: str
    seed: int
    lighting: str  # the simulator preset's lighting (the PSNR target is for good light)
    config: Path
    sequence: Path
    overrides: tuple[str, ...]  # --set items of the run, the suite's seed and frame cap included
    slot: Path

    @property
    def log_path(self) -> Path:
        return self.slot / "child.log"

    @property
    def child_json(self) -> Path:
        return self.slot / "child.json"


@dataclass(frozen=True)
class ChildResult:
    exit_code: int  # negative: killed by that signal
    wall_s: float
    peak_rss_gib: float


def preset_config(preset: str) -> Path:
    return CONFIG_DIR / "synthetic" / f"{preset}.toml"


def plan_runs(
    presets: Sequence[str],
    seeds: Sequence[int],
    frames: int | None,
    sets: Sequence[str],
    out: Path,
    data_root: Path,
) -> list[RunSpec]:
    """Every (preset, seed) run, checked before anything runs: each preset needs its config and its
    simulator preset, and the overrides must load (so a typo fails now, not after hours)."""
    from evgs.sim.presets import PRESETS

    for item in sets:
        key = item.partition("=")[0].strip()
        if key in SUITE_KEYS:
            raise UserError(f"--set {item!r}: the suite sets {key} itself; use {SUITE_KEYS[key]}")
    if frames is not None and frames < 1:
        raise UserError(f"--frames {frames}: must be ≥ 1")
    if not seeds:
        raise UserError("--seeds: need at least one seed")
    specs = []
    for preset in presets:
        config = preset_config(preset)
        if not config.is_file():
            known = sorted(p.stem for p in config.parent.glob("[!_]*.toml"))
            raise UserError(f"preset {preset!r}: no config {config} (configs: {', '.join(known)})")
        if preset not in PRESETS:
            known = ", ".join(PRESETS)
            raise UserError(f"preset {preset!r}: no simulator preset of that name (known: {known})")
        run_sets = list(sets)
        if frames is not None:
            configured = load_config(config, sets).data.num_frames
            run_sets.append(f"data.num_frames={frames if configured == 0 else min(frames, configured)}")
        else:
            load_config(config, sets)
        for seed in seeds:
            specs.append(
                RunSpec(
                    preset=preset,
                    seed=seed,
                    lighting=PRESETS[preset].lighting,
                    config=config,
                    sequence=data_root / "synthetic" / preset,
                    overrides=(*run_sets, f"seed={seed}"),
                    slot=out / preset / f"seed{seed}",
                )
            )
    return specs


def child_argv(spec: RunSpec, interrupted: Path | None = None) -> list[str]:
    """``evgs run`` of one spec in this interpreter, or ``evgs run --resume`` of its interrupted run."""
    argv = [sys.executable, "-m", "evgs", "run"]
    if interrupted is not None:
        return [*argv, "--resume", str(interrupted.absolute()), "--quiet"]
    argv += ["--seq", str(spec.sequence.absolute()), "--config", str(spec.config), "--out",
             str(spec.slot.absolute()), "--quiet"]  # fmt: skip
    for item in spec.overrides:
        argv += ["--set", item]
    return argv


class _Terminated(Exception):
    """SIGTERM reached the suite while a run was going."""


def _raise_terminated(signum: int, frame: object) -> None:
    raise _Terminated


POLL_S = 0.1
"""Seconds between two reads of the child's ``VmHWM``: where the peak is polled, growth in its last POLL_S
is not seen."""


def vm_hwm_kib(pid: int) -> int | None:
    """The peak resident set of ``pid``'s current memory image (``VmHWM``, KiB), or None where ``/proc``
    does not say (another OS, or the process has exited)."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def wait_with_peak(pid: int, spawner_hwm: int | None) -> tuple[int, int]:
    """Wait for ``pid``; its wait status and peak RSS in KiB. ``ru_maxrss`` when it exceeds the spawning
    process's high-water mark ``spawner_hwm`` (KiB; then it is the child's own); else the largest
    ``VmHWM`` read while the child ran, or ``ru_maxrss`` as an upper bound where none could be read."""
    polled = None
    while True:
        done, status, usage = os.wait4(pid, os.WNOHANG)
        if done:
            childs_own = usage.ru_maxrss > (spawner_hwm or 0)
            return status, usage.ru_maxrss if childs_own or polled is None else polled
        if (hwm := vm_hwm_kib(pid)) is not None:
            polled = max(polled or 0, hwm)
        time.sleep(POLL_S)


def run_child(argv: list[str], log_path: Path, append: bool = False) -> ChildResult:
    """Run ``argv`` with its output in (or, ``append``, added to) ``log_path``; its peak RSS
    (:func:`wait_with_peak`). A SIGTERM meanwhile stops the child first, then this process."""
    env = dict(os.environ)
    # The child imports the same evgs as this process, however this one found it.
    package_root = str(Path(evgs.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH")) if p)
    env["COLUMNS"] = "200"  # the log is a file: no wrapping of the run's messages at 80 columns
    log_path.parent.mkdir(parents=True, exist_ok=True)
    previous = signal.signal(signal.SIGTERM, _raise_terminated) or signal.SIG_DFL  # None: set outside Python
    try:
        with open(log_path, "ab" if append else "wb") as log:
            t0, spawner_hwm = time.perf_counter(), vm_hwm_kib(os.getpid())
            proc = subprocess.Popen(
                argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env
            )
            try:
                status, peak_kib = wait_with_peak(proc.pid, spawner_hwm)
            except KeyboardInterrupt:  # the child got the SIGINT too: let it write its checkpoint
                proc.wait()
                raise
            except _Terminated:
                # A SIGTERM reaches this process only: without this the run would go on, orphaned,
                # sharing the cores with whatever comes next. Its checkpoints are written atomically.
                proc.terminate()
                proc.wait()
                signal.signal(signal.SIGTERM, previous)
                signal.raise_signal(signal.SIGTERM)  # then as this process would have without the run
                raise
            proc.returncode = os.waitstatus_to_exitcode(status)
            wall = time.perf_counter() - t0
    finally:
        signal.signal(signal.SIGTERM, previous)
    return ChildResult(proc.returncode, wall, peak_kib * 1024 / 2**30)


def finished_run(slot: Path) -> Path | None:
    """The newest run directory in a slot that has ``metrics.json`` (written last by ``evgs run``)."""
    done = sorted(slot.glob("*/*/metrics.json"), key=lambda p: p.stat().st_mtime)
    return done[-1].parent if done else None


def interrupted_run(slot: Path) -> Path | None:
    """The newest run directory in a slot without ``metrics.json`` but with a checkpoint to go on from."""
    from evgs.slam.run_dir import RunDir

    runs = [p.parent for p in slot.glob("*/*/config.toml")]
    open_runs = [r for r in runs if not (r / "metrics.json").exists() and RunDir(r).checkpoint_path.is_file()]
    return max(open_runs, key=lambda r: r.stat().st_mtime) if open_runs else None


def _failure(exit_code: int, log_path: Path) -> str:
    if exit_code < 0:
        try:
            what = f"killed by {signal.Signals(-exit_code).name}"
        except ValueError:
            what = f"killed by signal {-exit_code}"
    else:
        what = f"exit code {exit_code}"
    lines = [s.strip() for s in log_path.read_text(errors="replace").splitlines() if s.strip()]
    return f"{what}: {lines[-1]}" if lines else what


def _empty_row(spec: RunSpec) -> Row:
    row: Row = dict.fromkeys(RUN_COLUMNS, math.nan)
    row.update(preset=spec.preset, seed=spec.seed, lighting=spec.lighting, status="failed", error="",
               run_dir="")  # fmt: skip
    return row


def evaluate(run_dir: Path, images: bool) -> Row:
    """The suite's metrics of one finished run (also saved as ``run_dir/eval/metrics.json``)."""
    from evgs.eval.run import evaluate_run, save_metrics

    ev = evaluate_run(run_dir, images=images, depth=images)
    save_metrics(ev, run_dir / "eval" / "metrics.json")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    s = ev.traj.summary()
    extent = trajectory_extent(ev.traj.p_gt)
    frames = int(metrics.get("frames", len(ev.assoc.t)))
    row: Row = {k: s[k] for k in ("ate_rmse", "drift_deg", "gaze_err_rmse_deg", "ate_x", "ate_y", "ate_z",
                                  "rpe_trans_rmse", "rpe_rot_rmse_deg")}  # fmt: skip
    row.update(frames=frames, extent=extent, ate_pct=ate_percent(s["ate_rmse"], extent))
    row["sim3_scale"] = s["scale"]
    img = ev.images.summary() if ev.images is not None else {}
    for k in ("psnr_db", "ssim", "lpips"):
        row[k] = float(img.get(k, math.nan))
    row["depth_err_pct"] = ev.depth.summary()["depth_err_pct"] if ev.depth is not None else math.nan
    seconds = metrics.get("seconds")
    row["s_per_frame"] = seconds / frames if seconds is not None and frames else math.nan
    scale = metrics.get("metric_scale")
    row["metric_scale"] = float(scale) if scale is not None else math.nan
    row["scale_err_pct"] = abs(s["scale"] - 1.0) * 100.0 if scale is not None else math.nan
    drift = metrics.get("range_map_drift")  # null in metrics.json when it could not be measured
    row["range_map_drift_pct"] = float(drift) * 100.0 if drift is not None else math.nan
    return row


def run_one(spec: RunSpec, resume: bool, images: bool) -> Row:
    """Run and evaluate one spec; any failure becomes the row's ``error``. With ``resume`` a finished
    run is only evaluated and an interrupted one continues from its checkpoint (when the first part's
    exit was recorded, the wall times add up and the peak memory is the larger)."""
    row = _empty_row(spec)
    run_dir = finished_run(spec.slot) if resume else None
    if run_dir is None:
        spec.slot.mkdir(parents=True, exist_ok=True)
        interrupted = interrupted_run(spec.slot) if resume else None
        child = run_child(child_argv(spec, interrupted), spec.log_path, append=interrupted is not None)
        if interrupted is not None and spec.child_json.is_file():
            before = ChildResult(**json.loads(spec.child_json.read_text()))
            child = ChildResult(child.exit_code, before.wall_s + child.wall_s,
                                max(before.peak_rss_gib, child.peak_rss_gib))  # fmt: skip
        with atomic_path(spec.child_json) as tmp:
            tmp.write_text(json.dumps(child.__dict__))
        row.update(wall_s=child.wall_s, peak_rss_gib=child.peak_rss_gib)
        if child.exit_code != 0:
            row["error"] = _failure(child.exit_code, spec.log_path)
            return row
        run_dir = finished_run(spec.slot)
        if run_dir is None:
            row["error"] = f"the run exited 0 but left no metrics.json under {spec.slot}"
            return row
    elif spec.child_json.is_file():
        child_doc = json.loads(spec.child_json.read_text())
        row.update(wall_s=child_doc["wall_s"], peak_rss_gib=child_doc["peak_rss_gib"])
    row["run_dir"] = str(run_dir)
    try:
        row.update(evaluate(run_dir, images))
    except Exception as e:  # recorded in the row: one bad run must not end the suite
        row["error"] = f"evaluation: {type(e).__name__}: {e}"
        return row
    if math.isnan(float(row["s_per_frame"])) and row["frames"]:  # type: ignore[arg-type]
        row["s_per_frame"] = float(row["wall_s"]) / float(row["frames"])  # type: ignore[arg-type]
    row["status"] = "ok"
    return row


def _progress(i: int, n: int, row: Row) -> str:
    head = f"[{i}/{n}] {row['preset']} seed {row['seed']}"
    if row["status"] != "ok":
        return f"{head}: FAILED: {row['error']}"
    psnr = "" if math.isnan(float(row["psnr_db"])) else f"PSNR {row['psnr_db']:.2f} dB, "  # type: ignore[arg-type]
    return (
        f"{head}: {row['frames']} frames, ATE {row['ate_rmse']:.4g} ({row['ate_pct']:.2f} %), drift "
        f"{row['drift_deg']:.2f}°, {psnr}{row['s_per_frame']:.2f} s/frame, {row['peak_rss_gib']:.2f} GiB "
        f"({row['run_dir']})"
    )


def run_suite(
    specs: Sequence[RunSpec], out: Path, seeds: Sequence[int], *, resume: bool = False, images: bool = True
) -> tuple[list[Row], list[Row], str]:
    """Simulate missing sequences, run and evaluate every spec, write ``runs.csv`` after each run (a
    killed suite keeps what it finished) and the summaries at the end. Returns (runs, summary, markdown)."""
    from evgs.sim import ensure_sequence

    for spec in {s.sequence: s for s in specs}.values():
        if not (spec.sequence / "sequence.toml").is_file():
            print(f"simulating {spec.sequence} …", flush=True)
        ensure_sequence(f"synthetic/{spec.preset}", spec.sequence.parents[1])
    out.mkdir(parents=True, exist_ok=True)
    rows: list[Row] = []
    for i, spec in enumerate(specs, 1):
        if not resume or finished_run(spec.slot) is None:
            head = f"[{i}/{len(specs)}] {spec.preset} seed {spec.seed}"
            print(f"{head}: running (log: {spec.log_path})", flush=True)
        rows.append(run_one(spec, resume, images))
        write_csv(out / "runs.csv", rows, RUN_COLUMNS)
        print(_progress(i, len(specs), rows[-1]), flush=True)
    summary = summarize(rows)
    table = markdown(summary, rows, seeds)
    write_csv(out / "summary.csv", summary, summary_columns())
    with atomic_path(out / "summary.md") as tmp:
        tmp.write_text(table)
    return rows, summary, table

"""``evgs bench slam``: the extent and the aggregation on known inputs, the plan's checks, a crashed run as
a failed row (with its own peak memory), one real run of the ``tiny`` preset that ``--resume`` then
skips, and a SIGTERM that stops the running child before the suite."""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from evgs.bench import slam
from evgs.bench.table import (
    RUN_COLUMNS,
    ate_percent,
    markdown,
    summarize,
    summary_columns,
    trajectory_extent,
    write_csv,
)
from evgs.cli import UserError, main
from evgs.data.sequence import Sequence
from evgs.sim.presets import PRESETS

REPO_DATA = Path(__file__).resolve().parents[1] / "data"
# Few iterations: the test checks the plumbing, not the accuracy.
FAST = ["init.num_opti_steps_for_init=10", "tracking.num_opti_steps=2", "global_ba.num_opti_steps_final=5",
        "output.diagnostics_every=1000"]  # fmt: skip


@pytest.fixture(scope="module")
def data_root(tmp_path_factory) -> Path:
    """A data root with ``synthetic/tiny``: the repository's simulated copy when there is one, else the
    suite simulates it."""
    root = tmp_path_factory.mktemp("data")
    cached = REPO_DATA / "synthetic" / "tiny"
    if (cached / "sequence.toml").is_file():
        (root / "synthetic").mkdir()
        (root / "synthetic" / "tiny").symlink_to(cached.resolve())
    return root


def test_extent_is_the_largest_pairwise_distance():
    a = np.linspace(0, 2 * np.pi, 40, endpoint=False)  # 40 points: antipodal pairs exist
    circle = np.stack([3 * np.cos(a), 3 * np.sin(a), np.full_like(a, 7.0)], axis=1)
    assert trajectory_extent(circle) == pytest.approx(6.0, rel=1e-12)
    line = np.outer(np.linspace(0, 1, 11), [1.0, 2.0, 2.0])  # length 3
    assert trajectory_extent(line[::-1]) == pytest.approx(3.0, rel=1e-12)
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(50, 3))
    brute = max(np.linalg.norm(p - q) for p in cloud for q in cloud)
    assert trajectory_extent(cloud, chunk=7) == pytest.approx(brute, rel=1e-12)
    assert trajectory_extent(np.zeros((1, 3))) == 0.0
    assert ate_percent(0.03, 6.0) == pytest.approx(0.5)
    assert math.isnan(ate_percent(0.03, 0.0))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        trajectory_extent(np.zeros((4, 2)))


def _row(preset: str, seed: int, lighting: str = "good", status: str = "ok", **values: float) -> dict:
    row: dict = dict.fromkeys(RUN_COLUMNS, math.nan)
    row.update(preset=preset, seed=seed, lighting=lighting, status=status, error="", run_dir="")
    row.update(values)
    return row


def test_summary_means_spreads_and_targets(tmp_path: Path):
    good = dict(frames=20, drift_deg=2.0, s_per_frame=5.0, peak_rss_gib=1.5, ssim=0.8, lpips=0.2)
    rows = [
        _row("a_good", 0, ate_pct=0.5, psnr_db=21.0, **good),
        _row("a_good", 1, ate_pct=0.7, psnr_db=23.0, **good),
        _row("a_good", 2, ate_pct=0.9, psnr_db=25.0, **good),
        _row("b_low", 0, "low", ate_pct=3.0, psnr_db=12.0, **good),
        _row("b_low", 1, "low", status="failed", error="killed by SIGKILL: out of memory"),
        _row("c_good", 0, ate_pct=0.2, psnr_db=math.nan, **good),  # --no-images
    ]
    a, b, c = summarize(rows)
    assert (a["preset"], a["runs"], a["ok"]) == ("a_good", 3, 3)
    assert a["ate_pct_mean"] == pytest.approx(0.7)
    assert a["ate_pct_std"] == pytest.approx(0.2)  # sample standard deviation
    assert a["psnr_db_mean"] == pytest.approx(23.0) and a["psnr_db_std"] == pytest.approx(2.0)
    assert all(a[f"target_{k}"] == "pass" for k in ("ate_pct", "drift_deg", "s_per_frame", "peak_rss_gib"))
    assert a["target_psnr_db"] == "pass"
    # A failed run: the statistics are over the successful one, and every applicable target fails.
    assert (b["runs"], b["ok"], b["ate_pct_mean"]) == (2, 1, 3.0)
    assert math.isnan(b["ate_pct_std"])
    assert b["target_drift_deg"] == "fail" and b["target_psnr_db"] == "n/a"  # low light: no PSNR target
    assert c["target_psnr_db"] == "n/a" and c["target_ate_pct"] == "pass"  # not measured
    assert math.isnan(a["scale_err_pct_mean"])

    md = markdown([a, b, c], rows, [0, 1, 2])
    lines = md.splitlines()
    assert lines[0].startswith("Targets (issue 8): ATE ≤ 1 %")
    (row_a,) = [line for line in lines if line.startswith("| a_good ")]
    cells = [s.strip() for s in row_a.strip("|").split("|")]
    assert cells[:5] == ["a_good", "3/3", "20 ± 0", "–", "0.70 ± 0.20"]
    assert cells[-5:] == ["✓"] * 5
    (row_b,) = [line for line in lines if line.startswith("| b_low ")]
    assert row_b.rstrip(" |").endswith("✗ | ✗ | ✗ | ✗ | –")
    assert "- b_low seed 1: killed by SIGKILL: out of memory" in lines

    write_csv(tmp_path / "summary.csv", [a, b, c], summary_columns())
    with open(tmp_path / "summary.csv", newline="") as f:
        back = list(csv.DictReader(f))
    assert [r["preset"] for r in back] == ["a_good", "b_low", "c_good"]
    assert back[1]["ate_pct_std"] == "" and float(back[0]["ate_pct_mean"]) == pytest.approx(0.7)


def test_plan_checks_presets_and_overrides(tmp_path: Path, monkeypatch):
    def plan(presets, frames=None, sets=()):
        return slam.plan_runs(presets, [0, 1], frames, list(sets), tmp_path / "out", tmp_path / "data")

    with pytest.raises(UserError, match=r"preset 'no_such': no config .*no_such\.toml"):
        plan(["tiny", "no_such"])
    with pytest.raises(UserError, match="the suite sets seed itself; use --seeds"):
        plan(["tiny"], sets=["seed=3"])
    with pytest.raises(UserError, match="use --frames"):
        plan(["tiny"], sets=["data.num_frames=3"])
    with pytest.raises(ValueError, match="did you mean 'tracking'"):
        plan(["tiny"], sets=["trackin.num_opti_steps=3"])
    # tiny runs to the end of its sequence (num_frames 0): the cap applies; docking_good stops at 75.
    specs = plan(["tiny", "docking_good"], frames=200, sets=["loss.lambda_ssim=0.1"])
    assert [(s.preset, s.seed) for s in specs] == [
        ("tiny", 0),
        ("tiny", 1),
        ("docking_good", 0),
        ("docking_good", 1),
    ]
    assert specs[1].overrides == ("loss.lambda_ssim=0.1", "data.num_frames=200", "seed=1")
    assert specs[2].overrides == ("loss.lambda_ssim=0.1", "data.num_frames=75", "seed=0")
    assert specs[3].slot == tmp_path / "out" / "docking_good" / "seed1"
    assert specs[0].sequence == tmp_path / "data" / "synthetic" / "tiny"
    monkeypatch.delitem(PRESETS, "tiny")
    with pytest.raises(UserError, match="preset 'tiny': no simulator preset of that name"):
        plan(["tiny"])


def test_crashed_runs_become_failed_rows(tmp_path: Path, data_root: Path, monkeypatch):
    """A child killed by a signal and one that exits with an error: both rows failed with the reason, the
    suite goes on, and the killed child's peak memory is its own (it touched 300 MiB)."""
    crash = {
        # It holds the 300 MiB for a moment: where the peak is polled, its last POLL_S is not seen.
        0: "import os, signal, time; b = b'x' * (300 << 20); time.sleep(0.5); os.kill(os.getpid(), 9)",
        1: "import sys; print('loading'); sys.exit('evgs: error: boom')",
    }
    monkeypatch.setattr(slam, "child_argv", lambda spec, _: [sys.executable, "-c", crash[spec.seed]])
    out = tmp_path / "suite"
    specs = slam.plan_runs(["tiny"], [0, 1], None, [], out, data_root)
    rows, (summary,), md = slam.run_suite(specs, out, [0, 1])
    assert [r["status"] for r in rows] == ["failed", "failed"]
    assert rows[0]["error"] == "killed by SIGKILL"
    assert rows[0]["peak_rss_gib"] >= 0.29
    assert rows[1]["error"] == "exit code 1: evgs: error: boom"
    assert (summary["runs"], summary["ok"], summary["target_ate_pct"]) == (2, 0, "fail")
    assert "- tiny seed 1: exit code 1: evgs: error: boom" in md
    with open(out / "runs.csv", newline="") as f:
        assert [r["status"] for r in csv.DictReader(f)] == ["failed", "failed"]
    assert (out / "summary.md").read_text() == md


def test_tiny_suite_end_to_end_and_resume(tmp_path: Path, data_root: Path, monkeypatch, capsys):
    out = tmp_path / "suite"
    args = ["bench", "slam", "--presets", "tiny", "--seeds", "0", "--frames", "4", "--out", str(out),
            "--data-root", str(data_root)]  # fmt: skip
    for s in FAST:
        args += ["--set", s]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "| tiny | 1/1 | 5 |" in printed
    with open(out / "runs.csv", newline="") as f:
        (row,) = csv.DictReader(f)
    assert row["status"] == "ok" and row["frames"] == "5"
    run_dir = Path(row["run_dir"])
    assert (run_dir / "metrics.json").is_file() and (run_dir / "eval" / "metrics.json").is_file()
    t_gt, T_gt = Sequence.load(data_root / "synthetic" / "tiny").poses_gt()
    extent = trajectory_extent(T_gt[:5, :3, 3])
    assert float(row["extent"]) == pytest.approx(extent, rel=1e-9)
    assert float(row["ate_pct"]) == pytest.approx(100 * float(row["ate_rmse"]) / extent, rel=1e-9)
    ate_axes = np.array([float(row[k]) for k in ("ate_x", "ate_y", "ate_z")])
    assert float(row["ate_rmse"]) == pytest.approx(float(np.sqrt(np.sum(ate_axes**2))), rel=1e-9)
    for k in ("psnr_db", "ssim", "lpips", "s_per_frame", "drift_deg"):
        assert math.isfinite(float(row[k])), k
    # Four frames: the map does not cover the meter's ray yet, which the log says (the column stays empty).
    assert row["range_map_drift_pct"] == ""
    assert "too few to compare" in (run_dir / "log.txt").read_text()
    assert 0.1 < float(row["peak_rss_gib"]) < 8
    assert (out / "summary.csv").is_file() and (out / "summary.md").is_file()

    # A second invocation without --resume refuses the used directory; with it, nothing is rerun.
    assert main(args) == 2

    def no_child(*_):
        raise AssertionError("a finished run was started again")

    real_run_child = slam.run_child
    monkeypatch.setattr(slam, "run_child", no_child)
    assert main([*args, "--resume"]) == 0
    with open(out / "runs.csv", newline="") as f:
        (again,) = csv.DictReader(f)
    assert again == row

    # A run interrupted after its last checkpoint (no metrics.json yet) continues with `evgs run --resume`
    # in the same run directory, its log and wall time added to the first part's.
    (run_dir / "metrics.json").unlink()
    first_wall = float(json.loads((out / "tiny" / "seed0" / "child.json").read_text())["wall_s"])
    calls = []

    def resumed_child(argv, log_path, append=False):
        calls.append((argv, append))
        return real_run_child(argv, log_path, append)

    monkeypatch.setattr(slam, "run_child", resumed_child)
    assert main([*args, "--resume"]) == 0
    ((argv, append),) = calls
    assert argv[-3:] == ["--resume", str(run_dir), "--quiet"] and append
    with open(out / "runs.csv", newline="") as f:
        (resumed,) = csv.DictReader(f)
    assert resumed["status"] == "ok" and resumed["run_dir"] == str(run_dir)
    assert float(resumed["wall_s"]) > first_wall
    assert resumed["ate_rmse"] == row["ate_rmse"]
    assert "resumed at chunk" in (run_dir / "log.txt").read_text()


def test_sigterm_stops_the_running_child_before_the_suite(tmp_path: Path):
    """A suite killed with SIGTERM must not leave its run going on the cores, orphaned."""
    log = tmp_path / "child.log"
    run = "import os, time; print(os.getpid(), flush=True); time.sleep(120)"
    suite = (
        "import sys\nfrom pathlib import Path\nfrom evgs.bench.slam import run_child\n"
        f"run_child([sys.executable, '-c', {run!r}], Path(sys.argv[1]))\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", suite, str(log)], env=dict(os.environ))
    deadline = time.monotonic() + 60
    while not (log.exists() and log.read_text().strip()):
        assert time.monotonic() < deadline and proc.poll() is None, "the child never started"
        time.sleep(0.05)
    child = int(log.read_text().split()[0])
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == -signal.SIGTERM  # the suite still ends as SIGTERM ends it
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)  # stopped and reaped


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="VmHWM is Linux's")
def test_peak_memory_is_the_childs_own_not_the_suites(tmp_path: Path):
    """A suite that holds 400 MiB spawns a run that touches 100 MiB: the run's peak is about 100 MiB (Linux
    keeps the high-water mark of the image ``exec`` replaced, so ``wait4``'s ``ru_maxrss`` says 400)."""
    held = np.ones(400 * 2**20 // 8)  # touched, so resident
    run = "import time, numpy as np; a = np.ones(100 * 2**20 // 8); time.sleep(1.0)"
    result = slam.run_child([sys.executable, "-c", run], tmp_path / "child.log")
    assert result.exit_code == 0
    assert 100 < result.peak_rss_gib * 1024 < 300, result.peak_rss_gib * 1024  # MiB: numpy's import + 100
    assert held.sum() > 0

"""``evgs run`` end to end on a tiny synthetic sequence: the estimate beats a constant-pose baseline,
the map renders, the run directory is complete, and an interrupted run resumed with ``--resume`` ends
bitwise where an uninterrupted one does."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.cli import main  # noqa: E402
from evgs.config import load_config  # noqa: E402
from evgs.data.sequence import Sequence  # noqa: E402
from evgs.data.tum import read_tum  # noqa: E402
from evgs.render import render  # noqa: E402
from evgs.slam.gaussians import load_ply  # noqa: E402
from evgs.slam.pipeline import new_state, run_slam  # noqa: E402
from evgs.slam.run_dir import RunDir  # noqa: E402
from evgs.slam.windows import EventData  # noqa: E402
from slam_synth import make_sequence  # noqa: E402

# The test sequence has no range meter: scale.source=none.
SETS = ["data.event_contrast=0.2", "gaussians.bounding_size=1.5", "gaussians.init_depth=2.0",
        "output.diagnostics_every=100", "scale.source=none"]  # fmt: skip


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("seq") / "synth"
    make_sequence(root)
    return root


def run_cli(seq_dir: Path, out: Path, *sets: str) -> Path:
    args = ["run", "--seq", str(seq_dir), "--config", "synthetic/tiny", "--out", str(out), "--quiet"]
    for s in (*SETS, *sets):
        args += ["--set", s]
    assert main(args) == 0
    (run,) = (out / "synth").iterdir()
    return run


@pytest.fixture(scope="module")
def full_run(seq_dir, tmp_path_factory) -> Path:
    return run_cli(seq_dir, tmp_path_factory.mktemp("runs"))


def test_run_directory_is_complete(full_run: Path, seq_dir: Path):
    for name in ("config.toml", "traj_est.txt", "gaussians.ply", "metrics.json", "log.txt"):
        assert (full_run / name).is_file(), name
    assert (full_run / "checkpoints" / "latest.pt").is_file()
    assert list((full_run / "diagnostics").glob("*.png"))
    t, T = read_tum(full_run / "traj_est.txt")
    frames = Sequence.load(seq_dir).frames_us()
    assert np.array_equal(np.round(t * 1e6).astype(np.int64), frames)
    assert np.allclose(T[:, 3], [0, 0, 0, 1])
    cfg = load_config(full_run / "config.toml")
    assert Path(cfg.seq) == seq_dir.resolve()
    # the synthetic presets smooth the tracked positions before the final global BA
    assert cfg.trajectory.smoothing_time > 0
    assert "smoothed the tracked positions" in (full_run / "log.txt").read_text()


def test_estimate_beats_constant_pose_and_map_renders(full_run: Path, seq_dir: Path):
    metrics = json.loads((full_run / "metrics.json").read_text())
    seq = Sequence.load(seq_dir)
    t_gt, T_gt = seq.poses_gt()
    _, T_est = read_tum(full_run / "traj_est.txt")
    # A constant pose, best aligned, sits at the centroid of the GT positions at the frames.
    p = T_gt[np.isin(t_gt, seq.frames_us()), :3, 3]
    assert len(p) == len(T_est)
    baseline = float(np.sqrt(np.mean(np.sum((p - p.mean(0)) ** 2, axis=1))))
    assert metrics["ate_rmse"] < 0.5 * baseline, (metrics["ate_rmse"], baseline)
    assert metrics["frames"] == len(T_est) and metrics["iterations"] > 0
    g = load_ply(full_run / "gaussians.ply")
    viewmats = torch.linalg.inv(torch.from_numpy(T_est[-1:])).float()
    with torch.no_grad():
        out = render(**g.render_inputs(), viewmats=viewmats, camera=seq.camera)
    assert float(out.alpha.max()) > 0.5 and float(out.color.max()) > 0.05


class InterruptAt:
    """A reporter that raises KeyboardInterrupt (as Ctrl-C would) at one iteration of one stage, the
    ``occurrence``-th time the run gets there (a branched start runs the same stage once per branch)."""

    def __init__(self, stage: str, frame: int, it: int, occurrence: int = 1):
        self.where, self.left = (stage, frame, it), occurrence

    def advance(self, state, spec, it, loss, events, seconds) -> None:
        if (spec.stage, spec.frame, it) == self.where:
            self.left -= 1
            if self.left == 0:
                raise KeyboardInterrupt

    def stage_end(self, state, spec, record) -> None:
        pass


CHEAP = ["init.num_opti_steps_for_init=20", "tracking.num_opti_steps=6", "mapping.num_opti_steps_for_BA=8",
         "global_ba.every=4", "global_ba.num_opti_steps=6", "global_ba.num_opti_steps_final=10",
         "strategy.refine_every=3", "economy.patience=2", "economy.min_fraction=0"]  # fmt: skip


@pytest.fixture(scope="module")
def cheap_run(seq_dir, tmp_path_factory) -> Path:
    """Few iterations, but every stage, refinement, early stopping and the coarse level take part."""
    return run_cli(seq_dir, tmp_path_factory.mktemp("cheap"), *CHEAP)


def test_resume_after_interrupt_matches_uninterrupted(cheap_run: Path, seq_dir: Path, tmp_path: Path):
    cfg = load_config(cheap_run / "config.toml")
    run = RunDir.create(tmp_path / "runs", "synth", cfg)
    state = new_state(cfg, EventData.from_sequence(Sequence.load(seq_dir), cfg.data))
    with pytest.raises(KeyboardInterrupt):
        run_slam(state, run, InterruptAt("map", 7, 3))
    assert not (run.root / "gaussians.ply").exists()
    assert main(["run", "--resume", str(run.root), "--quiet"]) == 0
    assert (run.root / "traj_est.txt").read_bytes() == (cheap_run / "traj_est.txt").read_bytes()
    assert (run.root / "gaussians.ply").read_bytes() == (cheap_run / "gaussians.ply").read_bytes()


def run_in_subprocess(seq_dir: Path, out: Path, **env: str) -> Path:
    """The cheap run in a fresh ``python -m evgs`` with ``env`` added to this process's environment."""
    args = [sys.executable, "-m", "evgs", "run", "--seq", str(seq_dir), "--config", "synthetic/tiny",
            "--out", str(out), "--quiet"]  # fmt: skip
    for s in (*SETS, *CHEAP):
        args += ["--set", s]
    subprocess.run(args, env=os.environ | env, check=True, cwd=Path(__file__).parents[1])
    (run,) = (out / "synth").iterdir()
    return run


def assert_same_run(run: Path, reference: Path) -> None:
    assert (run / "traj_est.txt").read_bytes() == (reference / "traj_est.txt").read_bytes()
    assert (run / "gaussians.ply").read_bytes() == (reference / "gaussians.ply").read_bytes()


def test_a_run_repeats_bitwise_on_one_thread(cheap_run: Path, seq_dir: Path, tmp_path: Path):
    """One Rust and one torch thread in a fresh process against this process's defaults: the run pins
    torch's thread count (``torch_threads``) and the Rust core is invariant to its own."""
    run = run_in_subprocess(
        seq_dir, tmp_path, RAYON_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1"
    )
    assert_same_run(run, cheap_run)
    assert json.loads((run / "metrics.json").read_text())["torch_threads"] == 2  # the config's, not the env's


def test_a_run_repeats_bitwise_with_another_cpus_mkl(cheap_run: Path, seq_dir: Path, tmp_path: Path):
    """MKL held to the AVX2 instructions, as a CPU without AVX-512 would run it: the pinned code paths
    (evgs/cpu_dispatch.py) give the same bits. Unpinned, MKL's choice alone moves this run on an AVX-512
    CPU (docs/ablations.md §92)."""
    run = run_in_subprocess(seq_dir, tmp_path, MKL_ENABLE_INSTRUCTIONS="AVX2")
    assert_same_run(run, cheap_run)
    assert json.loads((run / "metrics.json").read_text())["cpu_dispatch"]["torch_cpu_capability"] == "AVX2"


def test_missing_seenic_sequence_says_what_to_download(tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--seq", "seenic/orbit_ambient", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "7370076" in err and "hubble-orbit-slow-ambient" in err
    assert "evgs import seenic" in err and "data/seenic/orbit_ambient" in err
    assert not (tmp_path / "runs").exists()


def test_config_follows_the_sequence_name():
    from evgs.config import CONFIG_DIR, DEFAULT_CONFIG
    from evgs.slam.cli import config_for

    assert config_for("seenic/orbit_ambient", None) == CONFIG_DIR / "seenic" / "orbit_ambient.toml"
    assert config_for("seenic/orbit_slow", None) == CONFIG_DIR / "seenic" / "_dataset.toml"
    assert config_for("nowhere/x", None) == DEFAULT_CONFIG
    assert config_for("seenic/orbit_ambient", "my.toml") == Path("my.toml")


def test_range_scale_without_a_range_meter_is_refused_before_the_run(seq_dir, tmp_path, capsys):
    args = ["run", "--seq", str(seq_dir), "--config", "synthetic/tiny", "--out", str(tmp_path), "--quiet"]
    assert main([*args, "--set", "scale.source=range"]) == 2
    assert "scale.source = 'range' needs range.csv" in capsys.readouterr().err
    assert main([*args, "--set", "scale.source=none", "--set", "scale.range_weight=1"]) == 2
    assert "scale.range_weight > 0 needs range.csv" in capsys.readouterr().err
    meter = [
        "--set",
        "scale.source=none",
        "--set",
        "init.motion_search=true",
        "--set",
        "init.search_meter_advance=true",
    ]
    assert main([*args, *meter]) == 2
    assert "init.search_meter_advance = true needs range.csv" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # no run directory was started


def test_branched_start_names_its_branches_and_resumes_from_before_them(seq_dir: Path, tmp_path: Path):
    """``init.branches``: every branch's stages are in the log and its diagnostics carry its name; Ctrl-C
    inside a branch resumes from before the search and ends bitwise where an uninterrupted run does."""
    sets = (*CHEAP, "init.branches=2", "init.branch_frames=2", "output.diagnostics_every=10")
    full = run_cli(seq_dir, tmp_path / "full", *sets)
    log = (full / "log.txt").read_text()
    assert "branch0/init" in log and "branch1/track" in log and "branch frame" in log
    assert list((full / "diagnostics").glob("branch1_init_*.png"))
    metrics = json.loads((full / "metrics.json").read_text())
    assert metrics["frames"] == len(read_tum(full / "traj_est.txt")[0])
    cfg = load_config(full / "config.toml")
    run = RunDir.create(tmp_path / "runs", "synth", cfg)
    state = new_state(cfg, EventData.from_sequence(Sequence.load(seq_dir), cfg.data))
    m = cfg.init.num_frames
    with pytest.raises(KeyboardInterrupt):  # the second branch's first tracked frame
        run_slam(state, run, InterruptAt("track", m + 1, 2, occurrence=2))
    assert main(["run", "--resume", str(run.root), "--quiet"]) == 0
    assert (run.root / "traj_est.txt").read_bytes() == (full / "traj_est.txt").read_bytes()
    assert (run.root / "gaussians.ply").read_bytes() == (full / "gaussians.ply").read_bytes()


def test_a_run_directory_from_an_older_evgs_reads_its_config(tmp_path: Path):
    """A snapshot that lacks keys a later version added (as every run written before them does) still
    loads for ``--resume``, the keys at their defaults and named in the run's log."""
    cfg = load_config("synthetic/tiny", SETS)
    run = RunDir.create(tmp_path, "synth", cfg)
    text = run.config_path.read_text()
    old = "\n".join(line for line in text.splitlines() if not line.startswith("branch_frames ="))
    run.config_path.write_text(old + "\n")
    assert run.config() == cfg
    log = (run.root / "log.txt").read_text()
    assert (
        "keys missing from config.toml (added after this run), at their defaults: init.branch_frames" in log
    )

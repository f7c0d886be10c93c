"""The ``tiny`` preset end to end: a valid canonical sequence with events, poses, images and range;
``ensure_sequence`` simulates once and then reuses; the CLI applies overrides and reports bad ones."""

import os
import subprocess
import sys

import numpy as np
import pytest
from evgs.cli import main
from evgs.data.sequence import Sequence
from evgs.data.tum import write_tum
from evgs.geometry import invert_pose
from evgs.sim import ensure_sequence, preset
from evgs.sim.trajectory import Trajectory


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    return root, ensure_sequence("synthetic/tiny", root=root)


def test_tiny_preset_writes_a_valid_sequence(tiny):
    root, folder = tiny
    assert folder == root / "synthetic" / "tiny"
    cfg = preset("tiny")
    seq = Sequence.load(folder)
    assert (seq.camera.width, seq.camera.height) == (160, 120) and seq.camera == cfg.camera
    ev = seq.events()
    ev.validate("tiny")
    assert len(ev) > 1000
    assert np.all(np.diff(ev.t) >= 0)
    key = ev.t * (160 * 120) + ev.y.astype(np.int64) * 160 + ev.x
    assert np.all(np.diff(key) >= 0), "ties are ordered by pixel index"
    frames = seq.frames_us()
    np.testing.assert_array_equal(frames, np.arange(0, 400_001, 40_000))
    assert ev.t[0] >= 0 and ev.t[-1] <= frames[-1]
    # Both polarities, and the target's pixels fire far more than the noise floor alone.
    assert 0.2 < np.mean(ev.p == 1) < 0.8
    stats = seq.meta["simulator"]["stats"]
    assert stats["events"] == len(ev) and stats["renders"] >= len(frames)
    assert seq.meta["simulator"]["c_on"] == cfg.c_on


def test_tiny_ground_truth(tiny):
    _, folder = tiny
    seq = Sequence.load(folder)
    cfg = preset("tiny")
    t_us, T_wc = seq.poses_gt()
    np.testing.assert_array_equal(t_us, seq.frames_us())
    np.testing.assert_allclose(T_wc, cfg.make_trajectory()(t_us * 1e-6), atol=1e-8)
    # Camera-to-world: the camera centre is on the orbit, and the target origin lies straight ahead
    # (to the 9 decimals of the TUM file).
    np.testing.assert_allclose(np.linalg.norm(T_wc[:, :3, 3], axis=1), cfg.distance, atol=1e-7)
    origin_in_cam = invert_pose(T_wc)[:, :3, 3]
    np.testing.assert_allclose(origin_in_cam[:, :2], 0.0, atol=1e-7)
    np.testing.assert_allclose(origin_in_cam[:, 2], cfg.distance, atol=1e-7)
    # GT images: the target in the middle, black space at the corners.
    for k in (0, len(t_us) - 1):
        img = seq.image(k)
        assert img.shape == (120, 160)
        assert img[50:70, 70:90].mean() > 0.02
        assert img[:5, :5].max() == 0.0
    # Range along the optical axis hits the target's body (nearer than its centre, at 10 Hz).
    rt, rd = seq.range_samples()
    np.testing.assert_array_equal(rt, np.arange(0, 400_001, 100_000))
    assert np.all((rd > cfg.distance - 2.0) & (rd < cfg.distance))


def test_package_exposes_the_functions():
    import evgs.sim
    import evgs.sim.driver  # noqa: F401  (a submodule must not shadow the function of the same name)

    assert callable(evgs.sim.simulate) and callable(evgs.sim.ensure_sequence)
    assert evgs.sim.preset("tiny") is evgs.sim.PRESETS["tiny"]


def test_ensure_sequence_reuses_the_folder(tiny):
    root, folder = tiny
    stamp = (folder / "events.parquet").stat().st_mtime_ns
    assert ensure_sequence("tiny", root=root) == folder
    assert (folder / "events.parquet").stat().st_mtime_ns == stamp


def test_cli_overrides_and_errors(tmp_path, capsys):
    out = tmp_path / "s"
    # 0.13 s: the last frame is at 0.12 s, the events run to the end.
    args = ["simulate", "--preset", "tiny", "--out", str(out), "--no-progress", "--duration", "0.13"]
    sets = ["--set", "seed=7", "--set", "c_on=0.3", "--set", "distortion=-0.1,0.01,0,0,0"]
    assert main([*args, "--trajectory", "approach", *sets]) == 0
    seq = Sequence.load(out)
    assert seq.camera.distortion == (-0.1, 0.01, 0.0, 0.0, 0.0)
    np.testing.assert_array_equal(seq.frames_us(), [0, 40_000, 80_000, 120_000])
    assert seq.events().t[-1] > 120_000
    assert seq.meta["simulator"]["trajectory"] == "approach" and seq.meta["simulator"]["seed"] == 7
    assert seq.meta["simulator"]["c_on"] == 0.3
    assert "events" in capsys.readouterr().out
    assert main([*args, "--set", "nonsense=1"]) == 2
    assert "unknown setting 'nonsense'" in capsys.readouterr().err
    assert main([*args, "--set", "c_on=abc"]) == 2
    assert "cannot read 'abc' as float" in capsys.readouterr().err
    assert main([*args, "--set", "frame_rate=0"]) == 2
    assert "setting frame_rate = 0.0: must be > 0" in capsys.readouterr().err
    assert main([*args, "--target", str(tmp_path / "missing.obj")]) == 2
    assert "neither a built-in" in capsys.readouterr().err


def test_cli_replays_a_tum_trajectory(tmp_path):
    t = np.linspace(0.0, 0.12, 13)
    poses = Trajectory("swirl", 7.0, 1.0, 0.12, 10.0, 40.0)(t)
    write_tum(tmp_path / "traj.txt", 50.0 + t, poses)
    out = tmp_path / "replay"
    assert main(["simulate", "--preset", "tiny", "--poses", str(tmp_path / "traj.txt"), "--out", str(out),
                 "--no-progress"]) == 0  # fmt: skip
    seq = Sequence.load(out)
    t_us, T = seq.poses_gt()
    np.testing.assert_array_equal(t_us, [0, 40_000, 80_000, 120_000])
    np.testing.assert_allclose(T, poses[::4], atol=1e-7)
    assert seq.meta["simulator"]["poses_t0_s"] == 50.0


def test_whole_simulation_is_independent_of_thread_count(tmp_path):
    digests = []
    for n in ("1", "2"):
        out = tmp_path / f"t{n}"
        env = {**os.environ, "RAYON_NUM_THREADS": n, "LP_NUM_THREADS": n}
        cmd = [sys.executable, "-m", "evgs.cli", "simulate", "--preset", "tiny", "--duration", "0.12"]
        subprocess.run([*cmd, "--out", str(out), "--no-progress"], env=env, check=True, capture_output=True)
        ev = Sequence.load(out).events()
        digests.append([getattr(ev, c).tobytes() for c in "txyp"])
    assert len(digests[0][0]) > 0 and digests[0] == digests[1]

"""IncEventGS/Replica-event and ESIM/RPG adapters on fixtures written in their own layouts."""

import cv2
import numpy as np
import pytest
from evgs.data.sequence import Sequence
from evgs.geometry import rotmat_to_quat
from import_helpers import assert_projects_as_truth, orbit_poses, random_events, run_import

W, H, N = 96, 64, 6


def write_images(folder, n, names):
    folder.mkdir(parents=True)
    for i, name in zip(range(n), names, strict=True):
        cv2.imwrite(str(folder / name), np.full((H, W), 30 * i, np.uint8))


def write_replica(root, rng, *, images=True, opengl=False):
    root.mkdir(parents=True)
    ts = 0.2 + 0.05 * np.arange(N)
    (root / "poses_ts.txt").write_text("".join(f"{t:.6f}\n" for t in ts))
    T_wc = orbit_poses(N)
    stored = T_wc @ np.diag([1.0, -1.0, -1.0, 1.0]) if opengl else T_wc
    (root / "traj.txt").write_text("".join(" ".join(f"{v:.12g}" for v in T.ravel()) + "\n" for T in stored))
    ev = random_events(rng, 3000, 200_000, 450_000, W, H)
    data = np.stack([ev["x"], ev["y"], ev["t"] / 1e6, ev["p"]], axis=1).astype(np.float32)
    (root / "event_threshold_0.1").mkdir()
    np.save(root / "event_threshold_0.1" / "gray_events_data.npy", data)
    if images:
        write_images(root / "images", N, [f"frame{i:06d}.png" for i in range(N)])
    t_expected = np.round(data[:, 2].astype(np.float64) * 1e6).astype(np.int64)
    return t_expected, ev, np.round(ts * 1e6).astype(np.int64), T_wc


@pytest.mark.parametrize("opengl", [False, True])
def test_replica_import(tmp_path, opengl):
    t_ev, ev, frames, T_wc = write_replica(tmp_path / "room0", np.random.default_rng(40), opengl=opengl)
    axes = ["--axes", "opengl"] if opengl else []
    assert (
        run_import(
            "replica", tmp_path / "room0", "--intrinsics", "80,80,48,32", "--out", tmp_path / "o", *axes
        )
        == 0
    )
    seq = Sequence.load(tmp_path / "o")
    assert (seq.camera.width, seq.camera.height, seq.camera.fx) == (W, H, 80.0)
    got = seq.events()
    assert len(got) == len(t_ev)
    np.testing.assert_array_equal(got.t, np.sort(t_ev))
    np.testing.assert_array_equal(np.sort(got.p), np.sort(ev["p"]))
    np.testing.assert_array_equal(seq.frames_us(), frames)
    assert_projects_as_truth(seq, T_wc, frames)
    np.testing.assert_allclose(seq.image(2), 60 / 255, atol=1e-4)


def test_replica_errors(tmp_path, capsys):
    write_replica(tmp_path / "r", np.random.default_rng(41), images=False)
    argv = ["replica", tmp_path / "r", "--intrinsics", "80,80,48,32", "--out", tmp_path / "o"]
    assert run_import(*argv) == 2
    assert "pass --size WxH" in capsys.readouterr().err
    (tmp_path / "r" / "event_threshold_0.2").mkdir()
    assert run_import(*argv, "--size", "96x64") == 2
    assert "found: event_threshold_0.1, event_threshold_0.2" in capsys.readouterr().err
    assert run_import(*argv, "--size", "96x64", "--threshold", "0.1") == 0
    with open(tmp_path / "r" / "traj.txt", "a") as f:
        f.write("1 2 3\n")
    assert run_import(*argv, "--size", "96x64", "--threshold", "0.1") == 2
    assert f"traj.txt: line {N + 1}: expected 16 values" in capsys.readouterr().err


def write_rpg(root, rng, *, images=True, distortion=(0.1, -0.05, 0.001, 0.002, 0.01)):
    root.mkdir(parents=True)
    ev = random_events(rng, 2000, 1_000_000, 1_500_000, W, H)
    p01 = (ev["p"] > 0).astype(int)
    lines = [f"{t / 1e6:.6f} {x} {y} {p}" for t, x, y, p in zip(ev["t"], ev["x"], ev["y"], p01, strict=True)]
    (root / "events.txt").write_text("\n".join(lines) + "\n")
    (root / "calib.txt").write_text(" ".join(str(v) for v in (70.0, 71.0, 47.5, 31.5, *distortion)) + "\n")
    t_gt = 1.0 + 0.025 * np.arange(2 * N)
    T_wc = orbit_poses(2 * N)
    q = rotmat_to_quat(T_wc[:, :3, :3])
    gt = ["# timestamp tx ty tz qx qy qz qw"]
    gt += [" ".join(f"{v:.9f}" for v in [t, *T[:3, 3], *qi]) for t, T, qi in zip(t_gt, T_wc, q, strict=True)]
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    t_img = 1.0 + 0.05 * np.arange(N)
    if images:
        write_images(root / "images", N, [f"frame_{i:08d}.png" for i in range(N)])
        (root / "images.txt").write_text(
            "".join(f"{t:.6f} images/frame_{i:08d}.png\n" for i, t in enumerate(t_img))
        )
    return ev, np.round(t_gt * 1e6).astype(np.int64), T_wc, np.round(t_img * 1e6).astype(np.int64)


def test_rpg_import(tmp_path):
    ev, t_gt, T_wc, t_img = write_rpg(tmp_path / "shapes", np.random.default_rng(50))
    assert run_import("rpg", tmp_path / "shapes", "--out", tmp_path / "o") == 0
    seq = Sequence.load(tmp_path / "o")
    assert (seq.camera.width, seq.camera.height, seq.camera.fy, seq.camera.cy) == (W, H, 71.0, 31.5)
    assert seq.camera.distortion == (0.1, -0.05, 0.001, 0.002, 0.01)
    got = seq.events()
    np.testing.assert_array_equal(got.t, ev["t"])
    np.testing.assert_array_equal(got.y, ev["y"])
    np.testing.assert_array_equal(got.p, ev["p"])
    np.testing.assert_array_equal(seq.frames_us(), t_img)
    assert_projects_as_truth(seq, T_wc, t_gt)
    np.testing.assert_allclose(seq.image(5), 150 / 255, atol=1e-4)


def test_rpg_without_images(tmp_path, capsys):
    ev, t_gt, T_wc, _ = write_rpg(tmp_path / "s", np.random.default_rng(51), images=False, distortion=())
    assert run_import("rpg", tmp_path / "s", "--out", tmp_path / "o") == 2
    assert "pass --size" in capsys.readouterr().err
    assert run_import("rpg", tmp_path / "s", "--out", tmp_path / "o", "--size", "96x64") == 0
    seq = Sequence.load(tmp_path / "o")
    np.testing.assert_array_equal(seq.frames_us(), t_gt)
    assert seq.camera.distortion == ()
    (tmp_path / "s" / "calib.txt").write_text("70 71 47.5\n")
    assert run_import("rpg", tmp_path / "s", "--out", tmp_path / "o2", "--size", "96x64") == 2
    assert "calib.txt: line 1: expected 4 or 8 or 9 values (fx fy cx cy [k1 k2 p1 p2 [k3]]), got 3" in (
        capsys.readouterr().err
    )

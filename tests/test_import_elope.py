"""ELOPE adapter on fixtures written as ELOPE's own ``.npz`` (structured events, Euler-angle trajectory)."""

import numpy as np
import polars as pl
from evgs.data.sequence import Sequence
from import_helpers import POINT, assert_projects_as_truth, look_at, project, run_import
from scipy.spatial.transform import Rotation

EVENT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "?"), ("t", "<i8")])


def descent_poses(n: int) -> np.ndarray:
    """Camera-to-world poses of a camera descending over the ground (z down), looking at ``POINT``."""
    s = np.linspace(0.0, 1.0, n)
    eyes = np.stack([2.0 - s, 1.0 + 0.5 * s, -(60.0 - 30.0 * s)], axis=1)  # z < 0: above the ground
    return np.stack([look_at(e, POINT, np.array([1.0, 0.0, 0.0])) for e in eyes])


def write_elope(path, rng, T_wc, *, with_gt=True):
    n = len(T_wc)
    ts = 0.5 + 0.1 * np.arange(n)
    ne = 4000
    events = np.zeros(ne, EVENT_DTYPE)
    events["t"] = np.sort(rng.integers(500_000, int(ts[-1] * 1e6), ne))
    events["x"] = rng.integers(0, 200, ne)
    events["y"] = rng.integers(0, 200, ne)
    events["p"] = rng.random(ne) < 0.5
    arrays = {"events": events, "timestamps": ts}
    if with_gt:
        # Body = camera (identity mount); attitude as roll, pitch, yaw of R_wb = Rz(ψ)·Ry(θ)·Rx(φ).
        euler = Rotation.from_matrix(T_wc[:, :3, :3]).as_euler("xyz")
        vel = rng.normal(size=(n, 3))
        rates = rng.normal(size=(n, 3))
        arrays["traj"] = np.concatenate([T_wc[:, :3, 3], vel, euler, rates], axis=1)
        arrays["range_meter"] = np.stack([ts, 50.0 + np.arange(n)], axis=1)
    np.savez(path, **arrays)
    return events, ts, arrays


def test_elope_import(tmp_path):
    T_wc = descent_poses(10)
    events, ts, arrays = write_elope(tmp_path / "0007.npz", np.random.default_rng(30), T_wc)
    assert run_import("elope", tmp_path / "0007.npz", "--out", tmp_path / "out") == 0
    seq = Sequence.load(tmp_path / "out")
    assert seq.name == "0007"
    assert (seq.camera.width, seq.camera.fx, seq.camera.cx, seq.camera.cy) == (200, 100.0, 100.0, 100.0)
    got = seq.events()
    np.testing.assert_array_equal(got.t, events["t"])
    np.testing.assert_array_equal(got.x, events["x"])
    np.testing.assert_array_equal(got.p, np.where(events["p"], 1, -1))
    t_us = np.round(ts * 1e6).astype(np.int64)
    np.testing.assert_array_equal(seq.frames_us(), t_us)
    assert_projects_as_truth(seq, T_wc, t_us)
    t_r, r = seq.range_samples()
    np.testing.assert_array_equal(t_r, t_us)
    np.testing.assert_allclose(r, arrays["range_meter"][:, 1])
    vel = pl.read_csv(tmp_path / "out" / "velocities_gt.csv")
    assert vel.columns == ["t_us", "vx", "vy", "vz", "p", "q", "r"]
    np.testing.assert_array_equal(vel["t_us"].to_numpy(), t_us)
    np.testing.assert_allclose(vel.select("vx", "vy", "vz").to_numpy(), arrays["traj"][:, 3:6])
    np.testing.assert_allclose(vel.select("p", "q", "r").to_numpy(), arrays["traj"][:, 9:12])


def test_elope_level_attitude_looks_straight_down(tmp_path):
    """Zero roll/pitch/yaw at altitude h: the ground point below is at the principal point, depth h."""
    rng = np.random.default_rng(31)
    n, h = 3, 40.0
    traj = np.zeros((n, 12))
    traj[:, 0:3] = [5.0, -3.0, -h]
    ts = np.array([0.0, 0.1, 0.2])
    events = np.zeros(10, EVENT_DTYPE)
    events["t"] = np.sort(rng.integers(0, 200_000, 10))
    np.savez(tmp_path / "s.npz", events=events, timestamps=ts, traj=traj)
    assert run_import("elope", tmp_path / "s.npz", "--out", tmp_path / "out") == 0
    seq = Sequence.load(tmp_path / "out")
    _, T = seq.poses_gt()
    below = np.array([5.0, -3.0, 0.0])
    np.testing.assert_allclose(project(T, seq.camera, below), [[100.0, 100.0]] * n, atol=1e-9)
    np.testing.assert_allclose((np.linalg.inv(T[0]) @ np.r_[below, 1])[2], h)
    assert seq.range_samples() is None


def test_elope_options_and_test_sequence(tmp_path, capsys):
    T_wc = descent_poses(6)
    write_elope(tmp_path / "a.npz", np.random.default_rng(32), T_wc)
    # The attitude stored as world-to-body: read back with --attitude-direction w2c it is the same pose.
    arrays = dict(np.load(tmp_path / "a.npz"))
    arrays["traj"][:, 6:9] = Rotation.from_matrix(np.swapaxes(T_wc[:, :3, :3], 1, 2)).as_euler("xyz")
    np.savez(tmp_path / "b.npz", **arrays)
    argv = ["--attitude-direction", "w2c", "--focal", "120", "--principal", "99.5,99.5"]
    assert run_import("elope", tmp_path / "b.npz", "--out", tmp_path / "b", *argv) == 0
    seq = Sequence.load(tmp_path / "b")
    assert (seq.camera.fx, seq.camera.cx) == (120.0, 99.5)
    assert_projects_as_truth(seq, T_wc, seq.frames_us())
    write_elope(tmp_path / "t.npz", np.random.default_rng(33), T_wc, with_gt=False)
    assert run_import("elope", tmp_path / "t.npz", "--out", tmp_path / "t") == 0
    assert "no 'traj'" in capsys.readouterr().err
    assert Sequence.load(tmp_path / "t").poses_gt() is None


def test_elope_malformed(tmp_path, capsys):
    write_elope(tmp_path / "a.npz", np.random.default_rng(34), descent_poses(5))
    arrays = dict(np.load(tmp_path / "a.npz"))
    arrays["traj"] = arrays["traj"][:, :9]
    np.savez(tmp_path / "bad.npz", **arrays)
    assert run_import("elope", tmp_path / "bad.npz", "--out", tmp_path / "o") == 2
    assert "'traj' has shape (5, 9); expected (5, 12)" in capsys.readouterr().err
    del arrays["timestamps"]
    np.savez(tmp_path / "bad2.npz", **arrays)
    assert run_import("elope", tmp_path / "bad2.npz", "--out", tmp_path / "o") == 2
    assert "no 'timestamps' array" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_elope_camera_rotation(tmp_path, capsys):
    """A camera mounted rotated in the body: the body attitude plus --camera-rotation give the camera pose."""
    T_wc = descent_poses(5)
    R_bc = Rotation.from_euler("z", 90, degrees=True).as_matrix()  # camera x = body y
    write_elope(tmp_path / "a.npz", np.random.default_rng(35), T_wc)
    arrays = dict(np.load(tmp_path / "a.npz"))
    R_wb = T_wc[:, :3, :3] @ R_bc.T
    arrays["traj"][:, 6:9] = Rotation.from_matrix(R_wb).as_euler("xyz")
    np.savez(tmp_path / "a.npz", **arrays)
    rot = ",".join(f"{v:.15g}" for v in R_bc.ravel())
    assert run_import("elope", tmp_path / "a.npz", "--out", tmp_path / "o", "--camera-rotation", rot) == 0
    seq = Sequence.load(tmp_path / "o")
    assert_projects_as_truth(seq, T_wc, seq.frames_us())
    assert (
        run_import(
            "elope", tmp_path / "a.npz", "--out", tmp_path / "p", "--camera-rotation", "1,0,0,0,1,0,0,0,2"
        )
        == 2
    )
    assert "--camera-rotation: not a rotation matrix" in capsys.readouterr().err

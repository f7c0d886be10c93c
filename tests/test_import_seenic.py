"""SEENIC adapter on fixtures written in SEENIC's own format."""

import cv2
import numpy as np
import pytest
from evgs.data.poses import to_c2w
from evgs.data.seenic import CAMERA
from evgs.data.sequence import Sequence
from evgs.geometry import invert_pose
from import_helpers import assert_projects_as_truth, orbit_poses, random_events, run_import

N_POSES = 12


def write_seenic(root, rng, *, header: bool, direction: str = "c2w", n_events: int = 5000):
    """A SEENIC sequence folder; returns (events with p ±1, pose t µs, true c2w)."""
    root.mkdir(parents=True)
    t_pose = 1_000_000 + np.arange(N_POSES) * 40_000
    ev = random_events(rng, n_events, int(t_pose[0]), int(t_pose[-1]), 640, 480)
    p01 = (ev["p"] > 0).astype(int)
    lines = ["t,x,y,p"] if header else []
    lines += [f"{t},{x},{y},{p}" for t, x, y, p in zip(ev["t"], ev["x"], ev["y"], p01, strict=True)]
    (root / "events.csv").write_text("\n".join(lines) + "\n")
    T_wc = orbit_poses(N_POSES)
    stored = T_wc if direction == "c2w" else invert_pose(T_wc)
    rows = ["t,rx,ry,rz,x,y,z"] if header else []
    for t, T in zip(t_pose, stored, strict=True):
        r = cv2.Rodrigues(T[:3, :3])[0].ravel()
        rows.append(",".join(f"{v:.12g}" for v in [t, *r, *T[:3, 3]]))
    (root / "cam-poses.csv").write_text("\n".join(rows) + "\n")
    return ev, t_pose, T_wc


@pytest.mark.parametrize("header", [True, False])
def test_seenic_import(tmp_path, header):
    rng = np.random.default_rng(10)
    raw = tmp_path / "hubble-orbit-slow-ambient"
    ev, t_pose, T_wc = write_seenic(raw, rng, header=header)
    assert run_import("seenic", raw, "--out", tmp_path / "out") == 0
    seq = Sequence.load(tmp_path / "out")
    assert seq.name == "hubble-orbit-slow-ambient"
    assert seq.camera == CAMERA and seq.meta["undistortion"] == "event-frames"
    got = seq.events()
    assert len(got) == len(ev["t"])
    np.testing.assert_array_equal(got.t, ev["t"])
    np.testing.assert_array_equal(got.x, ev["x"])
    np.testing.assert_array_equal(got.p, ev["p"])  # 0/1 → −1/+1
    np.testing.assert_array_equal(seq.frames_us(), t_pose)
    assert_projects_as_truth(seq, T_wc, t_pose)


def test_seenic_w2c_option(tmp_path):
    raw = tmp_path / "seq"
    _, t_pose, T_wc = write_seenic(raw, np.random.default_rng(11), header=True, direction="w2c", n_events=500)
    assert run_import("seenic", raw, "--out", tmp_path / "out", "--pose-direction", "w2c") == 0
    seq = Sequence.load(tmp_path / "out")
    assert seq.meta["pose_direction"] == "w2c"
    assert_projects_as_truth(seq, T_wc, t_pose)
    # Read with the wrong direction the poses are the inverses: the convention really is applied.
    assert run_import("seenic", raw, "--out", tmp_path / "wrong") == 0
    _, T_wrong = Sequence.load(tmp_path / "wrong").poses_gt()
    np.testing.assert_allclose(to_c2w(T_wrong, "w2c"), T_wc, atol=1e-6)


def test_seenic_frames_selection(tmp_path):
    raw = tmp_path / "seq"
    ev, t_pose, T_wc = write_seenic(raw, np.random.default_rng(12), header=False, n_events=3000)
    assert run_import("seenic", raw, "--out", tmp_path / "out", "--frames", "3:8") == 0
    seq = Sequence.load(tmp_path / "out")
    np.testing.assert_array_equal(seq.frames_us(), t_pose[3:8])
    keep = (ev["t"] >= t_pose[3]) & (ev["t"] <= t_pose[7])
    np.testing.assert_array_equal(seq.events().t, ev["t"][keep])
    assert seq.meta["frame_offset"] == 3
    assert_projects_as_truth(seq, T_wc[3:8], t_pose[3:8])


def test_seenic_missing_and_malformed(tmp_path, capsys):
    raw = tmp_path / "seq"
    write_seenic(raw, np.random.default_rng(13), header=True, n_events=100)
    (raw / "cam-poses.csv").unlink()
    assert run_import("seenic", raw, "--out", tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert "cam-poses.csv" in err and "rx, ry, rz" in err
    (raw / "cam-poses.csv").write_text("t,rx,ry,rz,x,y,z\n0,0,0,0,0,0,0\n1,0,0,0,0,0\n")
    assert run_import("seenic", raw, "--out", tmp_path / "out") == 2
    assert "cam-poses.csv: line 3: expected 7 values" in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))


def test_seenic_unsorted_and_outside_events(tmp_path, capsys):
    raw = tmp_path / "seq"
    ev, _, _ = write_seenic(raw, np.random.default_rng(14), header=False, n_events=200)
    lines = (raw / "events.csv").read_text().splitlines()
    lines[10], lines[11] = lines[11], lines[10]
    lines[50], lines[60] = lines[60], lines[50]
    (raw / "events.csv").write_text("\n".join(lines) + "\n")
    assert run_import("seenic", raw, "--out", tmp_path / "out") == 0
    assert "events sorted by time (none dropped)" in capsys.readouterr().err
    got = Sequence.load(tmp_path / "out").events()
    assert len(got) == 200
    np.testing.assert_array_equal(got.t, ev["t"])
    lines[20] = "1000100,640,5,1"
    (raw / "events.csv").write_text("\n".join(lines) + "\n")
    assert run_import("seenic", raw, "--out", tmp_path / "out2") == 2
    err = capsys.readouterr().err
    assert "events.csv" in err and "line 21" in err
    assert not (tmp_path / "out2").exists()

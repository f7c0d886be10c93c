"""The canonical sequence layout and TUM files round-trip exactly."""

import numpy as np
import pytest
from evgs.data.sequence import Camera, Sequence, write_sequence
from evgs.data.tum import read_tum, write_tum
from evgs.events.arrays import EventArray
from evgs.geometry import invert_pose, make_pose, quat_to_rotmat, rotmat_to_quat


def random_poses(rng, n):
    q = rng.normal(size=(n, 4))
    return make_pose(quat_to_rotmat(q), rng.normal(size=(n, 3)))


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    R = quat_to_rotmat(rng.normal(size=(50, 4)))
    np.testing.assert_allclose(quat_to_rotmat(rotmat_to_quat(R)), R, atol=1e-12)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    # 90° about z: (qx, qy, qz, qw) = (0, 0, sin45°, cos45°)
    np.testing.assert_allclose(
        quat_to_rotmat(np.array([0, 0, np.sqrt(0.5), np.sqrt(0.5)])),
        [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
        atol=1e-12,
    )


def test_invert_pose():
    T = random_poses(np.random.default_rng(1), 5)
    np.testing.assert_allclose(T @ invert_pose(T), np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    T = random_poses(rng, 10)
    t = np.linspace(0.0, 1.0, 10)
    write_tum(tmp_path / "traj.txt", t, T)
    t2, T2 = read_tum(tmp_path / "traj.txt")
    np.testing.assert_allclose(t2, t, atol=1e-9)
    np.testing.assert_allclose(T2, T, atol=1e-8)


def test_tum_bad_line_names_file_and_line(tmp_path):
    (tmp_path / "bad.txt").write_text("# header\n0 0 0 0 0 0 0 1\n1 2 3\n")
    with pytest.raises(ValueError, match=r"bad.txt: line 3: expected 8 values"):
        read_tum(tmp_path / "bad.txt")


def test_sequence_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    n = 1000
    ev = EventArray(
        t=np.sort(rng.integers(0, 10_000, n)).astype(np.int64),
        x=rng.integers(0, 64, n).astype(np.uint16),
        y=rng.integers(0, 48, n).astype(np.uint16),
        p=rng.choice(np.array([-1, 1], np.int8), n),
        width=64,
        height=48,
    )
    cam = Camera(64, 48, 50.0, 50.0, 32.0, 24.0, (0.1, 0.0, 0.0, 0.0, 0.0))
    frames = np.array([0, 5000, 10_000])
    T = random_poses(rng, 3)
    imgs = rng.random((3, 48, 64))
    seq = write_sequence(
        tmp_path / "s",
        "s",
        cam,
        ev,
        frames,
        poses_gt=(frames, T),
        images=imgs,
        meta={"source": "test"},
    )
    seq = Sequence.load(seq.root)
    assert seq.camera == cam and seq.meta["source"] == "test"
    ev2 = seq.events()
    for c in "txyp":
        np.testing.assert_array_equal(getattr(ev2, c), getattr(ev, c))
    np.testing.assert_array_equal(seq.frames_us(), frames)
    t_us, T2 = seq.poses_gt()
    np.testing.assert_array_equal(t_us, frames)
    np.testing.assert_allclose(T2, T, atol=1e-8)
    np.testing.assert_allclose(seq.image(1), imgs[1], atol=1 / 65535)
    assert seq.image(7) is None and seq.range_samples() is None
    assert not list(tmp_path.glob(".*partial"))


def test_sequence_missing_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="no sequence.toml"):
        Sequence.load(tmp_path)

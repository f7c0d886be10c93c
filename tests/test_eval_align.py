"""Umeyama Sim(3)/SE(3) alignment, first-pose rotation alignment and timestamp association."""

import numpy as np
import pytest
from eval_synth import orbit, random_sim3
from evgs.eval.align import Sim3, align_first_pose, first_pose_rotation, umeyama
from evgs.eval.associate import associate, interpolate_poses
from evgs.geometry import make_pose
from scipy.spatial.transform import Rotation


def assert_sim3_close(a: Sim3, b: Sim3, tol: float = 1e-10) -> None:
    np.testing.assert_allclose(a.R, b.R, atol=tol)
    np.testing.assert_allclose(a.t, b.t, atol=tol)
    assert a.s == pytest.approx(b.s, abs=tol)


@pytest.mark.parametrize("seed", range(5))
def test_umeyama_recovers_known_sim3(seed):
    rng = np.random.default_rng(seed)
    truth = random_sim3(rng)
    src = rng.normal(size=(20, 3))
    assert_sim3_close(umeyama(src, truth.apply_points(src)), truth)


@pytest.mark.parametrize("seed", range(5))
def test_umeyama_recovers_sim3_of_coplanar_points(seed):
    # Coplanar points: the third singular value is 0 and the SVD's sign there is arbitrary, so without
    # the reflection fix half of these cases come out as a mirror image.
    rng = np.random.default_rng(seed)
    truth = random_sim3(rng)
    src = np.concatenate([rng.normal(size=(12, 2)), np.zeros((12, 1))], axis=1)
    got = umeyama(src, truth.apply_points(src))
    assert np.linalg.det(got.R) == pytest.approx(1.0)
    assert_sim3_close(got, truth)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    mirrored = src * np.array([1.0, 1.0, -1.0])  # the best orthogonal fit is the mirror, det −1
    got = umeyama(src, mirrored)
    assert np.linalg.det(got.R) == pytest.approx(1.0)
    # The proper rotation found beats random proper rotations, each with its own optimal s and t.
    xc, yc = src - src.mean(0), mirrored - mirrored.mean(0)
    best = np.sum((got.apply_points(src) - mirrored) ** 2)
    for R in Rotation.random(200, random_state=rng).as_matrix():
        s = max(np.sum(yc * (xc @ R.T)) / np.sum(xc * xc), 0.0)
        assert best <= np.sum((s * xc @ R.T - yc) ** 2) + 1e-9


def test_umeyama_se3_fixes_scale_and_rejects_degenerate_input():
    rng = np.random.default_rng(1)
    truth = Sim3(Rotation.random(random_state=rng).as_matrix(), np.array([1.0, -2.0, 0.5]), 1.0)
    src = rng.normal(size=(10, 3))
    got = umeyama(src, truth.apply_points(src) * 1.0, with_scale=False)
    assert got.s == 1.0
    assert_sim3_close(got, truth)
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="degenerate"):
        umeyama(line, line)


def test_sim3_pose_application_and_inverse():
    rng = np.random.default_rng(2)
    s3 = random_sim3(rng)
    T = orbit(7, rng)
    out = s3.apply_poses(T)
    np.testing.assert_allclose(out[:, :3, 3], s3.apply_points(T[:, :3, 3]))
    np.testing.assert_allclose(out[:, :3, :3], s3.R @ T[:, :3, :3])
    np.testing.assert_allclose(s3.inverse().apply_poses(out), T, atol=1e-12)
    np.testing.assert_allclose(s3.matrix() @ np.append(T[0, :3, 3], 1.0), np.append(out[0, :3, 3], 1.0))


def test_first_pose_alignment_eq13_14():
    rng = np.random.default_rng(4)
    T_gt = orbit(10, rng)
    R_off = Rotation.random(random_state=rng).as_matrix()
    T_est = make_pose(R_off, np.zeros(3)) @ T_gt
    R_align = first_pose_rotation(T_gt[0, :3, :3], T_est[0, :3, :3])
    np.testing.assert_allclose(R_align, R_off.T, atol=1e-12)
    aligned = align_first_pose(T_gt, T_est)
    np.testing.assert_allclose(aligned, T_gt, atol=1e-12)  # a pure global rotation is fully removed


def test_interpolation_exact_samples_and_midpoints():
    rng = np.random.default_rng(5)
    T = orbit(4, rng)
    t = np.array([0.0, 1.0, 2.0, 4.0])
    np.testing.assert_array_equal(interpolate_poses(t, T, t), T)
    mid = interpolate_poses(t, T, np.array([3.0]))[0]
    np.testing.assert_allclose(mid[:3, 3], (T[2, :3, 3] + T[3, :3, 3]) / 2)
    rel = Rotation.from_matrix(T[2, :3, :3].T @ T[3, :3, :3]).as_rotvec()
    np.testing.assert_allclose(
        mid[:3, :3], T[2, :3, :3] @ Rotation.from_rotvec(rel / 2).as_matrix(), atol=1e-12
    )
    with pytest.raises(ValueError, match="outside"):
        interpolate_poses(t, T, np.array([4.5]))


def test_associate_drops_and_counts_estimates_outside_gt_span():
    rng = np.random.default_rng(6)
    T_gt = orbit(5, rng)
    t_gt = np.arange(5.0)
    t_est = np.array([-1.0, 0.0 - 5e-7, 1.5, 4.0, 4.5])
    T_est = orbit(5, rng)
    a = associate(t_est, T_est, t_gt, T_gt)
    assert a.dropped == 2
    np.testing.assert_array_equal(a.est_index, [1, 2, 3])
    np.testing.assert_array_equal(a.T_gt[0], T_gt[0])  # snapped onto the span within tolerance
    np.testing.assert_array_equal(a.T_gt[2], T_gt[4])
    with pytest.raises(ValueError, match="ground-truth time span"):
        associate(np.array([9.0]), T_est[:1], t_gt, T_gt)

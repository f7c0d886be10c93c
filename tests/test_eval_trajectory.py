"""Trajectory metrics: hand-computed cases, and agreement with evo (a test-only oracle, GPL) to 1e-6."""

import numpy as np
import pytest
from eval_synth import orbit, perturb, random_sim3
from evgs.data.tum import read_tum, write_tum
from evgs.eval.associate import associate
from evgs.eval.trajectory import evaluate_trajectory, rotation_angle, rpe_pairs, wrap_deg
from evgs.geometry import make_pose
from scipy.spatial.transform import Rotation

A = 0.3
# Four GT positions and z-offsets with zero mean and zero cross-covariance with them: Umeyama's rotation
# and translation stay identity, and only the scale responds (s = 1 / (1 + a²)).
P_GT = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]])
D = np.array([[0, 0, A], [0, 0, A], [0, 0, -A], [0, 0, -A]])
YAW_DEG = np.array([0.0, 5.0, 10.0, 20.0])


def hand_case():
    T_gt = make_pose(np.broadcast_to(np.eye(3), (4, 3, 3)), P_GT)
    R_est = Rotation.from_euler("z", YAW_DEG[:, None], degrees=True).as_matrix()
    R_off = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()  # a global offset removed by eq. 13–14
    return T_gt, make_pose(R_off @ R_est, P_GT + D)


def test_ate_hand_computed_se3():
    T_gt, T_est = hand_case()
    m = evaluate_trajectory(T_gt, T_est, with_scale=False)
    np.testing.assert_allclose(m.sim3.R, np.eye(3), atol=1e-12)
    assert m.ate_rmse == pytest.approx(A, abs=1e-12)
    np.testing.assert_allclose(m.axis_rmse, [0, 0, A], atol=1e-12)


def test_ate_hand_computed_sim3():
    T_gt, T_est = hand_case()
    m = evaluate_trajectory(T_gt, T_est)
    assert m.sim3.s == pytest.approx(1 / (1 + A * A), abs=1e-12)
    # |e_i|² = (1 − s)² + s² a² = a² / (1 + a²) for every pose.
    assert m.ate_rmse == pytest.approx(A / np.sqrt(1 + A * A), abs=1e-12)
    np.testing.assert_allclose(m.ate_errors, A / np.sqrt(1 + A * A), atol=1e-12)


def test_orientation_error_drift_and_ypr_hand_computed():
    T_gt, T_est = hand_case()
    m = evaluate_trajectory(T_gt, T_est)
    np.testing.assert_allclose(m.orientation_error_deg, YAW_DEG, atol=1e-9)
    assert m.drift_deg == pytest.approx(20.0, abs=1e-9)
    np.testing.assert_allclose(m.ypr_rmse_deg, [np.sqrt(np.mean(YAW_DEG**2)), 0, 0], atol=1e-9)
    assert m.summary()["rot_err_rmse_deg"] == pytest.approx(np.sqrt(np.mean(YAW_DEG**2)), abs=1e-9)


def test_gaze_error_reads_a_constant_look_offset():
    """Cameras on the true path that all look 5° beside where they should (a turn about their own y, as
    the orbit's gaze offset): the Sim(3) fits the positions exactly, and the gaze error reads 5° at every
    frame, where the first-pose-aligned error starts at 0."""
    rng = np.random.default_rng(3)
    T_gt = orbit(30, rng)
    look = Rotation.from_euler("y", 5.0, degrees=True).as_matrix()
    T_est = random_sim3(rng).inverse().apply_poses(make_pose(T_gt[:, :3, :3] @ look, T_gt[:, :3, 3]))
    m = evaluate_trajectory(T_gt, T_est)
    assert m.ate_rmse == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(m.gaze_error_deg, 5.0, atol=1e-9)
    assert m.summary()["gaze_err_rmse_deg"] == pytest.approx(5.0, abs=1e-9)
    assert m.orientation_error_deg[0] == pytest.approx(0.0, abs=1e-9)


def test_gaze_error_undefined_on_a_straight_path():
    """An approach along a line: the positions leave the Sim(3)'s turn about the line free, so the gaze
    error is NaN, while the ATE and the first-pose-aligned errors are as usual."""
    n, rng = 20, np.random.default_rng(0)
    path = np.outer(np.linspace(0, 2, n), [0, 0, 1.0]) + rng.normal(scale=1e-5, size=(n, 3))  # a sim's wobble
    T_gt = make_pose(np.broadcast_to(np.eye(3), (n, 3, 3)), path)
    T_est = T_gt.copy()
    T_est[:, :3, 3] += rng.normal(scale=1e-3, size=(n, 3))
    m = evaluate_trajectory(T_gt, T_est)
    assert np.isnan(m.gaze_error_deg).all() and np.isnan(m.summary()["gaze_err_rmse_deg"])
    assert m.ate_rmse < 2e-3 and np.isfinite(m.drift_deg)


def test_rotation_angle_accurate_near_zero_and_pi():
    for ang in (1e-9, 1e-4, 1.0, np.pi - 1e-7, np.pi):
        R = Rotation.from_rotvec(ang * np.array([0.6, 0.0, 0.8])).as_matrix()
        assert rotation_angle(R) == pytest.approx(ang, rel=1e-6, abs=1e-15)


def test_wrap_deg():
    np.testing.assert_allclose(wrap_deg(np.array([190.0, -190.0, 180.0, 359.0])), [-170, 170, 180, -1])


def test_rpe_pairs():
    p = np.array([[0.0, 0, 0], [0.4, 0, 0], [0.8, 0, 0], [1.3, 0, 0], [1.5, 0, 0], [2.4, 0, 0]])
    np.testing.assert_array_equal(rpe_pairs(p, 2, "frames"), [[0, 2], [2, 4]])
    np.testing.assert_array_equal(rpe_pairs(p, 0.75, "m"), [[0, 2], [2, 5]])
    assert rpe_pairs(p, 100.0, "m").shape == (0, 2)
    with pytest.raises(ValueError):
        rpe_pairs(p, 1.5, "frames")


def test_rejects_too_few_poses():
    T = orbit(2, np.random.default_rng(0))
    with pytest.raises(ValueError, match="≥ 3"):
        evaluate_trajectory(T, T)


@pytest.fixture(scope="module")
def tum_pair(tmp_path_factory):
    """GT and a noisy Sim(3)-distorted estimate written as TUM files, same timestamps."""
    rng = np.random.default_rng(42)
    d = tmp_path_factory.mktemp("evo")
    t = 10.0 + np.arange(60) * 0.1
    T_gt = orbit(60, rng)
    T_est = perturb(T_gt, random_sim3(rng), rng, pos_sigma=0.05, rot_sigma=0.03)
    write_tum(d / "gt.txt", t, T_gt)
    write_tum(d / "est.txt", t, T_est)
    return d / "gt.txt", d / "est.txt"


def _ours(tum_pair, rpe_delta_m=1.0):
    t_gt, T_gt = read_tum(tum_pair[0])
    t_est, T_est = read_tum(tum_pair[1])
    a = associate(t_est, T_est, t_gt, T_gt)
    assert a.dropped == 0
    return evaluate_trajectory(a.T_gt, a.T_est, rpe_delta_m=rpe_delta_m)


def _evo_aligned(tum_pair):
    from evo.core import sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(tum_pair[0]))
    est = file_interface.read_tum_trajectory_file(str(tum_pair[1]))
    ref, est = sync.associate_trajectories(ref, est)
    est.align(ref, correct_scale=True)
    return ref, est


def test_ate_matches_evo_ape_sim3(tum_pair):
    from evo.core import metrics

    ref, est = _evo_aligned(tum_pair)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    ours = _ours(tum_pair)
    assert ours.ate_rmse == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)
    np.testing.assert_allclose(ours.ate_errors, ape.error, atol=1e-6)
    np.testing.assert_allclose(ours.p_est, est.positions_xyz, atol=1e-6)


def test_gaze_error_matches_evo_ape_angle(tum_pair):
    from evo.core import metrics

    ref, est = _evo_aligned(tum_pair)
    ape = metrics.APE(metrics.PoseRelation.rotation_angle_deg)
    ape.process_data((ref, est))
    ours = _ours(tum_pair)
    np.testing.assert_allclose(ours.gaze_error_deg, ape.error, atol=1e-6)
    assert ours.summary()["gaze_err_rmse_deg"] == pytest.approx(
        ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-6
    )


@pytest.mark.parametrize(("delta", "unit"), [(1, "frames"), (0.5, "m")])
def test_rpe_matches_evo_rpe(tum_pair, delta, unit):
    from evo.core import metrics

    ref, est = _evo_aligned(tum_pair)
    evo_unit = metrics.Unit.frames if unit == "frames" else metrics.Unit.meters
    ours = _ours(tum_pair, rpe_delta_m=delta if unit == "m" else 1.0)
    r = ours.rpe_frame if unit == "frames" else ours.rpe_metre
    assert len(r.pairs) > 5
    for relation, mine in (
        (metrics.PoseRelation.translation_part, r.trans),
        (metrics.PoseRelation.rotation_angle_deg, r.rot_deg),
    ):
        m = metrics.RPE(relation, delta=delta, delta_unit=evo_unit, all_pairs=False)
        m.process_data((ref, est))
        np.testing.assert_allclose(mine, m.error, atol=1e-6)
        assert float(np.sqrt(np.mean(mine**2))) == pytest.approx(
            m.get_statistic(metrics.StatisticsType.rmse), abs=1e-6
        )


def test_ate_matches_evo_ape_cli(tum_pair, tmp_path):
    """The command users run: ``evo_ape tum GT EST -as`` (result saved as a zip, read back)."""
    import shutil
    import subprocess
    import sys
    import zipfile
    from pathlib import Path

    exe = Path(sys.executable).with_name("evo_ape")
    if not exe.exists():
        exe = shutil.which("evo_ape")
    assert exe, "evo_ape not installed (pip install evo)"
    out = tmp_path / "ape.zip"
    subprocess.run(
        [
            str(exe),
            "tum",
            str(tum_pair[0]),
            str(tum_pair[1]),
            "-as",
            "--save_results",
            str(out),
            "--no_warnings",
        ],
        check=True,
        capture_output=True,
    )
    import json

    with zipfile.ZipFile(out) as z:
        stats = json.loads(z.read("stats.json"))
    assert _ours(tum_pair).ate_rmse == pytest.approx(stats["rmse"], abs=1e-6)

"""The map's depth against the simulated scene (``evgs.eval.depth``): the per-view comparison on known
arrays, and a run end to end whose map is a flat target's plane, written through a random Sim(3):
exactly on the plane it reads 0 %, moved 5 % nearer the cameras −5 %."""

import numpy as np
import pytest
import tomli_w
import tomllib
import trimesh
from eval_synth import random_sim3, write_fake_run, write_ply
from evgs.data.sequence import Camera, write_sequence
from evgs.eval.depth import DepthMetrics, compare_depth, simulated_scene
from evgs.eval.plots import plot_run
from evgs.eval.run import evaluate_run, save_metrics
from evgs.events.arrays import EventArray
from evgs.geometry import make_pose
from scipy.spatial.transform import Rotation

DISTANCE = 4.0  # the cameras' height over the target's face


def test_compare_depth_on_known_arrays():
    gt = np.array([[2.0, 4.0], [np.inf, 5.0]])
    alpha = np.array([[1.0, 0.5], [1.0, 0.2]])  # the last pixel is not the map's
    depth = np.array([[1.0, 2.2], [3.0, 9.9]]) * alpha  # un-normalised: D = mean depth × alpha
    l1, rel, coverage, spill = compare_depth(depth, alpha, gt, scale=2.0)  # map depths in metres: 2.0, 4.4
    assert l1 == pytest.approx((0.0 + 0.4) / 2)
    assert rel == pytest.approx(np.median([0.0, 0.1]))
    assert coverage == pytest.approx(2 / 3)  # 2 of the target's 3 pixels (the inf one is background)
    assert spill == pytest.approx(1 / 3)  # the opaque background pixel, per target pixel
    assert np.isnan(compare_depth(depth, alpha * 0, gt, 1.0)[1])  # nothing compared


def _flat_target_run(tmp_path, rng, nearer: float, half: float = 1.4):
    """A simulated-looking sequence of a 3 m square plate (a mesh file) seen from ``DISTANCE`` above,
    and a run whose map is a carpet of flat Gaussians on the plate's face lifted ``nearer`` × DISTANCE
    towards the cameras, map and trajectory both expressed through a random Sim(3)."""
    plate = trimesh.creation.box(extents=(3.0, 3.0, 0.02))  # centred on load: face at z = 0.01
    mesh = tmp_path / "plate.stl"
    plate.export(mesh)
    n = 4
    R = np.diag([1.0, -1.0, -1.0])  # looking down −z
    lateral = np.array([[-0.3, 0.0], [0.1, 0.1], [0.3, -0.2], [-0.1, 0.3]])  # not on one line (Sim(3))
    T_gt = make_pose(np.repeat(R[None], n, 0), np.column_stack([lateral, np.full(n, DISTANCE + 0.01)]))
    size = 64
    frames_us = 1_000_000 + np.arange(n, dtype=np.int64) * 50_000
    zero = np.zeros(1, np.uint16)
    seq = write_sequence(
        tmp_path / "seqs" / "plate", "plate", Camera(size, size, 40.0, 40.0, 31.5, 31.5),
        EventArray(frames_us[:1], zero, zero, np.ones(1, np.int8), size, size), frames_us,
        poses_gt=(frames_us, T_gt),
        meta={"source": "evgs simulate", "simulator": {"target": str(mesh), "mesh_scale": 1.0}},
    )  # fmt: skip
    sim3 = random_sim3(rng)  # estimate → ground truth
    inv = sim3.inverse()
    run = write_fake_run(tmp_path, seq, inv.apply_poses(T_gt))
    g = np.arange(-half, half + 1e-6, 0.025)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    means = np.column_stack([xy, np.full(len(xy), 0.01 + nearer * DISTANCE)])
    log_scales = np.log(np.tile([0.02, 0.02, 0.001], (len(means), 1))) + np.log(inv.s)
    q_xyzw = np.tile(Rotation.from_matrix(inv.R).as_quat(), (len(means), 1))
    write_ply(run / "gaussians.ply", inv.apply_points(means), log_scales, q_xyzw[:, [3, 0, 1, 2]],
              np.full(len(means), 6.0), np.full(len(means), 0.5))  # fmt: skip
    return run


@pytest.mark.parametrize("nearer", [0.0, 0.05])
def test_a_map_on_the_target_reads_its_offset(tmp_path, nearer):
    run = _flat_target_run(tmp_path, np.random.default_rng(3), nearer)
    ev = evaluate_run(run, images=False)
    assert ev.depth is not None
    d = ev.depth.summary()
    assert d["depth_err_pct"] == pytest.approx(-100 * nearer, abs=0.1)
    assert d["depth_l1_m"] == pytest.approx(nearer * DISTANCE, abs=0.005)
    assert d["depth_coverage"] > 0.95  # the carpet covers the whole plate
    if nearer == 0:  # (lifted, the carpet looks larger than the plate)
        # and little beyond it: a pixel's rim on two sides of 30, as the rasterizer evaluates pixel i at
        # i + 0.5 and the simulator's renderer at i (OpenCV), half a pixel apart
        assert d["depth_spill"] < 0.1
    assert [v.frame for v in ev.depth.views] == [0, 2, 3]  # the first, middle and last frames
    view = ev.depth.views[0]
    np.testing.assert_allclose(np.nanmedian(view.map_m / view.gt_m), 1.0 - nearer, atol=1e-3)
    save_metrics(ev, run / "eval" / "metrics.json")
    assert "depth" in (run / "eval" / "metrics.json").read_text()
    figures = plot_run(ev, run / "eval")
    assert figures["depth_error"].is_file() and figures["depth_views"].is_file()


def test_depth_is_skipped_with_a_reason_when_the_scene_is_gone(tmp_path):
    run = _flat_target_run(tmp_path, np.random.default_rng(4), 0.0)
    (tmp_path / "plate.stl").unlink()
    ev = evaluate_run(run, images=False)
    assert ev.depth is None
    assert any("cannot be rebuilt" in note for note in ev.notes)
    assert np.isnan(ev.summary()["depth_err_pct"])


def test_recorded_sequences_have_no_scene(tmp_path):
    run = _flat_target_run(tmp_path, np.random.default_rng(5), 0.0)
    toml = tmp_path / "seqs" / "plate" / "sequence.toml"
    meta = tomllib.loads(toml.read_text())
    del meta["simulator"]
    toml.write_text(tomli_w.dumps(meta))
    assert simulated_scene(evaluate_run(run, images=False, depth=False).sequence) is None
    assert evaluate_run(run, images=False).depth is None


def test_a_map_off_the_target_still_reports_its_coverage_and_spill():
    frames = np.arange(3)
    metrics = DepthMetrics(
        frames, np.full(3, np.nan), np.full(3, np.nan), np.zeros(3), np.array([0.5, 1.5, np.nan])
    )
    s = metrics.summary()
    assert np.isnan(s["depth_err_pct"]) and np.isnan(s["depth_l1_m"])
    assert s["depth_coverage"] == 0.0
    assert s["depth_spill"] == pytest.approx(1.0)  # the frame without the target skipped

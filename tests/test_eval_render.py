"""Image metrics of a run end to end: ``gaussians.ply`` rendered at the GT frames through the inverse of
the evaluation Sim(3). Needs ``evgs.render`` (branch raster) and ``evgs.slam.gaussians`` (branch slam):
skipped until those are merged.

The scene is written twice in the standard 3DGS PLY layout: in the GT frame (to render the GT images)
and mapped into the estimate's frame (the run's map). If the camera transform is right, the run's
renders reproduce the GT images.
"""

import numpy as np
import pytest
from eval_synth import orbit, perturb, random_sim3, write_fake_run, write_fake_sequence
from scipy.spatial.transform import Rotation

render_mod = pytest.importorskip("evgs.render")
gaussians_mod = pytest.importorskip("evgs.slam.gaussians")

import torch  # noqa: E402
from evgs.data.sequence import Camera  # noqa: E402
from evgs.eval.render_gt import gt_poses_in_map, render_at_gt_frames  # noqa: E402
from evgs.eval.run import evaluate_run  # noqa: E402
from evgs.geometry import invert_pose  # noqa: E402

SH_C0 = 0.28209479177387814
FIELDS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
          "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip


def write_ply(path, means, log_scales, quats_wxyz, opacity_logits, grey):
    rows = np.zeros(len(means), dtype=[(f, "<f4") for f in FIELDS])
    for i, a in enumerate("xyz"):
        rows[a] = means[:, i]
        rows[f"scale_{i}"] = log_scales[:, i]
    for i in range(3):
        rows[f"f_dc_{i}"] = (grey - 0.5) / SH_C0
    for i in range(4):
        rows[f"rot_{i}"] = quats_wxyz[:, i]
    rows["opacity"] = opacity_logits
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(rows)}"]
    header += [f"property float {f}" for f in FIELDS] + ["end_header"]
    path.write_bytes(("\n".join(header) + "\n").encode() + rows.tobytes())


def test_render_at_gt_frames_reproduces_gt_images(tmp_path):
    rng = np.random.default_rng(11)
    n_frames, n_g = 6, 300
    T_gt = orbit(n_frames, rng)
    means = rng.normal(size=(n_g, 3)) * 0.4
    log_scales = np.log(rng.uniform(0.03, 0.08, size=(n_g, 3)))
    q_xyzw = Rotation.random(n_g, random_state=rng).as_quat()
    logits = rng.uniform(0.0, 3.0, n_g)
    grey = rng.uniform(0.2, 1.0, n_g)
    write_ply(tmp_path / "gt.ply", means, log_scales, q_xyzw[:, [3, 0, 1, 2]], logits, grey)

    # GT images: the GT-frame scene rendered at the GT poses.
    g = gaussians_mod.load_ply(tmp_path / "gt.ply")
    viewmats = torch.from_numpy(invert_pose(T_gt).astype(np.float32))
    with torch.no_grad():
        res = render_mod.render(
            **g.render_inputs(), viewmats=viewmats, camera=Camera(64, 64, 60.0, 60.0, 32.0, 32.0)
        )
    gt_images = res.color.mean(dim=-1).clamp(0, 1).numpy()
    assert gt_images.std() > 0.05  # the scene is actually visible
    seq = write_fake_sequence(tmp_path, "render", T_gt, gt_images, focal=60.0)

    # The run: estimate and map expressed through the inverse of a random Sim(3).
    sim3 = random_sim3(rng)
    inv = sim3.inverse()
    run = write_fake_run(tmp_path, seq, perturb(T_gt, sim3, rng, pos_sigma=0.0, rot_sigma=0.0))
    q_map = (Rotation.from_matrix(inv.R) * Rotation.from_quat(q_xyzw)).as_quat()
    map_means, map_log_scales = inv.apply_points(means), log_scales + np.log(inv.s)
    write_ply(run / "gaussians.ply", map_means, map_log_scales, q_map[:, [3, 0, 1, 2]], logits, grey)

    ev = evaluate_run(run, image_poses="gt")
    np.testing.assert_allclose(ev.traj.sim3.s, sim3.s, rtol=1e-6)
    np.testing.assert_allclose(gt_poses_in_map(seq, ev.traj.sim3, np.arange(n_frames)), inv.apply_poses(T_gt),
                               atol=1e-6)  # fmt: skip
    renders = render_at_gt_frames(run / "gaussians.ply", seq, ev.traj.sim3, np.arange(n_frames))
    np.testing.assert_allclose(renders, gt_images, atol=2e-3)
    assert ev.images is not None
    assert ev.images.summary()["psnr_db"] > 45.0
    assert ev.images.summary()["lpips"] < 0.01


def test_image_metrics_from_estimated_poses_see_pose_errors(tmp_path):
    """Default viewpoint = the estimated poses: an exact estimate (up to Sim(3)) reproduces the GT images,
    a perturbed one scores lower, while the GT-viewpoint renders of the same map do not change."""
    rng = np.random.default_rng(5)
    n_frames, n_g = 5, 300
    T_gt = orbit(n_frames, rng)
    means = rng.normal(size=(n_g, 3)) * 0.4
    log_scales = np.log(rng.uniform(0.03, 0.08, size=(n_g, 3)))
    q_xyzw = Rotation.random(n_g, random_state=rng).as_quat()
    logits = rng.uniform(0.0, 3.0, n_g)
    grey = rng.uniform(0.2, 1.0, n_g)
    write_ply(tmp_path / "gt.ply", means, log_scales, q_xyzw[:, [3, 0, 1, 2]], logits, grey)
    g = gaussians_mod.load_ply(tmp_path / "gt.ply")
    with torch.no_grad():
        res = render_mod.render(
            **g.render_inputs(),
            viewmats=torch.from_numpy(invert_pose(T_gt).astype(np.float32)),
            camera=Camera(64, 64, 60.0, 60.0, 32.0, 32.0),
        )
    gt_images = res.color.mean(dim=-1).clamp(0, 1).numpy()
    seq = write_fake_sequence(tmp_path, "est", T_gt, gt_images, focal=60.0)
    scores = {}
    for name, sigma in [("exact", 0.0), ("perturbed", 0.05)]:
        sim3 = random_sim3(rng)
        inv = sim3.inverse()
        run = write_fake_run(tmp_path / name, seq, perturb(T_gt, sim3, rng, pos_sigma=sigma, rot_sigma=sigma))
        q_map = (Rotation.from_matrix(inv.R) * Rotation.from_quat(q_xyzw)).as_quat()
        write_ply(run / "gaussians.ply", inv.apply_points(means), log_scales + np.log(inv.s),
                  q_map[:, [3, 0, 1, 2]], logits, grey)  # fmt: skip
        scores[name] = evaluate_run(run).images.summary()["psnr_db"]
    assert scores["exact"] > 45.0
    assert scores["perturbed"] < scores["exact"] - 10.0

"""Image metrics of a run end to end: ``gaussians.ply`` rendered at the GT frames through the inverse of
the evaluation Sim(3). Needs ``evgs.render`` (branch raster) and ``evgs.slam.gaussians`` (branch slam):
skipped until those are merged.

The scene is written twice in the standard 3DGS PLY layout: in the GT frame (to render the GT images)
and mapped into the estimate's frame (the run's map). If the camera transform is right, the run's
renders reproduce the GT images.
"""

import numpy as np
import pytest
from eval_synth import orbit, perturb, random_sim3, write_fake_run, write_fake_sequence, write_ply
from scipy.spatial.transform import Rotation

render_mod = pytest.importorskip("evgs.render")
gaussians_mod = pytest.importorskip("evgs.slam.gaussians")

import torch  # noqa: E402
from evgs.data.sequence import Camera  # noqa: E402
from evgs.eval.render_gt import gt_poses_in_map, render_at_gt_frames  # noqa: E402
from evgs.eval.run import evaluate_run  # noqa: E402
from evgs.geometry import invert_pose  # noqa: E402


class Scene:
    """A random Gaussian scene seen along a GT orbit, written as a 3DGS PLY, with its GT images."""

    def __init__(self, tmp_path, rng, n_frames: int, name: str, n_g: int = 300):
        self.T_gt = orbit(n_frames, rng)
        self.means = rng.normal(size=(n_g, 3)) * 0.4
        self.log_scales = np.log(rng.uniform(0.03, 0.08, size=(n_g, 3)))
        self.q_xyzw = Rotation.random(n_g, random_state=rng).as_quat()
        self.logits = rng.uniform(0.0, 3.0, n_g)
        self.grey = rng.uniform(0.2, 1.0, n_g)
        self.write(tmp_path / "gt.ply", self.means, self.log_scales, self.q_xyzw)
        g = gaussians_mod.load_ply(tmp_path / "gt.ply")
        viewmats = torch.from_numpy(invert_pose(self.T_gt).astype(np.float32))
        with torch.no_grad():
            res = render_mod.render(
                **g.render_inputs(), viewmats=viewmats, camera=Camera(64, 64, 60.0, 60.0, 32.0, 32.0)
            )
        self.gt_images = res.color.mean(dim=-1).clamp(0, 1).numpy()
        self.seq = write_fake_sequence(tmp_path, name, self.T_gt, self.gt_images, focal=60.0)

    def write(self, path, means, log_scales, q_xyzw):
        write_ply(path, means, log_scales, q_xyzw[:, [3, 0, 1, 2]], self.logits, self.grey)

    def write_run(self, root, sim3, rng, sigma: float):
        """A run whose estimate (noise ``sigma``) and map are expressed through the inverse of ``sim3``."""
        inv = sim3.inverse()
        run = write_fake_run(root, self.seq, perturb(self.T_gt, sim3, rng, pos_sigma=sigma, rot_sigma=sigma))
        q_map = (Rotation.from_matrix(inv.R) * Rotation.from_quat(self.q_xyzw)).as_quat()
        self.write(
            run / "gaussians.ply", inv.apply_points(self.means), self.log_scales + np.log(inv.s), q_map
        )
        return run


def test_render_at_gt_frames_reproduces_gt_images(tmp_path):
    rng = np.random.default_rng(11)
    n_frames = 6
    scene = Scene(tmp_path, rng, n_frames, "render")
    assert scene.gt_images.std() > 0.05  # the scene is actually visible
    seq = scene.seq
    sim3 = random_sim3(rng)
    run = scene.write_run(tmp_path, sim3, rng, 0.0)

    ev = evaluate_run(run, image_poses="gt")
    np.testing.assert_allclose(ev.traj.sim3.s, sim3.s, rtol=1e-6)
    np.testing.assert_allclose(gt_poses_in_map(seq, ev.traj.sim3, np.arange(n_frames)),
                               sim3.inverse().apply_poses(scene.T_gt), atol=1e-6)  # fmt: skip
    renders = render_at_gt_frames(run / "gaussians.ply", seq, ev.traj.sim3, np.arange(n_frames))
    np.testing.assert_allclose(renders, scene.gt_images, atol=2e-3)
    assert ev.images is not None
    assert ev.images.summary()["psnr_db"] > 45.0
    assert ev.images.summary()["lpips"] < 0.01


def test_image_metrics_from_estimated_poses_see_pose_errors(tmp_path):
    """Default viewpoint = the estimated poses: an exact estimate (up to Sim(3)) reproduces the GT images,
    a perturbed one scores clearly lower."""
    rng = np.random.default_rng(5)
    scene = Scene(tmp_path, rng, 5, "est")
    psnr = {
        name: evaluate_run(scene.write_run(tmp_path / name, random_sim3(rng), rng, sigma)).images.summary()[
            "psnr_db"
        ]
        for name, sigma in [("exact", 0.0), ("perturbed", 0.05)]
    }
    assert psnr["exact"] > 45.0
    assert psnr["perturbed"] < psnr["exact"] - 10.0

"""Metric scale from a range meter or a known target size, on a synthetic scene whose truth is known."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.config import load_config  # noqa: E402
from evgs.render import render  # noqa: E402
from evgs.slam import checkpoint  # noqa: E402
from evgs.slam.gaussians import Gaussians, quat_to_rotmat  # noqa: E402
from evgs.slam.lie import se3_exp  # noqa: E402
from evgs.slam.metric_scale import (  # noqa: E402
    after_initialization,
    apply_scale,
    closing_scale,
    estimate_scale,
    first_surface,
    map_extent,
    range_agreement,
    range_scale,
    read_surface_scale,
)
from evgs.slam.pipeline import check_range_meter, run_slam, write_metric_scale  # noqa: E402
from evgs.slam.run_dir import RunDir  # noqa: E402
from evgs.slam.state import Position, SlamState  # noqa: E402
from evgs.slam.trajectory import Trajectory  # noqa: E402
from slam_synth import gt_state, make_sequence  # noqa: E402

TRUE_SCALE = 2.5  # metres per map unit of the state the tests build


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq") / "synth")


def state_in_map_units(synth, *sets: str) -> tuple[SlamState, np.ndarray]:
    """The scene and its GT knots shrunk by ``TRUE_SCALE`` (what a monocular run might hold), and the
    true range on the principal ray at the knot times: the metric scene's first surface there."""
    seq, scene = synth
    _, ranges = first_surface(scene.gaussians, torch.as_tensor(scene.poses))
    ranges = ranges.numpy()
    state = gt_state(seq, scene, *sets)
    apply_scale(state, 1 / TRUE_SCALE)
    return state, ranges


def test_apply_scale_leaves_every_render_unchanged(synth):
    seq, scene = synth
    state, _ = state_in_map_units(synth)
    with torch.no_grad():
        vm = torch.linalg.inv(torch.as_tensor(scene.poses)).float()
        before = render(**scene.gaussians.render_inputs(), viewmats=vm, camera=seq.camera)
        after = render(
            **state.gaussians.render_inputs(),
            viewmats=state.traj.viewmats_at(scene.frames_us),
            camera=seq.camera,
        )
    assert torch.allclose(after.color, before.color, atol=1e-5)
    assert torch.allclose(after.depth * TRUE_SCALE, before.depth, rtol=1e-4, atol=1e-5)


def test_range_meter_recovers_the_scale(synth):
    _, scene = synth
    state, ranges = state_in_map_units(synth)
    est = range_scale(state, scene.frames_us, ranges, min_alpha=0.5)
    assert est.scale == pytest.approx(TRUE_SCALE, rel=1e-4) and est.samples >= 3
    # A minority of wrong samples (the meter hitting something the map lacks) does not move the median.
    bad = ranges.copy()
    bad[:2] *= 3.0
    assert range_scale(state, scene.frames_us, bad, 0.5).scale == pytest.approx(TRUE_SCALE, rel=1e-4)
    with pytest.raises(ValueError, match="inside the run"):
        range_scale(state, scene.frames_us - 10**9, ranges, 0.5)
    with pytest.raises(ValueError, match="covers the image centre"):
        range_scale(state, scene.frames_us, ranges, 1.1)


def test_range_agreement_sees_the_map_drift_from_the_meter(synth, tmp_path):
    _, scene = synth
    state, ranges = state_in_map_units(synth)
    agreement = range_agreement(state, scene.frames_us, ranges, 0.5)
    assert agreement.covered.all() and len(agreement.t_us) >= 6
    np.testing.assert_allclose(agreement.ratios, TRUE_SCALE, rtol=1e-4)
    assert abs(agreement.drift()) < 1e-4
    # The meter reads 20 % farther over the second half: the map ends 20 % nearer than it says.
    half = len(ranges) // 2
    farther = np.where(np.arange(len(ranges)) < half, 1.0, 1.2) * ranges
    assert range_agreement(state, scene.frames_us, farther, 0.5).drift() == pytest.approx(0.2, rel=1e-3)
    # A map that covers no ray: nothing to compare, and a run says so.
    assert np.isnan(range_agreement(state, scene.frames_us, ranges, 1.1).drift())
    bare = dataclasses.replace(
        state, data=dataclasses.replace(state.data, ranges=(scene.frames_us, ranges)), metric={},
        cfg=load_config("synthetic/tiny", ["scale.min_alpha=1.1"]),
    )  # fmt: skip
    run = RunDir.create(tmp_path / "bare", "synth", state.cfg)
    check_range_meter(bare, run, None)
    assert bare.metric["range_map_samples"] == 0 and np.isnan(bare.metric["range_map_drift"])
    assert not (run.diagnostics / "range_meter.png").exists()
    assert "too few to compare" in (run.root / "log.txt").read_text()
    # In a run: the figure, the metrics and the log line, whatever scale.source is; the map's first
    # surface agrees with the meter at the map's scale.
    metered = dataclasses.replace(
        state, data=dataclasses.replace(state.data, ranges=(scene.frames_us, ranges)), metric={}
    )
    run = RunDir.create(tmp_path, "synth", state.cfg)
    check_range_meter(metered, run, None)
    assert metered.metric["range_map_ratio"] == pytest.approx(TRUE_SCALE, rel=1e-4)
    assert abs(metered.metric["range_map_drift"]) < 1e-4
    assert metered.metric["range_map_samples"] == len(ranges)
    assert (run.diagnostics / "range_meter.png").stat().st_size > 0
    assert "0.0% from the run's first fifth" in (run.root / "log.txt").read_text()


def test_closing_rate_scale_fits_the_advance_and_says_how_much_it_explains():
    # An approach in map units (0.2 per step along the optical axis) to a wall 5 units ahead that the
    # meter reads in metres at TRUE_SCALE: the fit recovers the scale and explains every decrease.
    twist = torch.tensor([0.0, 0.0, 0.2, 0.0, 0.0, 0.0], dtype=torch.float64)
    poses = se3_exp(torch.arange(12, dtype=torch.float64)[:, None] * twist[None])
    t_us = np.arange(12, dtype=np.int64) * 100_000
    traj = Trajectory(t_us, poses)
    metres = TRUE_SCALE * (5.0 - 0.2 * np.arange(12))
    fit = closing_scale(traj, t_us, metres)
    assert fit is not None and fit.samples == 12 and fit.jumps == 0
    assert fit.scale == pytest.approx(TRUE_SCALE, rel=1e-9) and fit.explained == pytest.approx(1.0)
    # Relief the ray sweeps: explained less; a range that only follows the target's shape: nothing.
    rng = np.random.default_rng(0)
    bumpy = metres + rng.normal(0.0, 0.05, 12)
    assert 0.5 < closing_scale(traj, t_us, bumpy).explained < 0.999
    # The ray crosses an edge onto a surface 0.4 m behind: that pair is left out, the fit unchanged.
    stepped = metres.copy()
    stepped[6:] += 0.4
    fit = closing_scale(traj, t_us, stepped)
    assert fit.jumps == 1 and fit.scale == pytest.approx(TRUE_SCALE, rel=1e-9)
    assert fit.explained == pytest.approx(1.0)
    still = Trajectory(t_us, se3_exp(torch.zeros(12, 6, dtype=torch.float64)))
    assert closing_scale(still, t_us, metres) is None  # no advance: nothing to fit
    assert closing_scale(traj, t_us[:1], metres[:1]) is None


def test_closing_rate_scale_is_not_diluted_by_the_trackers_jitter():
    # An approach of 0.2 map units per sample along the optical axis, each position off by a random
    # 0.05 along it (a tracker's jitter): the pairs' advances scatter, a least-squares slope through the
    # origin reads the scale ≈ 10 % low, the ratio of the sums within the two end samples' error.
    n = 40
    rng = np.random.default_rng(1)
    z = 0.2 * np.arange(n) + rng.normal(0.0, 0.05, n)
    poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    poses[:, 2, 3] = torch.from_numpy(z)
    t_us = np.arange(n, dtype=np.int64) * 100_000
    metres = TRUE_SCALE * (10.0 - 0.2 * np.arange(n))
    fit = closing_scale(Trajectory(t_us, poses), t_us, metres)
    advance, decrease = np.diff(z), -np.diff(metres)
    slope = advance @ decrease / (advance @ advance)
    assert slope < 0.95 * TRUE_SCALE  # the dilution the ratio avoids
    assert fit.scale == pytest.approx(TRUE_SCALE * 7.8 / (z[-1] - z[0]), rel=1e-9)
    assert fit.scale == pytest.approx(TRUE_SCALE, rel=0.02)


def test_the_closing_rate_leaves_out_the_initializations_samples(synth):
    state, _ = state_in_map_units(synth)
    m = state.num_init_chunks()
    t_us = state.traj.t_us.numpy().copy()
    kept_t, kept_r = after_initialization(state, t_us, np.arange(len(t_us), dtype=np.float64))
    assert kept_t[0] == t_us[m] and len(kept_t) == len(t_us) - m and kept_r[0] == m
    # A run that ends with its initialization has nothing after it: every sample counts.
    knots = state.traj.knots().detach()[: m + 1]
    short = dataclasses.replace(state, traj=Trajectory(state.traj.t_us[: m + 1].numpy(), knots))
    assert len(after_initialization(short, t_us, t_us.astype(np.float64))[0]) == len(t_us)


def test_range_scale_takes_the_closing_rate_where_it_explains_the_meter(synth):
    _, scene = synth
    state, ranges = state_in_map_units(synth)
    cfg = load_config(overrides=["scale.source=range"]).scale
    # The test scene orbits its target: the range follows the target's shape, the first surface decides.
    orbit = dataclasses.replace(state, data=dataclasses.replace(state.data, ranges=(scene.frames_us, ranges)))
    est = estimate_scale(orbit, cfg)
    assert est is not None and est.source == "range, first surface"
    assert est.scale == pytest.approx(TRUE_SCALE, rel=1e-4)
    # The same knots, the meter reading an approach: the closing rate (the map plays no part).
    poses = state.traj.knots().detach()
    advance = ((poses[1:, :3, 3] - poses[:-1, :3, 3]) * poses[:-1, :3, 2]).sum(1).numpy()
    approach = 20.0 - TRUE_SCALE * np.concatenate([[0.0], np.cumsum(advance)])
    moved = dataclasses.replace(
        state, data=dataclasses.replace(state.data, ranges=(scene.frames_us, approach))
    )
    est = estimate_scale(moved, cfg)
    assert est is not None and est.source.startswith("range, closing rate")
    assert est.scale == pytest.approx(TRUE_SCALE, rel=1e-6)
    strict = dataclasses.replace(cfg, closing_min_explained=1.0)
    bumpy = approach + np.where(np.arange(len(approach)) % 2, 0.01, -0.01)
    moved = dataclasses.replace(state, data=dataclasses.replace(state.data, ranges=(scene.frames_us, bumpy)))
    assert estimate_scale(moved, strict).source == "range, first surface"
    # A swirl: the ray sweeps the target's relief as the camera closes in, and the advances explain less
    # than 0.9 of the meter but far more than an orbit's ≈ 0.01: still the closing rate (docs §42, §60).
    wobble = 0.3 * np.abs(np.diff(approach)).mean()
    swirl = approach + np.where(np.arange(len(approach)) % 2, wobble, -wobble)
    moved = dataclasses.replace(state, data=dataclasses.replace(state.data, ranges=(scene.frames_us, swirl)))
    fit = closing_scale(moved.traj, *after_initialization(moved, scene.frames_us, swirl))
    assert fit is not None and 0.5 < fit.explained < 0.9
    est = estimate_scale(moved, cfg)
    assert est.source.startswith("range, closing rate") and est.scale == pytest.approx(fit.scale)


def test_the_first_surface_read_before_the_final_ba_is_the_one_applied(synth):
    _, scene = synth
    state, ranges = state_in_map_units(synth, "scale.source=range")
    orbit = dataclasses.replace(state, data=dataclasses.replace(state.data, ranges=(scene.frames_us, ranges)))
    before = read_surface_scale(orbit)
    assert before is not None and before.scale == pytest.approx(TRUE_SCALE, rel=1e-4)
    assert before.source == "range, first surface, read before the final BA"
    # The final BA then moves the map's surface against the cameras (here: the map grows 10 % about the
    # origin, the knots stay): the read kept is the one before it; without one, the map is read now.
    orbit.surface_scale = before
    with torch.no_grad():
        orbit.gaussians["means"].mul_(1.1)
    assert estimate_scale(orbit, orbit.cfg.scale) is before
    now = estimate_scale(dataclasses.replace(orbit, surface_scale=None), orbit.cfg.scale)
    assert now.source == "range, first surface" and abs(now.scale / TRUE_SCALE - 1) > 0.02
    # Told to read at the end, a run ignores a read its state carries (a checkpoint from another config).
    at_end = dataclasses.replace(orbit.cfg.scale, surface_read="end")
    assert estimate_scale(orbit, at_end).scale == now.scale
    # A finished run's checkpoint keeps the read; one written before the key existed has none.
    snap = checkpoint.snapshot(orbit)
    assert checkpoint.restore(snap, orbit.cfg, orbit.data).surface_scale == before
    del snap["surface_scale"]
    assert checkpoint.restore(snap, orbit.cfg, orbit.data).surface_scale is None
    # Nothing to read: no meter, another source, or a map that covers no sample's ray.
    assert read_surface_scale(state) is None
    other = load_config("synthetic/tiny", ["scale.source=target_size", "scale.target_size=1.0"])
    assert read_surface_scale(dataclasses.replace(orbit, cfg=other)) is None
    bare = load_config("synthetic/tiny", ["scale.source=range", "scale.min_alpha=1.1"])
    assert read_surface_scale(dataclasses.replace(orbit, cfg=bare)) is None


class SeeFinalBA:
    """A reporter that notes the state's first-surface read and relief prior when the final global BA
    begins."""

    def __init__(self):
        self.read_at_final, self.depth_tv_at_final = "not reached", None

    def advance(self, state, spec, it, loss, events, seconds) -> None:
        if spec.stage == "final" and self.read_at_final == "not reached":
            self.read_at_final, self.depth_tv_at_final = state.surface_scale, state.cfg.loss.depth_tv

    def stage_end(self, state, spec, record) -> None:
        pass


def finish_a_run(synth, tmp_path, *overrides: str) -> tuple[SlamState, RunDir, SeeFinalBA]:
    """A tracked run's last steps (the first-surface read, the smoother, a 3-step final BA, the scale),
    the range meter on an orbit of the scene."""
    _, scene = synth
    state, ranges = state_in_map_units(
        synth, "scale.source=range", "global_ba.num_opti_steps_final=3", *overrides
    )
    state = dataclasses.replace(
        state, data=dataclasses.replace(state.data, ranges=(scene.frames_us, ranges)),
        position=Position(initialized=True, next_chunk=state.data.n_chunks),
    )  # fmt: skip
    seen = SeeFinalBA()
    run = RunDir.create(tmp_path, "synth", state.cfg)
    run_slam(state, run, seen)
    return state, run, seen


def test_a_run_applies_the_first_surface_it_read_before_its_final_ba(synth, tmp_path):
    state, run, seen = finish_a_run(synth, tmp_path, "output.diagnostics_every=100")
    assert seen.read_at_final is not None and seen.read_at_final.scale == pytest.approx(TRUE_SCALE, rel=1e-4)
    assert state.metric["metric_scale"] == seen.read_at_final.scale
    assert state.metric["metric_scale_source"].endswith("read before the final BA")
    assert checkpoint.load(run.checkpoint_path)["surface_scale"]["scale"] == seen.read_at_final.scale


def test_a_run_told_to_read_the_surface_at_the_end_applies_the_finished_map(synth, tmp_path):
    state, run, seen = finish_a_run(synth, tmp_path, "scale.surface_read=end")
    assert seen.read_at_final is None
    # The checkpoint keeps map units: the finished map read there is the scale the run applied.
    snap = checkpoint.load(run.checkpoint_path)
    assert snap["surface_scale"] is None
    finished = checkpoint.restore(snap, state.cfg, state.data)
    expected = range_scale(finished, *state.data.ranges, state.cfg.scale.min_alpha)
    assert state.metric["metric_scale_source"] == "range, first surface"
    assert state.metric["metric_scale"] == pytest.approx(expected.scale, rel=1e-12)
    assert expected.scale == pytest.approx(TRUE_SCALE, rel=0.02)


def test_the_final_ba_runs_under_its_own_relief_prior(synth, tmp_path):
    """``global_ba.final_depth_tv`` >= 0 is ``loss.depth_tv`` in the final global BA alone, whose edits
    to the map reach the run; < 0 leaves it the run's."""
    before = state_in_map_units(synth)[0].gaussians.state()["means"]
    for final_tv, want in ((0.0, 0.0), (-1.0, 0.5)):
        sets = ["loss.depth_tv=0.5", f"global_ba.final_depth_tv={final_tv}", "scale.surface_read=end"]
        state, run, seen = finish_a_run(synth, tmp_path / str(final_tv), *sets)
        assert seen.depth_tv_at_final == want and state.cfg.loss.depth_tv == 0.5
        assert state.history[-1].stage == "final"
        finished = checkpoint.load(run.checkpoint_path)["gaussians"]["means"]  # map units
        assert finished.shape != before.shape or (finished - before).abs().max() > 1e-4


def flat_gaussian(depth: float, opacity: float, lateral: float = 0.0) -> dict[str, list]:
    """A wide, thin Gaussian facing the camera at ``depth`` on the optical axis (shifted ``lateral`` in x)."""
    logit = float(np.log(opacity / (1 - opacity)))
    return {"means": [lateral, 0.0, depth], "log_scales": [0.0, 0.0, -3.0], "quats": [1.0, 0, 0, 0],
            "opacity_logits": logit, "colors": [0.5]}  # fmt: skip


def gaussians_of(*parts: dict[str, list]) -> Gaussians:
    return Gaussians.from_state({k: torch.tensor([p[k] for p in parts]) for k in parts[0]})


def test_first_surface_is_the_weighted_median_depth_not_the_mean():
    T = torch.eye(4, dtype=torch.float64)[None]
    # An opaque wall at 2 hides the one at 5: the mean depth is 2 as well, and so is the surface.
    opacity, depth = first_surface(gaussians_of(flat_gaussian(2.0, 0.99), flat_gaussian(5.0, 0.99)), T)
    assert float(opacity[0]) == pytest.approx(0.99 + 0.01 * 0.99) and float(depth[0]) == pytest.approx(2.0)
    # A faint veil at 2 in front of a wall at 5: the light is lost at the wall (mean depth ~4.1).
    opacity, depth = first_surface(gaussians_of(flat_gaussian(2.0, 0.3), flat_gaussian(5.0, 0.99)), T)
    assert float(depth[0]) == pytest.approx(5.0)
    # Seen from x = 0.5 the ray passes the wall's centre half a sigma off: alpha = 0.99·exp(−1/8).
    shifted = torch.eye(4, dtype=torch.float64)
    shifted[0, 3] = 0.5
    opacity, depth = first_surface(gaussians_of(flat_gaussian(3.0, 0.99)), shifted[None])
    assert float(opacity[0]) == pytest.approx(0.99 * np.exp(-0.125)) and float(depth[0]) == pytest.approx(3.0)
    # Nothing ahead (the Gaussian is behind the camera): no opacity, no depth.
    opacity, depth = first_surface(gaussians_of(flat_gaussian(-3.0, 0.99)), T)
    assert float(opacity[0]) == 0.0 and np.isnan(float(depth[0]))


def test_first_surface_matches_a_dense_march_along_a_tilted_ray():
    g = small_random_map()
    pose = torch.eye(4, dtype=torch.float64)
    angle = 0.3
    pose[:3, :3] = torch.tensor(
        [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]],
        dtype=torch.float64,
    )
    pose[:3, 3] = torch.tensor([-0.4, 0.1, -0.2], dtype=torch.float64)
    opacity, depth = first_surface(g, pose[None])
    # Reference: each Gaussian's density sampled densely along the ray, its peak taken numerically.
    t = torch.linspace(0.01, 20.0, 400_001, dtype=torch.float64)
    points = pose[:3, 3] + t[:, None] * pose[:3, 2]
    peaks, where = [], []
    state = {k: v.detach().double() for k, v in g.state().items()}
    for mean, rot, scale, o in zip(
        state["means"], quat_to_rotmat(state["quats"]), state["log_scales"].exp(),
        torch.sigmoid(state["opacity_logits"]), strict=True,
    ):  # fmt: skip
        local = (points - mean) @ rot / scale
        density = torch.exp(-0.5 * (local**2).sum(1))
        k = int(density.argmax())
        peaks.append(min(float(o * density[k]), 0.99))
        where.append(float(t[k]))
    order = np.argsort(where)
    a = np.array(peaks)[order]
    a = np.where(a >= 1 / 255, a, 0.0)
    w = a * np.cumprod(np.concatenate([[1.0], 1 - a[:-1]]))
    assert 0.5 < w.sum() < 0.99 and (w > 0.01).sum() >= 3  # several Gaussians share the ray
    assert float(opacity[0]) == pytest.approx(w.sum(), abs=1e-6)
    assert float(depth[0]) == pytest.approx(
        np.array(where)[order][np.searchsorted(np.cumsum(w), w.sum() / 2)], abs=1e-3
    )


def small_random_map() -> Gaussians:
    """Twelve anisotropic, rotated Gaussians strung along x = z·tan(0.3) ahead of the test's ray."""
    gen = torch.Generator().manual_seed(5)
    t = torch.linspace(1.0, 8.0, 12)
    means = torch.stack([-0.4 + t * np.sin(0.3), 0.1 + 0.0 * t, -0.2 + t * np.cos(0.3)], 1)
    means = means + 0.3 * torch.randn(12, 3, generator=gen)
    quats = torch.nn.functional.normalize(torch.randn(12, 4, generator=gen), dim=1)
    return Gaussians.from_state({
        "means": means, "log_scales": torch.log(0.2 + 0.5 * torch.rand(12, 3, generator=gen)), "quats": quats,
        "opacity_logits": torch.randn(12, generator=gen), "colors": torch.full((12, 1), 0.5),
    })  # fmt: skip


def test_target_size_scales_the_map_extent(synth):
    state, _ = state_in_map_units(synth)
    extent = map_extent(state.gaussians)
    est = estimate_scale(
        state, load_config(overrides=["scale.source=target_size", "scale.target_size=3.0"]).scale
    )
    assert est is not None and est.scale == pytest.approx(3.0 / extent)
    apply_scale(state, est.scale)
    assert map_extent(state.gaussians) == pytest.approx(3.0, rel=1e-5)


def test_a_failed_estimate_keeps_map_units_and_says_why(synth, tmp_path):
    state, _ = state_in_map_units(synth, "scale.source=range")  # the test sequence has no range.csv
    means = state.gaussians["means"].detach().clone()
    run = RunDir.create(tmp_path, "synth", state.cfg)
    write_metric_scale(state, run, None)
    assert "no range.csv" in state.metric["metric_scale_failed"]
    assert torch.equal(state.gaussians["means"], means)
    assert "outputs stay in map units" in (run.root / "log.txt").read_text()

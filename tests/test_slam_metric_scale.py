"""Metric scale from a range meter or a known target size, on a synthetic scene whose truth is known."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.config import load_config  # noqa: E402
from evgs.render import render  # noqa: E402
from evgs.slam.gaussians import Gaussians  # noqa: E402
from evgs.slam.guards import BrightnessAnchor  # noqa: E402
from evgs.slam.metric_scale import apply_scale, estimate_scale, map_extent, range_scale  # noqa: E402
from evgs.slam.pipeline import write_metric_scale  # noqa: E402
from evgs.slam.run_dir import RunDir  # noqa: E402
from evgs.slam.state import SlamState  # noqa: E402
from evgs.slam.trajectory import Trajectory  # noqa: E402
from evgs.slam.windows import EventData  # noqa: E402
from slam_synth import make_sequence  # noqa: E402

TRUE_SCALE = 2.5  # metres per map unit of the state the tests build


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq") / "synth")


def state_in_map_units(synth, *sets: str) -> tuple[SlamState, np.ndarray]:
    """The scene and its GT knots shrunk by ``TRUE_SCALE`` (what a monocular run might hold), and the
    true range on the principal ray at the knot times, rendered from the metric scene."""
    seq, scene = synth
    cfg = load_config("synthetic/tiny", ["data.event_contrast=0.2", *sets])
    poses = torch.as_tensor(scene.poses)
    principal = dataclasses.replace(seq.camera, width=1, height=1, cx=0.5, cy=0.5)
    with torch.no_grad():
        out = render(
            **scene.gaussians.render_inputs(), viewmats=torch.linalg.inv(poses).float(), camera=principal
        )
    ranges = (out.depth / out.alpha).reshape(-1).double().numpy()
    g = Gaussians.from_state(scene.gaussians.state())
    state = SlamState(
        cfg, EventData.from_sequence(seq, cfg.data), Trajectory(scene.frames_us, scene.poses), g,
        torch.Generator().manual_seed(0), BrightnessAnchor(0.0),
    )  # fmt: skip
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

"""The guards inside the mapping stage: each failure is constructed on the known synthetic scene, shown
to persist without the guard and to be gone with it."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.slam.gaussians import PARAM_NAMES, Gaussians, opacity_logit  # noqa: E402
from evgs.slam.guards import surface_brightness  # noqa: E402
from evgs.slam.stages import map_window, render_knots, set_brightness_reference  # noqa: E402
from test_slam_stages import config, gt_state, synth  # noqa: E402, F401

K = 5  # mapping after tracking chunk K: knots 0..K+1


def with_blocker(g: Gaussians, T_wc: torch.Tensor, depth: float) -> Gaussians:
    """``g`` plus one opaque Gaussian ``depth`` in front of the camera ``T_wc``, on its optical axis."""
    centre = (T_wc[:3, :3] @ torch.tensor([0.0, 0.0, depth]).double() + T_wc[:3, 3]).float()
    rows = {
        "means": centre[None],
        "log_scales": torch.full((1, 3), float(torch.log(torch.tensor(0.06)))),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        "opacity_logits": torch.tensor([opacity_logit(0.99)]),
        "colors": torch.tensor([[0.5]]),
    }
    return Gaussians(*(torch.cat([g[k].detach(), rows[k]]) for k in PARAM_NAMES))


def covered(state) -> float:
    """Fraction of the newest view that is (nearly) opaque."""
    return float((render_knots(state, [K + 1]).alpha[0] > 0.95).float().mean())


@pytest.mark.parametrize("guarded", [False, True])
def test_blocker_in_front_of_the_camera(synth, guarded):  # noqa: F811
    _, scene = synth
    sets = ["mapping.num_opti_steps_for_BA=10", "mapping.max_new_gaussians=0", "economy.coarse_factor=1"]
    if not guarded:
        sets += ["guards.near_margin=0", "guards.max_footprint=1000"]
    clean = gt_state(synth, config(*sets), K + 2)
    baseline = covered(clean)
    g = with_blocker(scene.gaussians, torch.as_tensor(scene.poses[K + 1]), 0.04)
    state = gt_state(synth, config(*sets), K + 2, g)
    assert covered(state) > baseline + 0.3  # the blocker hides a large part of the view
    record = map_window(state, K)
    if guarded:
        assert record.pruned_blockers >= 1
        assert covered(state) < baseline + 0.05
    else:
        assert record.pruned_blockers == 0
        assert covered(state) > baseline + 0.15  # the event loss alone wears it down only slowly


def brightness(state) -> float:
    out = render_knots(state, list(range(K + 2)))
    return float(surface_brightness(out.color, out.alpha))


@pytest.mark.parametrize("weight", [0.0, 1.0])
def test_brightness_drift_is_pulled_back_by_the_anchor(synth, weight):  # noqa: F811
    """The event loss compares log-intensity differences, blind to a global brightness factor: a scene
    that brightened (as under opacity resets) stays bright without the anchor and returns with it."""
    sets = [
        "mapping.num_opti_steps_for_BA=40", "mapping.max_new_gaussians=0", "economy.coarse_factor=1",
        "gaussians.colors_lr=0.01", "strategy.reset_every=10", f"guards.brightness_weight={weight}",
        "loss.event_loss=l1",  # the paper's loss (log(I + eps) makes the MSE slightly brightness-aware)
    ]  # fmt: skip
    state = gt_state(synth, config(*sets), K + 2)
    state.anchor.weight = weight
    set_brightness_reference(state)
    b0 = brightness(state)
    with torch.no_grad():
        state.gaussians["colors"].mul_(1.25).clamp_(max=1.0)
    drifted = brightness(state) / b0 - 1
    assert drifted > 0.15
    map_window(state, K)
    after = brightness(state) / b0 - 1
    if weight == 0:
        assert after > 0.6 * drifted, (drifted, after)  # mostly kept: only eps and the clamp see it
    else:
        assert abs(after) < 0.4 * drifted, (drifted, after)

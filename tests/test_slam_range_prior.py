"""The range meter inside the optimisation (``scale.range_weight``, ``scale.rate_weight``) on a scene whose
truth is known."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.config import load_config  # noqa: E402
from evgs.render import render  # noqa: E402
from evgs.slam.gaussians import Gaussians  # noqa: E402
from evgs.slam.guards import BrightnessAnchor  # noqa: E402
from evgs.slam.lie import se3_exp, se3_inverse, se3_log  # noqa: E402
from evgs.slam.metric_scale import apply_scale  # noqa: E402
from evgs.slam.range_prior import (  # noqa: E402
    HUBER,
    RangePrior,
    closing_residuals,
    huber,
    huber_weights,
    meter_advance,
    meter_jumps,
    principal_camera,
)
from evgs.slam.run_dir import range_meter_jumps  # noqa: E402
from evgs.slam.stages import track  # noqa: E402
from evgs.slam.state import SlamState  # noqa: E402
from evgs.slam.trajectory import Trajectory  # noqa: E402
from evgs.slam.windows import EventData  # noqa: E402
from slam_synth import make_sequence  # noqa: E402

UNIT = 2.5  # metres per map unit of the states the tests build


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq") / "synth")


def state_with_meter(synth, *sets: str) -> SlamState:
    """The GT scene and knots in map units (shrunk by ``UNIT``), the sequence given a perfect range
    meter (the metric scene's depth on the principal ray at the frames), the prior built as a run
    builds it."""
    seq, scene = synth
    with torch.no_grad():
        viewmats = torch.linalg.inv(torch.as_tensor(scene.poses)).float()
        out = render(
            **scene.gaussians.render_inputs(), viewmats=viewmats, camera=principal_camera(seq.camera)
        )
    metres = (out.depth / out.alpha).reshape(-1).double().numpy()
    cfg = load_config("synthetic/tiny", ["data.event_contrast=0.2", "gaussians.bounding_size=1.0", *sets])
    data = EventData.from_sequence(seq, cfg.data)
    data = dataclasses.replace(data, ranges=(scene.frames_us.copy(), metres))
    prior = RangePrior.for_run(cfg, data)
    if prior is not None and prior.seed_unit is not None:  # the scene's own unit, as if it had been seeded so
        prior = dataclasses.replace(prior, seed_unit=UNIT)
    state = SlamState(
        cfg, data, Trajectory(scene.frames_us, scene.poses), Gaussians.from_state(scene.gaussians.state()),
        torch.Generator().manual_seed(0), BrightnessAnchor(0.0), range_prior=prior,
    )  # fmt: skip
    apply_scale(state, 1 / UNIT)
    return state


@torch.no_grad()
def knot_central_differences(traj: Trajectory, knot: int, f: Callable[[], float], eps: float) -> torch.Tensor:
    """(6,) central differences of ``f`` along each coordinate of ``knot``'s increment."""
    numeric = torch.zeros(6, dtype=torch.float64)
    base = traj.delta[knot].clone()
    for i in range(6):
        values = []
        for sign in (1.0, -1.0):
            traj.delta[knot] = base
            traj.delta[knot, i] += sign * eps
            values.append(f())
        numeric[i] = (values[0] - values[1]) / (2 * eps)
    traj.delta[knot] = base
    return numeric


def test_no_prior_without_weight_and_a_clear_error_without_a_meter(synth):
    seq, _ = synth
    cfg = load_config("synthetic/tiny", ["data.event_contrast=0.2"])
    data = EventData.from_sequence(seq, cfg.data)
    assert RangePrior.for_run(cfg, data) is None  # range_weight = 0: the meter only scales the outputs
    weighted = load_config("synthetic/tiny", ["data.event_contrast=0.2", "scale.range_weight=1"])
    with pytest.raises(ValueError, match="range.csv"):
        RangePrior.for_run(weighted, data)
    with pytest.raises(Exception, match="range_weight"):
        load_config("synthetic/tiny", ["scale.range_weight=-1"])


def test_the_unit_is_the_median_ratio_and_ignores_what_is_not_a_range(synth):
    state = state_with_meter(synth, "scale.range_weight=1")
    prior, traj = state.range_prior, state.traj
    assert prior.unit(state.gaussians, traj) == pytest.approx(UNIT, rel=1e-4)
    # Samples that are not ranges (no return, zero) are dropped; a minority of wrong ones (an edge, a
    # part the map lacks) does not move the median.
    t, r = state.data.ranges
    bad = r.copy()
    bad[3], bad[5], bad[1] = np.nan, 0.0, 3 * r[1]
    noisy = RangePrior.for_run(state.cfg, dataclasses.replace(state.data, ranges=(t, bad)))
    assert len(noisy.t_us) == len(t) - 2
    assert noisy.unit(state.gaussians, traj) == pytest.approx(UNIT, rel=1e-4)
    # Before the trajectory reaches a sample, or where the map covers no principal ray: no unit yet.
    assert prior.unit(state.gaussians, Trajectory(t[:1] - 10**6, traj.knots()[:1].detach())) is None
    assert dataclasses.replace(prior, min_alpha=1.1).unit(state.gaussians, traj) is None


def test_residuals_vanish_at_the_truth_and_measure_relative_error(synth):
    state = state_with_meter(synth, "scale.range_weight=1")
    prior, traj = state.range_prior, state.traj
    t, metres = prior.samples(int(traj.t_us[0]), int(traj.t_us[-1]))
    assert len(t) == len(traj)
    with torch.no_grad():
        vm = traj.viewmats_at(t)
        assert float(prior.residuals(state.gaussians, vm, metres, UNIT).abs().max()) < 1e-4
        # A meter reading 10 % long at the same unit: every residual is 1/1.1 − 1.
        q = prior.residuals(state.gaussians, vm, metres * 1.1, UNIT)
        assert torch.allclose(q, torch.tensor(1 / 1.1 - 1), atol=1e-4)
        # The penalty uses the samples of the span asked for, inside the trajectory; none is 0.
        long = dataclasses.replace(prior, ranges=prior.ranges * 1.1)
        expected = float(huber(torch.tensor(1 / 1.1 - 1)))
        assert float(long.penalty(state.gaussians, traj, int(t[2]), int(t[3]), UNIT)) == pytest.approx(
            expected, rel=1e-3
        )
        assert float(long.penalty(state.gaussians, traj, int(t[-1]) + 1, int(t[-1]) + 10**6, UNIT)) == 0.0
        assert float(long.penalty(state.gaussians, traj, int(t[0]), int(t[-1]), None)) == 0.0
        # Views whose principal ray the map does not cover are not used.
        uncovered = dataclasses.replace(prior, min_alpha=1.1)
        assert bool(torch.isnan(uncovered.residuals(state.gaussians, vm, metres, UNIT)).all())
        assert float(uncovered.penalty(state.gaussians, traj, int(t[0]), int(t[-1]), UNIT)) == 0.0


def approach(n: int, step: float, turn: float = 0.0) -> torch.Tensor:
    """(n, 4, 4) camera-to-world poses ``step`` apart along the first camera's optical axis (+z), each
    also turned by ``turn`` rad about its y axis: an approach to the plane z = 10 from z = 0."""
    twist = torch.tensor([0.0, 0.0, step, 0.0, turn, 0.0], dtype=torch.float64)
    return se3_exp(torch.arange(n, dtype=torch.float64)[:, None] * twist[None])


def test_closing_rate_vanishes_on_an_approach_and_measures_a_wrong_speed():
    poses = approach(5, 0.5)
    axes = poses[:, :3, 2]
    metres = 10.0 - 0.5 * np.arange(5)  # the plane z = 10 along the optical axis
    assert float(closing_residuals(poses, axes, metres, 1.0).abs().max()) < 1e-12
    # In map units of 2 m each: the same motion, the unit says how far it went.
    shrunk = poses.clone()
    shrunk[:, :3, 3] /= 2
    assert float(closing_residuals(shrunk, axes, metres, 2.0).abs().max()) < 1e-12
    # The approach at half its speed misses half of each decrease, relative to the range after it.
    q = closing_residuals(approach(5, 0.25), axes, metres, 1.0)
    assert torch.allclose(q, torch.as_tensor(-0.25 / metres[1:]))
    # Only the advance along the given axes counts: turned 90° they see none of it.
    turned = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64).expand(5, 3)
    assert torch.allclose(closing_residuals(poses, turned, metres, 1.0), torch.as_tensor(-0.5 / metres[1:]))
    # Sideways past the plane, the range stays: nothing to correct. A batch of trials at once.
    sideways = poses.clone()
    sideways[:, 0, 3] = torch.arange(5.0, dtype=torch.float64)
    sideways[:, 2, 3] = 0.0
    batch = closing_residuals(torch.stack([sideways, poses]), axes, np.full(5, 10.0), 1.0)
    assert batch.shape == (2, 4)
    assert float(batch[0].abs().max()) < 1e-12
    assert torch.allclose(batch[1], torch.tensor(0.5 / 10, dtype=torch.float64))


def test_meter_jumps_are_steps_no_smooth_advance_makes():
    # The simulated orbit's start: the ray slides off the dish onto the bus 0.37 m behind it.
    orbit = np.array([4.989, 4.9887, 5.3606, 5.3595, 5.3579, 5.3558, 5.3533])
    assert meter_jumps(orbit).tolist() == [False, True, False, False, False, False]
    # A descent whose closing speed doubles (1.5 → 3 % of the range per sample): steady throughout.
    r = [10.0]
    for rate in np.linspace(0.015, 0.03, 12):
        r.append(r[-1] * (1 - rate))
    assert not meter_jumps(np.array(r)).any()
    # One sample on an antenna in front: both pairs around it jump, the rest are steady.
    spike = 8.0 - 0.1 * np.arange(9)
    spike[4] -= 0.5
    assert np.flatnonzero(meter_jumps(spike)).tolist() == [3, 4]
    # A run's metrics count them over the meter's valid samples (a miss, NaN, is no sample).
    t = np.arange(len(orbit) + 1, dtype=np.int64) * 100_000
    with_miss = np.insert(orbit, 3, np.nan)
    assert range_meter_jumps(SimpleNamespace(data=SimpleNamespace(ranges=(t, with_miss)))) == 1
    assert range_meter_jumps(SimpleNamespace(data=SimpleNamespace(ranges=None))) == 0
    # One pair has nothing to compare with; of two that disagree, neither can be trusted.
    assert meter_jumps(np.array([5.0, 6.0])).tolist() == [False]
    assert meter_jumps(np.array([5.0, 5.0, 6.0])).tolist() == [True, True]
    assert meter_jumps(np.array([5.0])).tolist() == []


def test_closing_rate_pairs_reach_back_one_sample_inside_the_trajectory(synth):
    state = state_with_meter(synth, "scale.rate_weight=1")
    prior, traj = state.range_prior, state.traj
    t = prior.t_us
    # A span holding one sample pairs it with the one before; at the trajectory's start there is none.
    got, _, _ = prior.rate_samples(int(t[3]), int(t[4]) - 1, traj)
    assert list(got) == [t[2], t[3]]
    got, _, _ = prior.rate_samples(int(t[0]), int(t[1]) - 1, traj)
    assert list(got) == [t[0]]
    assert float(prior.rate_penalty(traj, int(t[0]), int(t[1]) - 1)) == 0.0
    # Nothing in the span: nothing, not the sample before it.
    got, _, _ = prior.rate_samples(int(t[-1]) + 1, int(t[-1]) + 10**6, traj)
    assert len(got) == 0
    short = Trajectory(t[:3], traj.knots()[:3].detach())
    got, _, _ = prior.rate_samples(int(t[2]), int(t[-1]), short)
    assert list(got) == [t[1], t[2]]


def test_closing_rate_gradient_matches_autograd_and_finite_differences(synth):
    """The penalty's gradient w.r.t. a knot's increment against central differences of the penalty with
    the axes held where the increment has them (as the penalty holds them); the residuals' against
    float64 autograd's numerical check."""
    state = state_with_meter(synth, "scale.rate_weight=1")
    prior, traj = state.range_prior, state.traj
    poses = traj.pose_at(prior.t_us[:4]).detach().requires_grad_(True)
    axes = poses.detach()[:, :3, 2].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p, a: closing_residuals(p, a, prior.ranges[:4], UNIT), (poses, axes)
    )
    with torch.no_grad():
        traj.delta[3] = torch.tensor([0.01, -0.02, 0.05, 0.01, 0.0, -0.01], dtype=traj.delta.dtype)
    traj.set_trainable([3])
    lo, hi = int(traj.t_us[2]), int(traj.t_us[4])
    traj.delta.grad = None
    prior.rate_penalty(traj, lo, hi).backward()
    analytic = traj.delta.grad[3].double().clone()
    t, metres, _ = prior.rate_samples(lo, hi, traj)
    with torch.no_grad():
        axes = traj.pose_at(t)[:, :3, 2].clone()

    def penalty() -> float:
        return float(huber(closing_residuals(traj.pose_at(t), axes, metres, UNIT)).mean())

    numeric = knot_central_differences(traj, 3, penalty, 1e-4)
    assert float(analytic.norm()) > 1e-4
    assert torch.allclose(analytic, numeric, rtol=0.02, atol=0.01 * float(numeric.norm())), (
        analytic,
        numeric,
    )


def test_closing_rate_unit_is_set_by_the_seeding(synth):
    seq, _ = synth
    cfg = load_config(
        "synthetic/tiny", ["data.event_contrast=0.2", "scale.rate_weight=1", "gaussians.init_depth=4"]
    )
    data = EventData.from_sequence(seq, cfg.data)
    t = data.frames_us.astype(np.int64)
    metres = np.linspace(10.0, 8.0, len(t))
    before = np.concatenate([[t[0] - 1000], t[2:]]), np.concatenate([[99.0], metres[2:]])
    prior = RangePrior.for_run(cfg, dataclasses.replace(data, ranges=before))
    # The first reading at or after the first frame is the seeding's depth, 4 map units.
    assert prior.seed_unit == pytest.approx(metres[2] / 4)
    boxed = load_config(
        "synthetic/tiny", ["data.event_contrast=0.2", "scale.rate_weight=1", "gaussians.init_depth=0"]
    )
    with pytest.raises(ValueError, match="init_depth"):
        RangePrior.for_run(boxed, dataclasses.replace(data, ranges=(t, metres)))
    with pytest.raises(ValueError, match="first frame"):
        RangePrior.for_run(cfg, dataclasses.replace(data, ranges=(t[:1] - 1000, metres[:1])))


def test_meter_advance_is_the_closing_rate_per_chunk_at_the_seeding_unit(synth):
    seq, _ = synth
    cfg = load_config("synthetic/tiny", ["data.event_contrast=0.2", "gaussians.init_depth=4"])
    data = EventData.from_sequence(seq, cfg.data)
    t0, chunk = int(data.frames_us[0]), float(np.diff(data.frames_us).mean())
    # Two samples per chunk over the first three chunks and beyond, closing 0.05 m per sample: 0.1 m per
    # chunk, 10 m at the first frame (4 map units, so 2.5 m per unit).
    t = t0 + np.arange(12) * chunk / 2
    metres = 10.0 - 0.05 * np.arange(12)
    got = meter_advance(cfg, dataclasses.replace(data, ranges=(t, metres)), 3)
    assert got == pytest.approx(0.1 / 2.5)
    # A step where the ray crosses an edge onto a nearer surface says nothing about the advance: left out.
    stepped = metres - np.where(np.arange(12) >= 3, 0.5, 0.0)
    assert meter_advance(cfg, dataclasses.replace(data, ranges=(t, stepped)), 3) == pytest.approx(0.1 / 2.5)
    # A meter that does not close: no advance.
    assert meter_advance(cfg, dataclasses.replace(data, ranges=(t, np.full(12, 10.0))), 3) == 0.0
    with pytest.raises(ValueError, match="search_meter_advance needs the sequence's range meter"):
        meter_advance(cfg, dataclasses.replace(data, ranges=None), 3)


def test_huber_is_quadratic_then_linear_and_its_irls_weights_agree():
    q = torch.tensor([-0.3, -HUBER, -0.01, 0.0, 0.02, HUBER, 0.2], dtype=torch.float64, requires_grad=True)
    h = huber(q)
    small = q.abs() <= HUBER
    assert torch.allclose(h[small], q[small] ** 2)
    assert torch.allclose(h[~small], HUBER * (2 * q[~small].abs() - HUBER))
    (grad,) = torch.autograd.grad(h.sum(), q)
    # The Gauss–Newton gradient of Σ w·q² with the IRLS weights is the true gradient.
    assert torch.allclose(2 * huber_weights(q.detach()) * q.detach(), grad)


def test_penalty_gradient_matches_finite_differences(synth):
    """The penalty's gradient w.r.t. a knot's increment (through the rasterizer's depth and alpha
    gradients) against central differences of the penalty itself."""
    state = state_with_meter(synth, "scale.range_weight=1")
    prior, traj = state.range_prior, state.traj
    with torch.no_grad():  # move knot 3 off the truth so the penalty has a slope
        traj.delta[3] = torch.tensor([0.01, -0.02, 0.05, 0.01, 0.0, -0.01], dtype=traj.delta.dtype)
    traj.set_trainable([3])
    lo, hi = int(traj.t_us[2]), int(traj.t_us[4])
    traj.delta.grad = None
    prior.penalty(state.gaussians, traj, lo, hi, UNIT * 1.05).backward()
    # The poses only: the map is the events' to shape.
    assert all(p.grad is None or not bool(p.grad.any()) for p in state.gaussians.params.values())
    analytic = traj.delta.grad[3].double().clone()
    numeric = knot_central_differences(
        traj, 3, lambda: float(prior.penalty(state.gaussians, traj, lo, hi, UNIT * 1.05)), 1e-3
    )
    assert float(analytic.norm()) > 1e-3
    assert torch.allclose(analytic, numeric, rtol=0.05, atol=0.02 * float(numeric.norm())), (
        analytic,
        numeric,
    )


SOLVERS = pytest.mark.parametrize(
    "solver_sets",
    [("tracking.solver=lm", "tracking.num_opti_steps=8", "tracking.lm_jacobian=central"),
     ("tracking.solver=lm", "tracking.num_opti_steps=8", "tracking.lm_jacobian=analytic"),
     ("tracking.solver=adam", "tracking.num_opti_steps=40", "trajectory.pose_lr=3e-3")],
    ids=["lm-central", "lm-analytic", "adam"],
)  # fmt: skip
K = 4  # the knot the tracking tests start from: they track knot K + 1


def moved_by_meter(
    synth, solver_sets, term: str, weight: float, short: Callable[[np.ndarray], np.ndarray]
) -> float:
    """How far tracking moves knot ``K + 1``, started at the truth, along its optical axis (a fraction of
    the range) when the meter reads ``short(metres)`` and its ``term`` weighs ``weight``."""
    sets = [
        *solver_sets,
        f"{term}={weight}",
        "economy.coarse_factor=1",
        "tracking.mask_alpha=-1",
        "tracking.velocity_prior=0",  # the range term alone
    ]
    state = state_with_meter(synth, *sets)
    t, metres = state.data.ranges
    if weight > 0:
        state.range_prior = dataclasses.replace(state.range_prior, ranges=short(metres.copy()))
    T_gt = state.traj.knots()[K + 1].detach().clone()
    state.traj = Trajectory(t[: K + 1], state.traj.knots()[: K + 1].detach())
    track(state, K, pose=T_gt)
    xi = se3_log(se3_inverse(T_gt.double()) @ state.traj.knots()[K + 1].detach().double())
    return float(xi[2]) * UNIT / metres[K + 1]


@pytest.mark.parametrize("term", ["scale.range_weight", "scale.rate_weight"])
@SOLVERS
def test_tracking_follows_the_meter_along_the_optical_axis(synth, solver_sets, term):
    """The meter reads each frame from the newest on 1.5 % more short of the truth the events were made
    from (a ramp, not a jump: meter_jumps leaves a step out): with a heavy weight on either of its terms
    tracking moves the new knot most of the way to the meter along its optical axis; without them it
    stays at the truth. So both solvers minimise both terms."""

    def ramp(m: np.ndarray) -> np.ndarray:
        m[K + 1 :] *= 1 - 0.015 * np.arange(1, len(m) - K)
        return m

    assert abs(moved_by_meter(synth, solver_sets, term, 0.0, ramp)) < 0.002
    assert 0.01 < moved_by_meter(synth, solver_sets, term, 1000.0, ramp) < 0.02  # most of the way


@SOLVERS
def test_tracking_ignores_a_jump_of_the_meter(synth, solver_sets):
    """From the newest frame on the meter reads 5 % short, as when its ray leaves an edge for a surface
    in front: a step no advance explains. The closing rate leaves that pair out, so even at a heavy
    weight tracking keeps the knot at the truth."""

    def step(m: np.ndarray) -> np.ndarray:
        m[K + 1 :] *= 0.95
        return m

    assert abs(moved_by_meter(synth, solver_sets, "scale.rate_weight", 1000.0, step)) < 0.002

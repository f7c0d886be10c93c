"""The SLAM stages on a tiny synthetic sequence whose scene and poses are known (``slam_synth``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.config import ConfigError, load_config  # noqa: E402
from evgs.slam import pose_solver  # noqa: E402
from evgs.slam.gaussians import PARAM_NAMES, Gaussians  # noqa: E402
from evgs.slam.guards import BrightnessAnchor  # noqa: E402
from evgs.slam.lie import se3_exp, se3_inverse, se3_log  # noqa: E402
from evgs.slam.loss import depth_variation, total_variation  # noqa: E402
from evgs.slam.optimize import Convergence, StageSpec, loss_step, lr_boost, set_lr_boost  # noqa: E402
from evgs.slam.pipeline import new_state  # noqa: E402
from evgs.slam.pose_solver import prior_curvature, prior_weight  # noqa: E402
from evgs.slam.seeding import initial_gaussians, seeding_weights  # noqa: E402
from evgs.slam.stages import global_ba, map_window, track  # noqa: E402
from evgs.slam.state import SlamState  # noqa: E402
from evgs.slam.trajectory import Trajectory  # noqa: E402
from evgs.slam.windows import EventData, Windows, scaled_camera  # noqa: E402
from slam_synth import CONTRAST, make_sequence  # noqa: E402


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq") / "synth")


def config(*sets: str):
    base = ["data.event_contrast=0.2", "gaussians.bounding_size=1.0", "economy.patience=0"]
    return load_config("synthetic/tiny", [*base, *sets])


def gt_state(synth, cfg, n_knots: int, gaussians: Gaussians | None = None) -> SlamState:
    seq, scene = synth
    traj = Trajectory(scene.frames_us[:n_knots], scene.poses[:n_knots])
    g = Gaussians.from_state((gaussians or scene.gaussians).state())
    data = EventData.from_sequence(seq, cfg.data)
    return SlamState(cfg, data, traj, g, torch.Generator().manual_seed(0), BrightnessAnchor(0.0))


def record_windows(monkeypatch) -> list[Windows]:
    """Every batch of windows the stages draw from now on, in order (cleared by the caller between stages)."""
    seen: list[Windows] = []
    take = EventData.windows

    def spy(self, sampler, batch, factor=1):
        win = take(self, sampler, batch, factor)
        seen.append(win)
        return win

    monkeypatch.setattr(EventData, "windows", spy)
    return seen


def ranges(seen: list[Windows]) -> list[tuple[int, int]]:
    """``(start, end)`` event indices of every window in ``seen``."""
    return [(int(s), int(e)) for win in seen for s, e in zip(win.starts, win.ends, strict=True)]


def lengths(seen: list[Windows]) -> list[int]:
    return [e - s for s, e in ranges(seen)]


def pose_error(T: torch.Tensor, T_gt: np.ndarray) -> tuple[float, float]:
    """(translation, rotation angle) of ``T_gt⁻¹ T``."""
    xi = se3_log(se3_inverse(torch.as_tensor(T_gt)) @ T.detach().double())
    return float(xi[:3].norm()), float(xi[3:].norm())


def test_event_data_chunks_and_coarse_frames(synth):
    seq, scene = synth
    data = EventData.from_sequence(seq, config().data)
    assert data.n_chunks == len(scene.frames_us) - 1
    s, e = data.span(2, 5)
    assert (s, e) == (data.chunks[2, 0], data.chunks[4, 1])
    t = data.events.t
    assert t[s] >= scene.frames_us[2] and t[e - 1] < scene.frames_us[5]
    full = data.frames_of(np.array([s]), np.array([e]))[0]
    assert float(full.sum()) / CONTRAST == pytest.approx(int(data.events.p[s:e].sum()), abs=1e-3)
    half = data.frames_of(np.array([s]), np.array([e]), 2)[0]
    assert half.shape == (30, 40)
    assert torch.allclose(half, full.reshape(30, 2, 40, 2).sum((1, 3)) / 4, atol=1e-6)
    cam = scaled_camera(data.camera, 2)
    assert (cam.width, cam.height, cam.fx) == (40, 30, 35.0)
    # Coarse pixel 7 gathers fine pixels 14 and 15 (OpenCV centres): one ray through fine 14.5 and coarse 7.
    for fine, coarse in ((data.camera.cx, cam.cx), (data.camera.cy, cam.cy)):
        assert (14.5 - fine) / data.camera.fx == pytest.approx((7.0 - coarse) / cam.fx, abs=1e-12)


def test_span_with_min_extends_sparse_chunks(synth):
    seq, _ = synth
    data = EventData.from_sequence(seq, config().data)
    s, e = data.chunks[3]
    need = int(e - s) + 1
    data = EventData.from_sequence(
        seq, config(f"data.min_n_winsize={need}", f"data.max_n_winsize={need}").data
    )
    assert data.span_with_min(3, 4) == (data.chunks[2, 0], e)


def test_convergence_stops_on_plateau_only():
    c = Convergence(patience=3, min_rel_change=0.01)
    stops = [c.update(v) for v in [10, 9, 8, 7, 6, 5, 5, 5, 5, 5, 5]]
    assert stops.index(True) == 10  # blocks (5, 5, 5) → (5, 5, 5); (6, 5, 5) → (5, 5, 5) is 6 % better
    off = Convergence(0, 0.5)
    assert not any(off.update(1.0) for _ in range(10))


def test_lr_boost_decays_exponentially_from_the_boost_to_the_configured_rates():
    spec = StageSpec("init", 5, 11, (0, 10), 1, 0, [1], [0, 1], True, lr_boost=100.0)
    assert [lr_boost(spec, it) for it in (0, 5, 10)] == pytest.approx([100.0, 10.0, 1.0])
    assert lr_boost(dataclasses.replace(spec, lr_boost=1.0), 0) == 1.0
    p = torch.nn.Parameter(torch.zeros(2))
    opt = torch.optim.Adam([p], lr=1e-3)
    set_lr_boost([opt, None], 10.0)
    set_lr_boost([opt], 2.0)  # relative to the rate at creation, not compounding
    assert opt.param_groups[0]["lr"] == pytest.approx(2e-3)


def test_event_seeding_needs_the_depth_range_ahead_of_the_camera(synth):
    seq, _ = synth
    cfg = config("gaussians.init_seeding=events", "gaussians.init_depth=0.5", "gaussians.bounding_size=1.0")
    with pytest.raises(ValueError, match="init_depth"):
        initial_gaussians(cfg.gaussians, EventData.from_sequence(seq, cfg.data), 3, torch.Generator())
    cfg = config("gaussians.init_seeding=events", "gaussians.init_depth=2.5", "gaussians.num_init=300")
    data = EventData.from_sequence(seq, cfg.data)
    cam = data.camera
    for first in (0, data.n_chunks - 3):  # the first chunks (a run's), or later ones (benches/slam_oracle.py)
        g = initial_gaussians(cfg.gaussians, data, 3, torch.Generator().manual_seed(0), first=first)
        means = g["means"].detach()
        z = means[:, 2]
        assert len(g) == 300 and float(z.min()) >= 1.5 and float(z.max()) <= 3.5
        active = data.activity(data.span(first, first + 3)) >= cfg.gaussians.init_min_events
        u = (means[:, 0] / z * cam.fx + cam.cx + 0.5).floor().long()  # OpenCV centres: pixel i spans
        v = (means[:, 1] / z * cam.fy + cam.cy + 0.5).floor().long()  # [i - 0.5, i + 0.5)
        assert bool(active[v, u].all())
        # new_state seeds this map: a run at first = 0, benches/slam_oracle.py at --start
        seeded = new_state(dataclasses.replace(cfg, seed=0), data, first=first).gaussians
        assert torch.equal(seeded["means"].detach(), means)
    with pytest.raises(ValueError, match="'box' seeding has no slab"):
        box = config("gaussians.init_seeding=box", "gaussians.init_tilt_deg=5")
        initial_gaussians(box.gaussians, data, 3, torch.Generator())


def test_the_silhouettes_inside_is_seeded_when_its_outline_is_closed_within_the_fill_gap():
    # A square's outline (3 events per pixel) with a 4-pixel break in its top edge, and a lone noise pixel.
    counts = torch.zeros(40, 40)
    counts[10, 10:31] = counts[30, 10:31] = counts[10:31, 10] = counts[10:31, 30] = 3.0
    counts[10, 18:22] = 0.0
    counts[2, 2] = 1.0
    inside = torch.zeros(40, 40, dtype=torch.bool)
    inside[11:30, 11:30] = inside[10, 18:22] = True  # the break closes too

    plain = seeding_weights(counts, 2, 0)
    assert torch.equal(plain, torch.where(counts >= 2, counts, 0.0))  # below min_events: not seeded
    assert torch.equal(seeding_weights(counts, 2, 2), plain)  # the break is wider than the gap
    filled = seeding_weights(counts, 2, 4)
    assert bool((filled[inside] == 2.0).all())  # the inside, at the weight of min_events
    assert torch.equal(filled[~inside], plain[~inside])  # the outline and the outside unchanged
    with pytest.raises(Exception, match="init_fill_gap"):
        config("gaussians.init_fill_gap=-1")


def reprojection_px(T: torch.Tensor, T_gt: torch.Tensor, points: torch.Tensor, fx: float) -> float:
    """Mean image displacement (px) of ``points`` seen from ``T`` instead of ``T_gt``: the error the
    event loss observes (lateral translation and rotation trade off in a narrow view)."""
    uv = []
    for pose in (T, T_gt):
        T_cw = se3_inverse(pose.detach().double())
        p = points.double() @ T_cw[:3, :3].T + T_cw[:3, 3]
        uv.append(fx * p[:, :2] / p[:, 2:])
    return float((uv[0] - uv[1]).norm(dim=1).mean())


@pytest.mark.parametrize(
    "solver_sets",
    [
        ("tracking.solver=adam", "tracking.num_opti_steps=60", "trajectory.pose_lr=3e-3"),
        # Curvature: a few steps suffice. The perturbed start is the prediction the prior pulls towards.
        (
            "tracking.solver=lm",
            "tracking.num_opti_steps=8",
            "tracking.velocity_prior=0",
            "tracking.lm_jacobian=central",
        ),
        (
            "tracking.solver=lm",
            "tracking.num_opti_steps=8",
            "tracking.velocity_prior=0",
            "tracking.lm_jacobian=analytic",
        ),
    ],
    ids=["adam", "lm-central", "lm-analytic"],
)
def test_tracking_recovers_a_perturbed_pose(synth, solver_sets):
    _, scene = synth
    # The reference's alpha mask: the solvers are compared on the pixels the map covers.
    cfg = config(*solver_sets, "economy.coarse_factor=1", "tracking.mask_alpha=0.8")
    k = 4
    state = gt_state(synth, cfg, k + 1)
    T_gt = torch.as_tensor(scene.poses[k + 1])
    start = T_gt @ se3_exp(torch.tensor([0.05, -0.04, 0.03, 0.02, -0.03, 0.02]).double())
    track(state, k, pose=start)
    est = state.traj.knots()[k + 1]
    points, fx = scene.gaussians["means"].detach(), state.data.camera.fx
    before, after = reprojection_px(start, T_gt, points, fx), reprojection_px(est, T_gt, points, fx)
    assert before > 2.0 and after < 0.2 * before, (before, after)
    # What the 80×60 view leaves traded (rotation against lateral translation) falls less: Adam's rotation
    # error ends at 0.44–0.63 of the start's over 60–120 steps, whichever pixel convention renders.
    assert pose_error(est, T_gt.numpy())[1] < 0.7 * pose_error(start, T_gt.numpy())[1]
    # The earlier knots are untouched.
    assert torch.equal(state.traj.knots()[: k + 1], torch.as_tensor(scene.poses[: k + 1]))


@pytest.mark.parametrize("solver", ["adam", "lm"])
def test_tracking_windows_reach_back_span_frames_and_end_at_the_new_frame(synth, monkeypatch, solver):
    """``tracking.span_frames = n``: every tracking window ends at the new chunk's last event and starts
    at most n chunks back, some beyond the new chunk; with the longer baselines tracking still recovers
    the perturbed pose (Adam less of it in its fixed steps). 1 keeps the new chunk alone (extended only
    to data.min_n_winsize)."""
    _, scene = synth
    k, n = 5, 3
    T_gt = torch.as_tensor(scene.poses[k + 1])
    start = T_gt @ se3_exp(torch.tensor([0.05, -0.04, 0.03, 0.02, -0.03, 0.02]).double())
    drawn = record_windows(monkeypatch)
    sets = ("economy.coarse_factor=1", "tracking.mask_alpha=0.8", "tracking.velocity_prior=0")
    steps = ("tracking.num_opti_steps=8",) if solver == "lm" else ()
    for frames in (1, n):
        drawn.clear()
        cfg = config(f"tracking.solver={solver}", *steps, *sets, f"tracking.span_frames={frames}")
        state = gt_state(synth, cfg, k + 1)
        track(state, k, pose=start)
        chunks = state.data.chunks
        seen = ranges(drawn)
        lo = chunks[k + 1 - frames, 0] if frames > 1 else state.data.span_with_min(k, k + 1)[0]
        assert seen and all(s >= lo and e <= chunks[k, 1] for s, e in seen), frames
        if frames > 1:
            assert all(e == chunks[k, 1] for _, e in seen)
            assert min(s for s, _ in seen) < chunks[k - 1, 0]  # baselines of more than two frames occur
        err = pose_error(state.traj.knots()[k + 1], T_gt.numpy())[1]
        # Adam's 30 fixed-size steps on the longer windows correct less of the start than LM's 8
        assert err < (0.5 if solver == "lm" else 0.8) * pose_error(start, T_gt.numpy())[1], (frames, err)
    with pytest.raises(ConfigError, match="tracking.span_frames must be >= 1"):
        config("tracking.span_frames=0")


def test_lm_windows_are_drawn_once_per_frame_and_level(synth, monkeypatch):
    """``tracking.lm_windows = n``: LM draws n windows once per resolution level of a tracked frame and
    steps on them throughout, and still recovers the perturbed pose; 0 draws fresh ones every step."""
    _, scene = synth
    k = 4
    T_gt = torch.as_tensor(scene.poses[k + 1])
    start = T_gt @ se3_exp(torch.tensor([0.05, -0.04, 0.03, 0.02, -0.03, 0.02]).double())
    drawn = record_windows(monkeypatch)
    sets = ("tracking.solver=lm", "tracking.num_opti_steps=20", "tracking.mask_alpha=0.8")
    for windows, coarse, draws in ((2, 1, [2]), (3, 2, [3, 3]), (0, 1, None)):
        drawn.clear()
        cfg = config(*sets, f"tracking.lm_windows={windows}", f"economy.coarse_factor={coarse}")
        state = gt_state(synth, cfg, k + 1)
        record = track(state, k, pose=start)
        if windows:  # however many steps LM takes before it converges
            assert [len(w.starts) for w in drawn] == draws, windows
            widths = [w.frames.shape[-1] for w in drawn]
            assert widths == sorted(set(widths)) and widths[-1] == state.data.camera.width  # coarse first
        else:
            assert [len(w.starts) for w in drawn] == [1] * record.iterations
        err = pose_error(state.traj.knots()[k + 1], T_gt.numpy())[1]
        assert err < 0.5 * pose_error(start, T_gt.numpy())[1], (windows, err)
    with pytest.raises(ConfigError, match="tracking.lm_windows must be >= 0"):
        config("tracking.lm_windows=-1")


def test_lm_on_fixed_windows_keeps_its_linearisation_and_tracks_to_the_same_bits(synth, monkeypatch):
    """On fixed windows (``tracking.lm_windows``) LM keeps the forward-mode linearisation of the step it
    accepted (or of the increment a rejected step failed to leave): one pass per step instead of that
    pass and a plain render, with the very knot that rendering everything again gives."""
    from evgs.slam import pose_solver

    _, scene = synth
    k = 4
    start = torch.as_tensor(scene.poses[k + 1]) @ se3_exp(
        torch.tensor([0.05, -0.04, 0.03, 0.02, -0.03, 0.02]).double()
    )
    cfg = config(
        "tracking.solver=lm", "tracking.num_opti_steps=12", "tracking.lm_windows=2", "economy.coarse_factor=2"
    )
    passes = {"render": 0, "render_pose_jvp": 0}

    def counted(name):
        fn = getattr(pose_solver, name)

        def wrapper(*args, **kwargs):
            passes[name] += 1
            return fn(*args, **kwargs)

        return wrapper

    for name in passes:
        monkeypatch.setattr(pose_solver, name, counted(name))
    knots, counts = [], []
    for keep in (True, False):
        monkeypatch.setattr(pose_solver, "KEEP_LINEARISATION", keep)
        passes.update(render=0, render_pose_jvp=0)
        state = gt_state(synth, cfg, k + 1)
        record = track(state, k, pose=start)
        knots.append(state.traj.knots()[k + 1])
        counts.append((record.iterations, dict(passes)))
    assert torch.equal(knots[0], knots[1])
    (kept_its, kept), (its, fresh) = counts
    assert kept_its == its and kept["render"] == 0 and fresh["render"] > 0
    # one pass per step's trial, and one at each of the two levels' first step (their windows are new)
    assert kept["render_pose_jvp"] <= its + 2 < fresh["render_pose_jvp"] + fresh["render"]


def test_lm_analytic_jacobian_matches_central_differences_of_the_residuals(synth):
    """``tracking.lm_jacobian = "analytic"``: the residuals at the increment equal :func:`residuals`'s,
    and their Jacobian (the trajectory's tangents through the rasterizer's forward mode) matches central
    differences of the residuals on the pixels LM uses. Not on every pixel: a render jumps where a splat
    crosses alpha = 1/255 or its extent's edge (≈ 0.004 in log intensity), which a difference over ±ε
    turns into a spike of 0.002/ε on a share of the pixels that shrinks with ε (2 % at 1e-4, < 1 % at
    1e-5); the analytic Jacobian holds those cut-offs fixed."""
    cfg = config("tracking.solver=lm", "tracking.mask_alpha=0.8", "economy.coarse_factor=1")
    k = 4
    state = gt_state(synth, cfg, k + 2)
    data = state.data
    win = data.windows(data.sampler(data.span(k, k + 1), 3, cfg.data.max_n_winsize), 2, 1)
    delta = torch.tensor([0.01, -0.005, 0.003, 0.002, -0.004, 0.003], dtype=torch.float64)
    eps = 1e-5
    variants = torch.cat([torch.zeros(1, 6), eps * torch.eye(6), -eps * torch.eye(6)]).double()
    lin = pose_solver.linearised(state, k + 1, delta, variants, win, 1, data.span(k, k + 1), None)
    ref = pose_solver.residuals(state, k + 1, delta + variants, win, 1, data.span(k, k + 1), None)
    torch.testing.assert_close(lin.events[0], ref.events[0], rtol=0, atol=1e-6)
    assert torch.equal(lin.alpha[0], ref.alpha[0])
    mask = (ref.alpha[0] > 0.8).all(0)
    fd = ((ref.events[1:7] - ref.events[7:13]) / (2 * eps))[:, mask].double()
    got = lin.jacobian[:, mask].double()
    for d in range(6):
        scale = got[d].abs().max()
        assert scale > 1.0, d
        agree = (got[d] - fd[d]).abs() <= 0.02 * scale
        assert agree.float().mean() > 0.98, (d, agree.float().mean())
        assert (got[d] - fd[d]).abs().median() < 5e-3 * scale, d  # float32 renders differenced over 2e-5


def test_lm_velocity_prior_pulls_towards_the_prediction(synth):
    """``tracking.velocity_prior`` is a pull towards where the knot started (the constant-velocity
    prediction): off, LM recovers the true pose; at weight 1 it stops part-way (the data's curvature and
    the prior's are equal); overwhelming, the knot stays where it started."""
    _, scene = synth
    k = 4
    T_gt = torch.as_tensor(scene.poses[k + 1])
    start = T_gt @ se3_exp(torch.tensor([0.05, -0.04, 0.03, 0.02, -0.03, 0.02]).double())
    errors = []
    for weight in (0.0, 1.0, 1e6):
        cfg = config("tracking.solver=lm", "tracking.num_opti_steps=8", "economy.coarse_factor=1",
                     "tracking.mask_alpha=0.8", f"tracking.velocity_prior={weight}")  # fmt: skip
        state = gt_state(synth, cfg, k + 1)
        track(state, k, pose=start)
        errors.append(pose_error(state.traj.knots()[k + 1], T_gt.numpy())[1])
    at_start = pose_error(start, T_gt.numpy())[1]
    assert errors[0] < 0.5 * at_start
    assert errors[0] < errors[1] < 0.9 * at_start, (errors, at_start)
    assert errors[2] == pytest.approx(at_start, rel=0.01)


def test_lm_velocity_prior_lets_go_after_its_frames(synth):
    """``tracking.velocity_prior_frames``: an overwhelming prior holds the knot at its start while the
    frame is within the first tracked ones, and past them LM tracks exactly as with the prior off."""
    _, scene = synth
    k = 4
    T_gt = torch.as_tensor(scene.poses[k + 1])
    start = T_gt @ se3_exp(torch.tensor([0.05, -0.04, 0.03, 0.02, -0.03, 0.02]).double())

    def tracked(*sets: str) -> torch.Tensor:
        cfg = config("tracking.solver=lm", "tracking.num_opti_steps=8", "economy.coarse_factor=1",
                     "tracking.mask_alpha=0.8", *sets)  # fmt: skip
        state = gt_state(synth, cfg, k + 1)
        track(state, k, pose=start)
        return state.traj.knots()[k + 1].detach()

    n = k + 1 - config().init.num_frames  # the knot is the n-th tracked frame
    assert n >= 2  # so that n − 1 frames is not 0 (the whole run)
    free, held = tracked("tracking.velocity_prior=0"), tracked("tracking.velocity_prior=1e6")
    at_start = pose_error(start, T_gt.numpy())[1]
    assert pose_error(free, T_gt.numpy())[1] < 0.5 * at_start
    assert pose_error(held, T_gt.numpy())[1] == pytest.approx(at_start, rel=0.01)
    for frames, expected in ((n, held), (n - 1, free)):
        limited = tracked("tracking.velocity_prior=1e6", f"tracking.velocity_prior_frames={frames}")
        assert torch.equal(limited, expected), frames
    tc = config("tracking.velocity_prior=2", "tracking.velocity_prior_frames=3").tracking
    assert [prior_weight(tc, i) for i in (1, 3, 4)] == [2.0, 2.0, 0.0]
    assert prior_weight(config("tracking.velocity_prior=2").tracking, 10**6) == 2.0


def test_prior_curvature_floors_each_kind_separately():
    """Translations and rotations have different units: each is floored by its own best-seen coordinate."""
    diag = torch.tensor([1.0, 0.5, 0.01, 2.0, 0.4, 0.02], dtype=torch.float64)
    assert torch.equal(prior_curvature(diag, 3.0, 0.0), torch.diag(3.0 * diag))
    floored = prior_curvature(diag, 3.0, 0.25).diagonal()
    assert floored.tolist() == pytest.approx([3.0, 1.5, 0.75, 6.0, 1.5, 1.5])
    assert torch.equal(prior_curvature(diag, 0.0, 0.25), torch.zeros(6, 6, dtype=torch.float64))


def test_lm_velocity_prior_floor_holds_the_weakly_seen_rotation(synth, monkeypatch):
    """With the floor, a start off the truth along the rotation the events see least stays near the
    constant-velocity prediction (the start), where without it LM corrects it; along the best-seen
    rotation both correct it alike."""
    _, scene = synth
    k = 4
    T_gt = torch.as_tensor(scene.poses[k + 1])
    seen = []
    spy = lambda d, w, f: seen.append(d) or prior_curvature(d, w, f)  # noqa: E731
    monkeypatch.setattr(pose_solver, "prior_curvature", spy)

    def corrected(axis: int, floor: float) -> float:
        """Share of a 0.02 rad error about ``axis`` (3..5) that tracking removes."""
        offset = torch.zeros(6, dtype=torch.float64)
        offset[axis] = 0.02
        cfg = config("tracking.solver=lm", "tracking.num_opti_steps=8", "economy.coarse_factor=1",
                     "tracking.mask_alpha=0.8", "tracking.velocity_prior=1",
                     f"tracking.velocity_prior_floor={floor}")  # fmt: skip
        state = gt_state(synth, cfg, k + 1)
        track(state, k, pose=T_gt @ se3_exp(offset))
        return 1 - float(se3_log(se3_inverse(T_gt) @ state.traj.knots()[k + 1].detach())[axis]) / 0.02

    corrected(3, 0.0)
    rot = torch.stack(seen)[:, 3:].median(0).values
    weak, strong = 3 + int(rot.argmin()), 3 + int(rot.argmax())
    assert float(rot.min()) < 0.3 * float(rot.max()), rot  # the scene has a weakly seen rotation
    assert corrected(weak, 0.0) > 0.3 and corrected(weak, 1.0) < 0.5 * corrected(weak, 0.0)
    assert corrected(strong, 1.0) == pytest.approx(corrected(strong, 0.0), abs=0.1)


def test_mapping_keeps_parameters_aligned_through_densification(synth):
    _, scene = synth
    cfg = config(
        "mapping.num_opti_steps_for_BA=12", "strategy.refine_start=0", "strategy.refine_every=4",
        "strategy.grow_grad2d=1e-9", "strategy.prune_opa=0.05", "mapping.max_new_gaussians=40",
        "economy.coarse_factor=1",
    )  # fmt: skip
    g = scene.gaussians
    keep = torch.arange(len(g)) % 3 != 0  # a third of the scene is missing: the view has holes
    partial = Gaussians(*(g[k].detach()[keep] for k in PARAM_NAMES))
    k = 5
    state = gt_state(synth, cfg, k + 2, partial)
    n0 = len(state.gaussians)
    record = map_window(state, k)
    n = len(state.gaussians)
    assert record.added > 0 and record.iterations == 12
    assert n > n0 + record.added  # grown by clones/splits as well
    assert all(len(state.gaussians[name]) == n for name in PARAM_NAMES)
    assert all(torch.isfinite(state.gaussians[name]).all() for name in PARAM_NAMES)
    assert np.isfinite(record.loss)
    # The window's knots moved, knot 0 (the gauge) did not.
    knots = state.traj.knots()
    assert torch.equal(knots[0], torch.as_tensor(scene.poses[0]))
    assert not torch.equal(knots[k + 1], torch.as_tensor(scene.poses[k + 1]))


def test_mapping_without_poses_trains_the_map_only(synth):
    """``mapping.train_poses = false``: the local BA leaves every knot where tracking put it."""
    cfg = config("mapping.num_opti_steps_for_BA=4", "economy.coarse_factor=1", "mapping.train_poses=false")
    k = 5
    state = gt_state(synth, cfg, k + 2)
    knots = state.traj.knots().detach().clone()
    means = state.gaussians["means"].detach().clone()
    record = map_window(state, k)
    assert record.iterations == 4
    assert torch.equal(state.traj.knots(), knots)
    assert not torch.equal(state.gaussians["means"][: len(means)], means)


def test_mapping_replays_the_chunks_before_its_window(synth, monkeypatch):
    """``mapping.replay_every = 3``: every third iteration of a local BA draws its window from the tracked
    chunks before the window (not the initialization's), whose knots stay where they were; the other
    iterations keep to the window."""
    sets = ("mapping.num_opti_steps_for_BA=9", "economy.coarse_factor=1", "mapping.window=2")
    k = 5
    drawn = record_windows(monkeypatch)
    for every in (0, 3):
        drawn.clear()
        state = gt_state(synth, config(*sets, f"mapping.replay_every={every}"), k + 2)
        before = state.traj.knots().detach().clone()
        map_window(state, k)
        m = state.num_init_chunks()
        assert 0 < m < k - 1
        old, new = state.data.span(m, k - 1), state.data.span(k - 1, k + 1)
        inside = [
            "old" if old[0] <= s and e <= old[1] else "new" if new[0] <= s and e <= new[1] else "across"
            for s, e in ranges(drawn)
        ]
        replayed = ["old" if every and (i + 1) % every == 0 else "new" for i in range(9)]
        assert inside == replayed
        assert torch.equal(state.traj.knots()[: k - 1], before[: k - 1])
    for bad in (-1, 1):
        with pytest.raises(ConfigError, match="mapping.replay_every must be 0"):
            config(f"mapping.replay_every={bad}")


@pytest.mark.parametrize("hold", [False, True])
def test_the_final_global_ba_holds_the_positions_when_asked(synth, hold: bool):
    """``global_ba.final_hold_positions``: the final global BA turns the knots about their centres and
    keeps where they are (to the rebase's rounding); the periodic global BAs move both either way."""
    cfg = config("global_ba.num_opti_steps_final=15", "global_ba.num_opti_steps=15",
                 f"global_ba.final_hold_positions={str(hold).lower()}")  # fmt: skip
    for final in (True, False):
        state = gt_state(synth, cfg, 5)
        with torch.no_grad():
            state.traj.base[1:] = state.traj.base[1:] @ se3_exp(
                torch.tensor([0.02, 0, 0, 0, 0.01, 0], dtype=torch.float64)
            )
            before = state.traj.knots().clone()
        global_ba(state, final=final)
        after = state.traj.knots().detach()
        moved = (after[1:, :3, 3] - before[1:, :3, 3]).norm(dim=-1)
        turned = (after[1:, :3, :3] - before[1:, :3, :3]).abs().amax(dim=(-2, -1))
        assert bool((turned > 1e-6).all())
        if hold and final:
            assert float(moved.max()) < 1e-12
        else:
            assert bool((moved > 1e-6).all())


def test_global_ba_windows_reach_global_ba_max_n_winsize(synth, monkeypatch):
    """``global_ba.max_n_winsize`` lengthens the global BA's windows only; 0 keeps data.max_n_winsize."""
    cfg = config(
        "global_ba.num_opti_steps_final=20",
        "mapping.num_opti_steps_for_BA=20",
        "economy.coarse_factor=1",
        "data.min_n_winsize=200",
        "data.max_n_winsize=500",
    )
    short, long_ = 500, 2000
    drawn = record_windows(monkeypatch)
    state = gt_state(
        synth, dataclasses.replace(cfg, global_ba=dataclasses.replace(cfg.global_ba, max_n_winsize=long_)), 5
    )
    assert state.data.span(0, 4)[1] - state.data.span(0, 4)[0] > long_  # the span allows long windows
    global_ba(state, final=True)
    final = lengths(drawn)
    drawn.clear()
    map_window(state, 3)
    assert max(final) > short and max(final) <= long_
    assert max(lengths(drawn)) <= short
    sampler = state.data.sampler(state.data.span(0, 4), 0)  # 0: the data's
    starts, ends = sampler.sample(50)
    assert int((np.asarray(ends) - np.asarray(starts)).max()) <= short
    with pytest.raises(ConfigError, match="global_ba.max_n_winsize must be 0"):
        config(f"global_ba.max_n_winsize={cfg.data.min_n_winsize - 1}")


def test_final_global_ba_runs_every_step_without_its_early_stop(synth):
    """``global_ba.final_early_stop = false``: economy's convergence stop (here on at once) no longer ends
    the final global BA; the periodic ones still stop on it."""
    stop_at_once = ("economy.patience=2", "economy.min_rel_change=10", "economy.min_fraction=0")
    sets = ("global_ba.num_opti_steps_final=12", "global_ba.num_opti_steps=12", "economy.coarse_factor=1")
    runs = {}
    for early in (True, False):
        cfg = config(*stop_at_once, *sets, f"global_ba.final_early_stop={str(early).lower()}")
        state = gt_state(synth, cfg, 5)
        runs[early] = (global_ba(state, final=False), global_ba(state, final=True))
    assert [r.iterations for r in runs[True]] == [4, 4]
    assert runs[True][1].stopped_early
    assert runs[False][0].iterations == 4
    assert runs[False][1].iterations == 12 and not runs[False][1].stopped_early


def test_start_frame_counts_in_the_data_sets_numbering(synth):
    """``evgs import --frames A:B`` renumbers frames from 0 and records A as ``frame_offset``; the configs'
    ``start_frame`` (the paper's numbering) must still select the same frames."""
    seq, _ = synth
    data_cfg = config().data
    whole = EventData.from_sequence(seq, dataclasses.replace(data_cfg, start_frame=3, num_frames=2))
    # Pretend this folder's frame 0 is the data set's frame 2: data-set frame 5 is folder frame 3.
    imported = dataclasses.replace(seq, meta={**seq.meta, "frame_offset": 2})
    sub = EventData.from_sequence(imported, dataclasses.replace(data_cfg, start_frame=5, num_frames=2))
    np.testing.assert_array_equal(sub.frames_us, whole.frames_us)
    with pytest.raises(ValueError, match="before the imported range"):
        EventData.from_sequence(imported, dataclasses.replace(data_cfg, start_frame=1, num_frames=2))


def test_total_variation_enters_the_global_ba_only(synth):
    """``global_ba.tv_weight`` adds ``w · TV(renders)`` to the global BA's loss, not to a local BA's."""
    sets = ("global_ba.num_opti_steps_final=1", "mapping.num_opti_steps_for_BA=1", "economy.coarse_factor=1")
    losses = {}
    for w in (0.0, 0.5):
        cfg = config(*sets, f"global_ba.tv_weight={w}")
        losses[w] = (
            global_ba(gt_state(synth, cfg, 5), final=True).loss,
            map_window(gt_state(synth, cfg, 5), 3).loss,
        )
    assert losses[0.5][1] == losses[0.0][1]
    assert losses[0.5][0] > losses[0.0][0]
    # The step's loss is the event loss plus exactly w · TV of the gray renders.
    state = gt_state(synth, config(*sets), 5)
    spec = StageSpec("final", 4, 1, state.data.span(0, 4), 1, 0, [], [], True, tv_weight=0.5)
    step = loss_step(state, spec, state.data.windows(state.data.sampler(spec.span, 0), 1, 1), 1)
    tv = total_variation(step.out.color[..., 0]).item()
    assert step.total.item() == pytest.approx(step.terms.total.item() + 0.5 * tv, rel=1e-6)


def test_depth_variation_enters_the_stages_that_train_the_map_only(synth):
    """``loss.depth_tv`` adds ``w · depth_variation`` to the loss of a stage that trains the map (init,
    local and global BAs), not to tracking's."""
    state = gt_state(synth, config("loss.depth_tv=0.5"), 5)
    win = state.data.windows(state.data.sampler(state.data.span(0, 4), 0), 1, 1)
    for train in (True, False):
        spec = StageSpec("map", 4, 1, state.data.span(0, 4), 1, 0, [], [], train)
        step = loss_step(state, spec, win, 1)
        extra = 0.5 * depth_variation(step.out.depth, step.out.alpha).item() if train else 0.0
        assert extra >= 0 and (extra > 0) == train
        assert step.total.item() == pytest.approx(step.terms.total.item() + extra, rel=1e-6)

"""The rate check before the final global BA: the tracked motion's speed scored over the whole run."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.config import ConfigError, load_config  # noqa: E402
from evgs.slam import rate_check  # noqa: E402
from evgs.slam.lie import se3_exp, se3_inverse, se3_log  # noqa: E402
from evgs.slam.motion_search import fit  # noqa: E402
from evgs.slam.optimize import fixed_window_loss  # noqa: E402
from evgs.slam.rate_check import (  # noqa: E402
    SCORE_WINDOWS,
    check_rate,
    parabola_vertex,
    rate_factors,
    replica_seed,
)
from evgs.slam.seeding import seeded_map  # noqa: E402
from evgs.slam.state import stage_seed  # noqa: E402
from evgs.slam.trajectory import Trajectory, scaled_motion  # noqa: E402
from slam_synth import make_sequence, search_state  # noqa: E402

SLOW = 0.85  # the slowed run's speed, of the truth's
STEPS = 300  # each refit's: at 60 the tiny scene's refits score every faster motion better


def test_scaled_motion_is_the_same_constant_velocity_path_at_another_speed():
    T0 = se3_exp(torch.tensor([0.3, -0.2, 1.0, 0.4, 0.1, -0.7], dtype=torch.float64))
    xi = torch.tensor([0.02, 0.01, -0.03, 0.015, -0.01, 0.02], dtype=torch.float64)
    k = torch.arange(6, dtype=torch.float64)[:, None]
    knots = T0 @ se3_exp(k * xi)
    for f in (0.8, 1.0, 1.3):
        got = scaled_motion(knots, f)
        assert torch.allclose(got, T0 @ se3_exp(k * f * xi), atol=1e-12)
        assert torch.equal(got[0], knots[0])


def test_the_vertex_is_the_parabola_s_through_the_best_and_its_neighbours():
    f = rate_factors(0.1)
    assert np.allclose(f, [0.9, 0.95, 1.0, 1.05, 1.1])
    assert parabola_vertex(f, (f - 1.03) ** 2 + 0.5) == pytest.approx(1.03)
    # Only the best and its neighbours count: a steep rise far below does not pull the vertex up.
    steep = np.array([9.0, 4.0, 1.0, 0.2, 0.6])
    assert parabola_vertex(f, steep) == pytest.approx(1.05 + 0.05 * 0.5 * 0.4 / 1.2)
    assert parabola_vertex(f, np.array([900.0, 4.0, 1.0, 0.2, 0.6])) == parabola_vertex(f, steep)
    assert parabola_vertex(f, (f - 1.3) ** 2) == pytest.approx(1.1)  # beyond the scan: its end
    assert parabola_vertex(f, -0.1 * f) == pytest.approx(1.1)  # a line: its lower end


@pytest.fixture(scope="module")
def checked(tmp_path_factory):
    """The scene's own path at its speed and at 0.85 of it (as a run that kept the search's slow rung
    would hold it), each rate-checked: the state, its map before, the record and the factor applied."""
    seq, scene = make_sequence(tmp_path_factory.mktemp("seq") / "synth")
    P = torch.as_tensor(scene.poses)
    truth = se3_inverse(P[:1]) @ P
    out = {}
    for speed in (1.0, SLOW):
        state = search_state(seq, "global_ba.rate_check=0.3", f"global_ba.rate_check_steps={STEPS}")
        state.traj = Trajectory(scene.frames_us, scaled_motion(truth, speed))
        before = state.gaussians.state()
        record = check_rate(state, seeded_map(state))
        out[speed] = (state, before, record, float(record.note.split("×")[1].split()[0]))
    return truth, out


def test_the_rate_check_speeds_a_slowed_run_up_towards_the_truth(checked):
    """From 0.85 of the truth's speed the check speeds the run up, nearer the truth, and by more than it
    speeds up the truth itself; the knots are the tracked ones scaled by the factor, the run's map is
    left alone, and the record says what was tried."""
    truth, out = checked
    state, before, record, factor = out[SLOW]
    assert factor > out[1.0][3] and abs(out[1.0][3] - 1) < 0.1, (record.note, out[1.0][2].note)
    chord = lambda T: float(se3_log(se3_inverse(T[0]) @ T[-1])[3:].norm())  # noqa: E731
    got = state.traj.knots().detach()
    assert abs(chord(got) - chord(truth)) < abs(chord(truth) * SLOW - chord(truth))
    assert torch.allclose(got, scaled_motion(truth, SLOW * factor), atol=1e-9)
    assert all(torch.equal(v, before[k]) for k, v in state.gaussians.state().items())
    assert record.stage == "rate" and record.iterations == 5 * STEPS and state.history[-1] is record
    assert record.note.count("×") == 6 and record.seconds > 0


def test_the_rate_check_needs_the_first_surface_read_at_the_end():
    """It moves the cameras the map was fitted to: a first-surface read before the final BA would
    measure the run's map from cameras it no longer fits."""
    bad = ["global_ba.rate_check=0.1", "scale.source=range", "scale.surface_read=before_final_ba"]
    with pytest.raises(ConfigError, match="scale.surface_read = 'end'"):
        load_config(overrides=bad)
    load_config(overrides=[*bad[:2], "scale.surface_read=end"])
    load_config(overrides=[bad[0], "scale.source=none"])
    with pytest.raises(ConfigError, match="rate_check must be in"):
        load_config(overrides=["global_ba.rate_check=1.5"])


def test_each_speed_scores_the_mean_of_its_seedings_refits(tmp_path):
    """With two seedings a speed's score is the mean of the run's own refit and one from another seeding
    and random streams, which scores differently (so it is another draw, not a repeat)."""
    seq, scene = make_sequence(tmp_path / "synth")
    P = torch.as_tensor(scene.poses)
    truth = se3_inverse(P[:1]) @ P
    steps, notes = 20, {}
    for k in (1, 2):
        sets = ["global_ba.rate_check=0.2", f"global_ba.rate_check_steps={steps}"]
        state = search_state(seq, *sets, f"global_ba.rate_check_seedings={k}")
        state.traj = Trajectory(scene.frames_us, truth)
        record = check_rate(state, seeded_map(state))
        assert record.iterations == 5 * steps * k
        notes[k] = [float(x.split()[1].rstrip(",)")) for x in record.note.split("(scores ")[1].split("×")[1:]]
    state = search_state(seq, "global_ba.rate_check=0.2")
    s1 = replica_seed(state.cfg.seed, 1)
    assert s1 != state.cfg.seed and replica_seed(state.cfg.seed, 0) == state.cfg.seed
    other = dataclasses.replace(state, gaussians=seeded_map(state, torch.Generator().manual_seed(s1)))
    span = state.data.span(0, len(scene.frames_us) - 1)
    for f, one, two in zip(rate_factors(0.2), notes[1], notes[2], strict=True):
        trial = fit(other, scaled_motion(truth, float(f)), None, steps, True, "rate", s1)
        with torch.no_grad():
            replica = fixed_window_loss(trial, span, stage_seed(state.cfg.seed, "rate", 0), SCORE_WINDOWS)
        assert abs(replica - one) > 1e-5
        assert two == pytest.approx((one + replica) / 2, abs=1.5e-5)


def test_the_rate_check_needs_at_least_one_seeding():
    with pytest.raises(ConfigError, match="rate_check_seedings >= 1"):
        load_config(overrides=["global_ba.rate_check_seedings=0"])


def test_the_refits_carry_their_own_relief_prior(tmp_path, monkeypatch):
    """``global_ba.rate_check_depth_tv`` >= 0 is ``loss.depth_tv`` in the rate check's refits alone (the
    run keeps its own); < 0 leaves the refits the run's."""
    seq, scene = make_sequence(tmp_path / "synth")
    seen = []

    def fake_fit(state, knots, reporter, steps, smooth, stage, seed):
        seen.append(state.cfg.loss.depth_tv)
        return state

    monkeypatch.setattr(rate_check, "fit", fake_fit)
    monkeypatch.setattr(rate_check, "fixed_window_loss", lambda *args: 1.0)
    sets = ["global_ba.rate_check=0.2", "loss.depth_tv=0.5"]
    for extra, want in (("global_ba.rate_check_depth_tv=0", 0.0), ("global_ba.rate_check_depth_tv=-1", 0.5)):
        seen.clear()
        state = search_state(seq, *sets, extra)
        state.traj = Trajectory(scene.frames_us, torch.as_tensor(scene.poses))
        check_rate(state, seeded_map(state))
        assert seen == [want] * 5 and state.cfg.loss.depth_tv == 0.5

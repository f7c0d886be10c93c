"""The run's start in branches (``init.branches``): each motion runs the initialization and
``init.branch_frames`` tracked frames, the branch that explains those chunks best goes on."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.config import ConfigError, load_config  # noqa: E402
from evgs.slam.branches import branch_hypotheses, branch_score, run_branches  # noqa: E402
from evgs.slam.lie import se3_inverse, se3_log  # noqa: E402
from evgs.slam.metric_scale import first_surface  # noqa: E402
from evgs.slam.motion_search import Hypothesis  # noqa: E402
from evgs.slam.stages import initialize, start_from, step_chunk  # noqa: E402
from evgs.slam.state import StageRecord  # noqa: E402
from slam_synth import gt_state, make_sequence, search_state  # noqa: E402

FRAMES = 2


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq") / "synth")


def state(synth):
    return search_state(synth[0], f"init.branch_frames={FRAMES}", "init.num_opti_steps_for_init=100")


def truth(synth, m: int) -> Hypothesis:
    """The scene's own mean velocity over the initialization chunks."""
    P = torch.as_tensor(synth[1].poses)
    return Hypothesis("truth", se3_log(se3_inverse(P[0]) @ P[m]) / m)


def test_the_branch_that_explains_its_chunks_best_goes_on_as_if_alone(synth):
    s = state(synth)
    m = s.num_init_chunks()
    true = truth(synth, m)
    wrong = Hypothesis("reversed", -true.twist)
    notes: list[StageRecord] = []
    kept = [run_branches(state(synth), order, notes.append) for order in ([true, wrong], [wrong, true])]
    for k in kept:
        assert k.position.initialized and k.position.next_chunk == m + FRAMES
        record = k.history[-1]
        assert record.stage == "branch" and record.note.startswith("kept truth of 2")
        assert "reversed" in record.note and record.seconds > 0
        assert k.branch == ""
    # The order of the branches does not matter, and the kept one is the truth's run on its own.
    alone = state(synth)
    start_from(alone, true)
    initialize(alone)
    alone.position.initialized, alone.position.next_chunk = True, m
    for _ in range(FRAMES):
        step_chunk(alone, lambda r: None)
    for k in kept:
        assert torch.equal(k.traj.knots(), alone.traj.knots())
        assert torch.equal(k.gaussians["means"], alone.gaussians["means"])
    assert branch_score(alone, m + FRAMES) == kept[0].history[-1].loss
    # Every branch's stages were reported, tagged with the branch.
    stages = {r.stage for r in notes}
    assert {"branch0/init", "branch1/init", "branch0/track", "branch1/map"} <= stages


def test_the_range_score_is_the_spread_of_the_meter_against_the_map(synth):
    seq, scene = synth
    n = len(scene.frames_us) - 1
    s = gt_state(seq, scene, "init.branch_score=range")
    with pytest.raises(ValueError, match="needs the sequence's range meter"):
        branch_score(s, n)
    with pytest.raises(ValueError, match="needs the sequence's range meter"):  # before any branch runs
        run_branches(s, [truth(synth, s.num_init_chunks())], lambda r: None)
    _, true_range = first_surface(scene.gaussians, torch.as_tensor(scene.poses))

    def metered(ranges: np.ndarray, *sets: str) -> float:
        st = gt_state(seq, scene, "init.branch_score=range", *sets)
        st = dataclasses.replace(st, data=dataclasses.replace(st.data, ranges=(scene.frames_us, ranges)))
        return branch_score(st, n)

    # The map keeps the meter's distance at any one scale: no spread.
    assert metered(2.5 * true_range.numpy()) < 1e-6
    # The meter reads 20 % farther from the k-th sample on: log 1.2 apart in a fraction p of them.
    k = (n + 1) // 3
    p = (n + 1 - k) / (n + 1)
    stepped = np.where(np.arange(n + 1) < k, 1.0, 1.2) * true_range.numpy()
    assert metered(stepped) == pytest.approx(np.log(1.2) * np.sqrt(p * (1 - p)), rel=1e-4)
    # A map that covers none of the meter's rays never wins.
    assert metered(true_range.numpy(), "scale.min_alpha=1.1") == float("inf")


def test_branch_settings_are_checked():
    with pytest.raises(ConfigError, match="init.branches must be >= 1"):
        load_config("synthetic/tiny", ["init.branches=0"])
    with pytest.raises(ConfigError, match="init.branch_frames >= 0"):
        load_config("synthetic/tiny", ["init.branch_frames=-1"])
    with pytest.raises(ConfigError, match="init.branches > 1 needs init.motion_search"):
        load_config("synthetic/tiny", ["init.branches=2", "init.motion_search=false"])
    with pytest.raises(ConfigError, match="branch_score"):
        load_config("synthetic/tiny", ["init.branch_score=loss"])


@pytest.mark.parametrize("train_knots", [True, False])
def test_the_initialization_holds_the_knots_on_the_searched_motion_when_asked(synth, train_knots):
    """``init.train_knots = false``: the initialization fits the map alone, its knots stay on the motion
    it starts from to the last bit; with true (the default) they move."""
    s = search_state(
        synth[0], "init.num_opti_steps_for_init=20", f"init.train_knots={str(train_knots).lower()}"
    )
    m = s.num_init_chunks()
    start_from(s, truth(synth, m))
    with torch.no_grad():
        knots, means = s.traj.knots().clone(), s.gaussians["means"].clone()
    initialize(s)
    with torch.no_grad():
        assert torch.equal(s.traj.knots(), knots) != train_knots
        assert not torch.equal(s.gaussians["means"], means)


def test_the_initialization_holds_the_knots_rotations_when_asked(synth):
    """``init.train_knot_rotation = false``: the initialization moves the knots' positions and keeps their
    rotations on the motion it starts from, to rounding (the knots are re-projected onto SE(3))."""
    s = search_state(synth[0], "init.num_opti_steps_for_init=20", "init.train_knot_rotation=false")
    m = s.num_init_chunks()
    start_from(s, truth(synth, m))
    with torch.no_grad():
        knots = s.traj.knots().clone()
    initialize(s)
    with torch.no_grad():
        after = s.traj.knots()
        torch.testing.assert_close(after[:, :3, :3], knots[:, :3, :3], rtol=0, atol=1e-12)
        moved = (after[1:, :3, 3] - knots[1:, :3, 3]).norm(dim=-1)
        assert bool((moved > 1e-6).all())
        torch.testing.assert_close(after[0], knots[0], rtol=0, atol=0)  # knot 0 is the gauge


def test_the_branches_take_the_best_of_each_direction_when_asked():
    """``init.branch_directions``: a motion at another rate (the search's ladder, also after the meter's
    advance) is the same direction and gives no branch of its own; veers and polls are other directions."""
    orbit = Hypothesis("orbit +y", torch.tensor([0.03, 0, 0, 0, 0.01, 0], dtype=torch.float64), "orbit")
    mirror = Hypothesis("orbit -y", -orbit.twist, "orbit")
    ranked = [
        orbit.advancing(0.01).scaled(0.5),
        orbit.scaled(2.0).advancing(0.01),
        mirror.advancing(0.01),
        mirror.advancing(0.01).scaled(0.5),
        Hypothesis("orbit +y veer a+20°", orbit.twist, "orbit"),
    ]
    assert ranked[0].direction == ranked[1].direction == "orbit +y (meter advance 0.01)"
    assert branch_hypotheses(ranked, 3, False) == ranked[:3]
    assert branch_hypotheses(ranked, 3, True) == [ranked[0], ranked[2], ranked[4]]
    assert branch_hypotheses(ranked, 2, True) == [ranked[0], ranked[2]]
    assert branch_hypotheses(ranked[:2], 3, True) == ranked[:1]


def test_held_init_knots_need_the_motion_search():
    with pytest.raises(ConfigError, match="train_knots = false needs init.motion_search"):
        load_config(overrides=["init.train_knots=false"])
    with pytest.raises(ConfigError, match="train_knot_rotation = false needs init.motion_search"):
        load_config(overrides=["init.train_knot_rotation=false"])

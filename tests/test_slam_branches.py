"""The run's start in branches (``init.branches``): each motion runs the initialization and
``init.branch_frames`` tracked frames, the branch that explains those chunks best goes on."""

from __future__ import annotations

import dataclasses
from functools import partial

import numpy as np
import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.config import ConfigError, load_config  # noqa: E402
from evgs.slam import branches, checkpoint  # noqa: E402
from evgs.slam.branches import branch_hypotheses, branch_score, run_branches  # noqa: E402
from evgs.slam.lie import se3_inverse, se3_log  # noqa: E402
from evgs.slam.metric_scale import first_surface  # noqa: E402
from evgs.slam.motion_search import Hypothesis  # noqa: E402
from evgs.slam.seeding import seeded_map, seeding_generator  # noqa: E402
from evgs.slam.stages import initialize, start_from, step_chunk  # noqa: E402
from evgs.slam.state import StageRecord  # noqa: E402
from slam_synth import gt_state, make_sequence, search_state  # noqa: E402

FRAMES = 2


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq") / "synth")


def state(synth, *sets: str):
    return search_state(synth[0], f"init.branch_frames={FRAMES}", "init.num_opti_steps_for_init=100", *sets)


def truth(synth, m: int) -> Hypothesis:
    """The scene's own mean velocity over the initialization chunks."""
    P = torch.as_tensor(synth[1].poses)
    return Hypothesis("truth", se3_log(se3_inverse(P[0]) @ P[m]) / m)


def branch_scores(note: str) -> dict[str, float]:
    """The branches' scores in a branch record's note: ``... (mean tracking loss on chunks a–b: name
    score, name score[; its restarts ...])``."""
    listed = note.split(": ", 1)[1].split(";")[0].rstrip(")")
    return {name: float(score) for name, score in (item.rsplit(" ", 1) for item in listed.split(", "))}


def kept_name(note: str) -> str:
    """The kept branch's name: ``kept NAME of N`` or ``kept NAME, restart k of N``."""
    return note.removeprefix("kept ").split(" of ")[0].split(", restart ")[0]


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


def test_the_tracking_score_is_the_mean_loss_of_the_frames_each_branch_tracked(synth):
    s = state(synth, "init.branch_score=tracking")
    m = s.num_init_chunks()
    true = truth(synth, m)
    kept = run_branches(s, [Hypothesis("reversed", -true.twist), true], lambda r: None)
    record = kept.history[-1]
    assert f" of 2 (mean tracking loss on chunks {m}–{m + FRAMES - 1}: reversed " in record.note
    # The lower score goes on. Over two tiny frames the truth and its reverse score within a few per cent,
    # and which is lower depends on the CPU's bits (docs/ablations.md §86), so the test checks the rule.
    scores = branch_scores(record.note)
    assert set(scores) == {"reversed", "truth"} and kept_name(record.note) == min(scores, key=scores.get)
    tracked = [r.loss for r in kept.history if r.stage == "track"]
    assert len(tracked) == FRAMES
    assert record.loss == branch_score(kept, m + FRAMES) == pytest.approx(np.mean(tracked), rel=1e-12)
    # A branch that tracked nothing, or lost a frame, never wins.
    assert branch_score(state(synth, "init.branch_score=tracking"), m) == float("inf")
    last_track = next(r for r in reversed(kept.history) if r.stage == "track")
    kept.history.append(dataclasses.replace(last_track, loss=float("nan")))
    assert branch_score(kept, m + FRAMES) == float("inf")


def test_restarts_run_the_kept_motion_again_from_other_seedings_and_keep_the_best(synth):
    sets = ("init.branch_score=tracking", "init.branch_restarts=3")
    s = state(synth, *sets)
    m = s.num_init_chunks()
    true = truth(synth, m)
    reseed = partial(seeded_map, s)

    with pytest.raises(ValueError, match="needs a reseed function"):
        run_branches(s, [true], lambda r: None)
    notes: list[StageRecord] = []
    kept = run_branches(s, [Hypothesis("reversed", -true.twist), true], notes.append, reseed=reseed)
    record = kept.history[-1]
    assert " of 4 (" in record.note and "; its restarts " in record.note
    stages = {r.stage for r in notes}
    assert {"branch0/init", "branch1/track", "restart1/init", "restart2/track"} <= stages
    # The restarts ran the best branch's motion again, each from its own seeding: a score of its own, and
    # the lowest of the three went on.
    scores = [float(x) for x in record.note.split("; its restarts ")[1].rstrip(")").split(", ")]
    branches_scored = branch_scores(record.note)
    best = min(branches_scored, key=branches_scored.get)
    assert kept_name(record.note) == best and len({branches_scored[best], *scores}) == 3
    lowest = min(branches_scored[best], *scores)
    assert record.loss == branch_score(kept, m + FRAMES) == pytest.approx(lowest, abs=5e-6)
    # Deterministic: the same call gives the same run.
    hyps = [Hypothesis("reversed", -true.twist), true]
    again = run_branches(state(synth, *sets), hyps, lambda r: None, reseed=reseed)
    assert torch.equal(again.traj.knots(), kept.traj.knots())
    assert again.history[-1].note == record.note


def test_a_restart_that_scores_best_goes_on(synth, monkeypatch):
    s = state(synth, "init.branch_restarts=2")
    m = s.num_init_chunks()
    reseed = partial(seeded_map, s)

    monkeypatch.setattr(branches, "branch_score", lambda st, n: 0.0 if st.branch == "restart1" else 1.0)
    kept = run_branches(s, [truth(synth, m)], lambda r: None, reseed=reseed)
    assert kept.history[-1].note.startswith("kept truth, restart 1 of 2 (loss on chunks 0–")
    assert kept.branch == "" and kept.seeding == 1
    # A refit from scratch (the rate check) starts from restart 1's map, not the run's own, also resumed.
    restart_map = reseed(seeding_generator(s.cfg.seed, 1))
    assert not torch.equal(seeded_map(s)["means"], restart_map["means"])
    for st in (kept, checkpoint.restore(checkpoint.snapshot(kept), kept.cfg, kept.data)):
        assert st.seeding == 1 and torch.equal(seeded_map(st)["means"], restart_map["means"])
    # It is the run from restart 1's seeding on its own.
    alone = state(synth, "init.branch_restarts=2")
    alone.generator = seeding_generator(s.cfg.seed, 1)
    alone.gaussians = reseed(alone.generator)
    start_from(alone, truth(synth, m))
    initialize(alone)
    alone.position.initialized, alone.position.next_chunk = True, m
    for _ in range(FRAMES):
        step_chunk(alone, lambda r: None)
    assert torch.equal(kept.traj.knots(), alone.traj.knots())
    assert torch.equal(kept.gaussians["means"], alone.gaussians["means"])


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
    with pytest.raises(ConfigError, match="init.branch_restarts must be >= 1"):
        load_config("synthetic/tiny", ["init.branch_restarts=0"])
    with pytest.raises(ConfigError, match="init.branch_restarts > 1 needs init.motion_search"):
        load_config("synthetic/tiny", ["init.branch_restarts=2", "init.motion_search=false"])
    with pytest.raises(ConfigError, match="needs init.branch_frames >= 1"):
        load_config(
            "synthetic/tiny",
            [
                "init.branches=2",
                "init.motion_search=true",
                "init.branch_score=tracking",
                "init.branch_frames=0",
            ],
        )


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

"""The initialization's motion search: its hypotheses, its search logic and its refit score."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch import Tensor

pytest.importorskip("evgs.render")

from evgs.slam import motion_search  # noqa: E402
from evgs.slam.lie import se3_inverse, se3_log  # noqa: E402
from evgs.slam.motion_search import (  # noqa: E402
    Hypothesis,
    directions,
    score,
    search_chunks,
    search_motion,
    veered,
)
from evgs.slam.stages import search, start_from  # noqa: E402
from slam_synth import make_sequence, search_state  # noqa: E402

RATE, DEPTH = 0.01, 3.0


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("seq") / "synth")


def synth_state(synth, *sets: str):
    return search_state(synth[0], *sets)


@pytest.mark.parametrize("orbit_depth", [None, 1.3 * DEPTH])
def test_hypotheses_are_rigid_orbits_about_the_centre_or_translations(orbit_depth):
    """The orbits keep their centre (``init_depth``, or ``init.search_orbit_depth`` behind the slab) where
    every camera looks; the translations' speed stays ``rate × init_depth`` either way."""
    hyps = {h.name: h for h in directions(RATE, DEPTH, orbit_depth=orbit_depth)}
    assert len(hyps) == 11 and "still" in hyps
    c = DEPTH if orbit_depth is None else orbit_depth
    centre = torch.tensor([0.0, 0.0, c], dtype=torch.float64)
    for name, h in hyps.items():
        K = h.knots(4)
        R, t = K[:, :3, :3], K[:, :3, 3]
        assert torch.allclose(K[0], torch.eye(4, dtype=torch.float64))
        assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
        if name.startswith("orbit"):  # the centre stays where every camera looks
            assert torch.allclose(R @ centre + t, centre.expand(4, 3), atol=1e-12)
            assert torch.allclose(se3_log(K[3])[3:].norm(), torch.tensor(3 * RATE, dtype=torch.float64))
        elif name.startswith("translate"):
            assert torch.allclose(R, torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
            assert torch.allclose(t.norm(dim=1), torch.arange(4, dtype=torch.float64) * RATE * DEPTH)
    # An orbit about +y moves the camera towards -x (the centre stays ahead): t_x ≈ -rate·depth.
    assert float(hyps["orbit +y"].knots(2)[1, 0, 3]) == pytest.approx(-RATE * c, rel=1e-3)


def test_tilted_orbits_keep_the_centre_and_roll_by_the_tilt():
    """``init.search_tilt``: every orbit also about its axis tilted ± the angle towards the optical axis
    (an orbit seen at an elevation), still about the centre and at the same rate."""
    plain = {h.name for h in directions(RATE, DEPTH)}
    hyps = {h.name: h for h in directions(RATE, DEPTH, 20.0)}
    assert len(hyps) == 19 and plain <= set(hyps)
    centre = torch.tensor([0.0, 0.0, DEPTH], dtype=torch.float64)
    for sign in "+-":
        for axis in "xy":
            for tilt in (20.0, -20.0):
                h = hyps[f"orbit {sign}{axis} tilt {tilt:+g}°"]
                K = h.knots(3)
                assert torch.allclose(K[:, :3, :3] @ centre + K[:, :3, 3], centre.expand(3, 3), atol=1e-12)
                w = h.twist[3:]
                assert float(w.norm()) == pytest.approx(RATE)
                assert np.degrees(np.arcsin(float(w[2]) / RATE)) == pytest.approx(tilt)
                assert float(w["xy".index(axis)]) * (1 if sign == "+" else -1) > 0


def test_without_polls_the_search_picks_the_best_sized_basis_motion_tilted_or_not(synth, monkeypatch):
    """The defaults (no compass, tilted orbits): a quadratic score around an orbit seen from an
    elevation of 18° (about -y tilted towards the optical axis, at 1.1× the nominal rate) is won by the
    tilted basis orbit; without the tilt only the plain one is there to win, at a worse score."""
    tilted = {h.name: h.twist for h in directions(RATE, DEPTH, 20.0)}["orbit -y tilt -20°"]
    w = RATE * torch.tensor([0.0, -np.cos(np.radians(18)), -np.sin(np.radians(18))], dtype=torch.float64)
    truth = 1.1 * torch.cat([-torch.linalg.cross(w, torch.tensor([0.0, 0.0, DEPTH], dtype=torch.float64)), w])
    assert float((tilted - truth).norm()) < 0.2 * float(truth.norm())

    unit = RATE * torch.tensor([DEPTH] * 3 + [1.0] * 3, dtype=torch.float64)  # equal image motion

    def fake_score(state, hyp, reporter):
        return float(((hyp.twist - truth) / unit).square().sum())

    monkeypatch.setattr(motion_search, "score", fake_score)
    sets = [f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}", "init.search_polls=0"]
    found = search_motion(synth_state(synth, *sets, "init.search_tilt=20"))
    assert found.best.name == "orbit -y tilt -20°"
    assert len(found.tried) == 19 + 8  # no motion, 18 directions, 4 more sizes of the best of each family
    plain = search_motion(synth_state(synth, *sets))
    assert plain.best.name == "orbit -y" and plain.score > 2 * found.score


def test_the_best_translation_is_sized_even_when_an_orbit_beats_it_at_the_nominal_rate(synth, monkeypatch):
    """docking_good: its approach, at half the nominal rate, scores worse at the nominal rate than an
    orbit does; sized only by rank, the orbit alone would be sized and win. Each family's best is sized,
    so the approach at its own rate is found."""
    basis = {h.name: h.twist for h in directions(RATE, DEPTH)}
    truth = 0.5 * basis["translate +z"]
    unit = RATE * torch.tensor([DEPTH] * 3 + [1.0] * 3, dtype=torch.float64)  # equal image motion

    def fake_score(state, hyp, reporter):
        to_truth = float(((hyp.twist - truth) / unit).square().sum())
        to_orbit = float(((hyp.twist - basis["orbit -y"]) / unit).square().sum())
        return min(4.0 * to_truth, 0.5 + to_orbit)

    monkeypatch.setattr(motion_search, "score", fake_score)
    nominal = {name: fake_score(None, Hypothesis(name, tw), None) for name, tw in basis.items()}
    assert min(nominal, key=nominal.get) == "orbit -y" and nominal["translate +z"] > nominal["orbit -y"]
    sets = [f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}", "init.search_polls=0"]
    found = search_motion(synth_state(synth, *sets))
    assert found.best.name == "translate +z ×0.5" and found.score == 0.0
    assert len(found.tried) == 11 + 8


def test_the_finalists_are_ranked_by_their_longer_refits_ahead_of_the_rest(synth, monkeypatch):
    """``init.search_finalists``: short refits rank the orbit's double rate first, the longer ones the
    orbit itself (``make run``'s hubble, docs/ablations.md §74). The k best of the short refits are
    refitted longer and ranked by that, ahead of the rest; the iterations count both."""
    basis = {h.name: h.twist for h in directions(RATE, DEPTH)}
    unit = RATE * torch.tensor([DEPTH] * 3 + [1.0] * 3, dtype=torch.float64)
    calls = []

    def fake_score(state, hyp, reporter, steps=None):
        calls.append(steps)
        truth = basis["orbit -y"] * (1.0 if steps == 120 else 2.0)
        return float(((hyp.twist - truth) / unit).square().sum()) + (0.0 if steps == 120 else 1.0)

    monkeypatch.setattr(motion_search, "score", fake_score)
    sets = [f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}", "init.search_polls=0"]
    sets.append("init.search_steps=60")
    plain = search_motion(synth_state(synth, *sets))
    assert plain.best.name == "orbit -y ×2" and plain.finals == []
    calls.clear()
    found = search_motion(synth_state(synth, *sets, "init.search_finalists=3", "init.search_final_steps=120"))
    assert calls.count(120) == 3 and len(calls) == len(found.tried) + 3
    assert [h for h, _ in plain.tried] == [h for h, _ in found.tried]  # the short refits as before
    short = sorted(plain.tried, key=lambda hs: hs[1])[:3]
    assert {h for h, _ in found.finals} == {h for h, _ in short}
    assert [s for _, s in found.finals] == sorted(s for _, s in found.finals)
    assert found.best.name == "orbit -y" and found.score == found.finals[0][1] == 0.0
    assert [h.name for h in found.ranked[:3]] == [h for h, _ in found.finals]
    assert [h.name for h in found.ranked[3:]] == [h for h, _ in sorted(plain.tried, key=lambda hs: hs[1])[3:]]
    assert found.steps == 60 * len(found.tried) + 120 * 3


def test_the_finalists_refit_under_their_own_relief_prior(synth, monkeypatch):
    """``init.search_final_depth_tv`` >= 0 is ``loss.depth_tv`` in the finalists' refits alone; the short
    refits keep the run's, and < 0 leaves the finalists the run's too."""
    seen = []

    def fake_score(state, hyp, reporter, steps=None):
        seen.append((steps, state.cfg.loss.depth_tv))
        return float(hyp.twist.norm())

    monkeypatch.setattr(motion_search, "score", fake_score)
    sets = ["init.search_polls=0", "init.search_finalists=2", "loss.depth_tv=0.5"]
    search_motion(synth_state(synth, *sets, "init.search_final_depth_tv=2.0"))
    assert {tv for steps, tv in seen if steps is None} == {0.5}
    assert [tv for steps, tv in seen if steps is not None] == [2.0, 2.0]
    seen.clear()
    search_motion(synth_state(synth, *sets))
    assert {tv for _, tv in seen} == {0.5}


def test_a_finalist_scores_as_a_search_refitting_that_long_would(synth):
    """A finalist's longer refit is the refit a search with ``init.search_steps`` at that length runs:
    the same windows and random numbers, so the same score to the last digit."""
    _, scene = synth
    P = torch.as_tensor(scene.poses)
    short = synth_state(synth, "init.search_steps=10")
    m = short.num_init_chunks()
    truth = Hypothesis("truth", se3_log(se3_inverse(P[0]) @ P[m]) / m)
    longer = score(short, truth, None, 30)
    assert longer == score(synth_state(synth, "init.search_steps=30"), truth, None)
    assert longer != score(short, truth, None)


def test_veered_translations_keep_speed_and_rotation_and_turn_by_the_angle():
    """Four moves: ± the angle towards each of two axes across the translation, which with the
    translation itself are orthogonal."""
    h = Hypothesis("t", torch.tensor([0.01, -0.02, 0.05, 0.0, 0.001, 0.0], dtype=torch.float64), "translate")
    out = veered(h, 20.0)
    assert len(out) == 4 and all(o.family == "translate" for o in out)
    v = h.twist[:3]
    across = []
    for o in out:
        v2 = o.twist[:3]
        assert torch.equal(o.twist[3:], h.twist[3:])
        assert float(v2.norm()) == pytest.approx(float(v.norm()))
        assert np.degrees(np.arccos(float(v2 @ v / v.norm() ** 2))) == pytest.approx(20.0)
        across.append(v2 - v2 @ v / v.norm() ** 2 * v)
    assert torch.allclose(across[0], -across[1]) and torch.allclose(across[2], -across[3])
    assert abs(float(across[0] @ across[2])) < 1e-12


def score_by_distance_to_a_descent(monkeypatch) -> tuple[Tensor, list[str]]:
    """A descent's motion, forward and 12° sideways along -y, as the search's truth: every hypothesis
    scores its squared distance to it (no refits). Returns the truth and the search's settings."""
    ang = np.radians(12.0)
    truth = RATE * DEPTH * torch.tensor([0.0, -np.sin(ang), np.cos(ang), 0, 0, 0], dtype=torch.float64)

    def fake_score(state, hyp, reporter):
        return float(((hyp.twist - truth) / (RATE * DEPTH)).square().sum())

    monkeypatch.setattr(motion_search, "score", fake_score)
    return truth, [f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}", "init.search_polls=0"]


def test_a_winning_translation_is_veered_towards_a_sideways_part(synth, monkeypatch):
    """``init.search_veer``: a descent's motion, forward and 12° sideways along -y, is won by the basis
    approach; veered by 20° and then by 10° back, it comes to within 2° of the true direction. Off,
    the approach stays as it is."""
    truth, sets = score_by_distance_to_a_descent(monkeypatch)
    plain = search_motion(synth_state(synth, *sets))
    assert plain.best.name == "translate +z" and len(plain.tried) == 11 + 8
    found = search_motion(synth_state(synth, *sets, "init.search_veer=20"))
    assert len(found.tried) == 11 + 8 + 12 and found.score < 0.2 * plain.score
    v, t = found.best.twist[:3], truth[:3]
    assert np.degrees(np.arccos(float(v @ t / (v.norm() * t.norm())))) < 2.5
    with pytest.raises(ValueError, match="search_veer < 90"):
        synth_state(synth, *sets, "init.search_veer=90")


def test_a_family_left_out_is_never_scored_and_the_winner_stays(synth, monkeypatch):
    """``init.search_families``: the descent's motion (forward and 12° sideways) is found by the
    translations alone exactly as by the whole basis, without one orbit refitted; orbits alone try no
    translation. An unknown family is refused."""
    _, sets = score_by_distance_to_a_descent(monkeypatch)
    every = search_motion(synth_state(synth, *sets, "init.search_veer=20"))
    moved = search_motion(synth_state(synth, *sets, "init.search_veer=20", "init.search_families=translate"))
    assert moved.best.name == every.best.name and torch.equal(moved.best.twist, every.best.twist)
    assert not any(name.startswith("orbit") for name, _ in moved.tried)
    assert len(moved.tried) == len(every.tried) - 4 - 4  # the basis orbits and the orbit ladder
    turned = search_motion(synth_state(synth, *sets, "init.search_families=orbit"))
    assert {name.split()[0] for name, _ in turned.tried} == {"still", "orbit"}
    assert len(turned.tried) == 1 + 4 + 4
    with pytest.raises(ValueError, match="must be one of"):
        synth_state(synth, *sets, "init.search_families=roll")


def test_a_winning_orbit_is_veered_towards_an_approach(synth, monkeypatch):
    """A swirl's start: an orbit about +y whose camera also closes in, its translation 25° towards the
    optical axis. The basis orbit wins; veered, its translation comes within 6° of the true direction at
    the same rotation."""
    orbit = next(h for h in directions(RATE, DEPTH) if h.name == "orbit +y").twist
    v = orbit[:3]
    ang = np.radians(25.0)
    closing = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) * v.norm()
    truth = torch.cat([np.cos(ang) * v + np.sin(ang) * closing, orbit[3:]])

    def fake_score(state, hyp, reporter):
        return float(((hyp.twist - truth) / (RATE * DEPTH)).square().sum())

    monkeypatch.setattr(motion_search, "score", fake_score)
    sets = [f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}", "init.search_polls=0"]
    plain = search_motion(synth_state(synth, *sets))
    assert plain.best.name == "orbit +y"
    found = search_motion(synth_state(synth, *sets, "init.search_veer=20"))
    assert found.best.name.startswith("orbit +y") and "veer" in found.best.name
    assert len(found.tried) == 11 + 8 + 12 and found.score < 0.2 * plain.score
    got, want = found.best.twist[:3], truth[:3]
    assert np.degrees(np.arccos(float(got @ want / (got.norm() * want.norm())))) < 6.0
    assert torch.equal(found.best.twist[3:], orbit[3:])


def test_with_the_meter_every_hypothesis_advances_as_fast_as_the_meter_closes(synth, monkeypatch):
    """A swirl's start: an orbit about +y whose camera also closes in. The basis orbits do not approach;
    with ``init.search_meter_advance`` every hypothesis is scored with the meter's advance, so the search
    lands on the truth exactly, and the approaches of all sizes coincide into one."""
    state = synth_state(
        synth, f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}", "init.search_polls=0"
    )
    m, _ = search_chunks(state)
    t0, t1 = int(state.data.frames_us[0]), int(state.data.frames_us[m])
    t = np.linspace(t0, t1, 2 * m + 1)
    per_chunk = 0.04  # metres; the first reading is init_depth map units, so 2 m per unit
    metres = 2.0 * DEPTH - per_chunk * np.arange(2 * m + 1) / 2
    state = dataclasses.replace(state, data=dataclasses.replace(state.data, ranges=(t, metres)))
    state = dataclasses.replace(state, cfg=dataclasses.replace(
        state.cfg, init=dataclasses.replace(state.cfg.init, search_meter_advance=True)
    ))  # fmt: skip
    advance = per_chunk / 2.0
    truth = next(h for h in directions(RATE, DEPTH) if h.name == "orbit +y").twist.clone()
    truth[2] = advance

    def fake_score(state, hyp, reporter):
        return float(((hyp.twist - truth) / (RATE * DEPTH)).square().sum())

    monkeypatch.setattr(motion_search, "score", fake_score)
    without = dataclasses.replace(state.cfg.init, search_meter_advance=False)
    plain = search_motion(dataclasses.replace(state, cfg=dataclasses.replace(state.cfg, init=without)))
    found = search_motion(state)
    assert found.best.name == "orbit +y (meter advance 0.02)"
    assert torch.allclose(found.best.twist, truth) and found.score == pytest.approx(0.0, abs=1e-20)
    assert all(h.twist[2] == pytest.approx(advance) for h in found.ranked)
    # The approach and the retreat of every size are now one and the same motion, scored once.
    assert len(found.tried) < len(plain.tried)
    assert len({tuple(h.twist.tolist()) for h in found.ranked}) == len(found.ranked)
    # Sized after the meter set its advance, a motion keeps its size in its name.
    assert found.best.scaled(0.5).advancing(advance).name == "orbit +y ×0.5 (meter advance 0.02)"


def test_search_finds_the_minimum_of_a_known_score(synth, monkeypatch):
    """The search logic alone: a quadratic score around a motion outside the basis (an orbit about y at
    1.7× the nominal rate plus some roll and approach) is found from the basis hypotheses."""
    state = synth_state(synth, f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}",
                        "init.search_polls=48")  # fmt: skip
    orbit_y = next(h for h in directions(RATE, DEPTH) if h.name == "orbit -y").twist
    truth = 1.7 * orbit_y + torch.tensor([0, 0, 0.2 * RATE * DEPTH, 0, 0, 0.3 * RATE], dtype=torch.float64)
    weights = torch.tensor([4.0, 4.0, 1.0, 1.0, 1.0, 1.0], dtype=torch.float64)

    def fake_score(state, hyp, reporter):
        return float((weights * (hyp.twist - truth) ** 2).sum())

    monkeypatch.setattr(motion_search, "score", fake_score)
    found = search_motion(state)
    # No motion, 10 directions, 4 sizes of the best orbit and of the best translation, the compass polls.
    assert found.tried[0][0] == "still" and len(found.tried) == 11 + 8 + 48
    assert found.steps == state.cfg.init.search_steps * len(found.tried)
    assert found.best.name.startswith("orbit -y")
    assert found.score == fake_score(None, found.best, None) == min(s for _, s in found.tried)
    start = min(s for _, s in found.tried[:11])
    assert found.score < 0.05 * start
    assert float((found.best.twist - truth).norm()) < 0.2 * float(truth.norm())


def test_the_compass_starts_from_several_sized_directions(synth, monkeypatch):
    """Two basins (the orbit preset): a shallow one at the basis orbit about -x, and the truth, an orbit
    about -y with roll, whose basis orbit (no roll) scores worse than the -x one. From the best start
    alone the compass stays in the shallow basin; with ``search_starts = 2`` it also climbs from -y."""
    basis = {h.name: h.twist for h in directions(RATE, DEPTH)}
    shallow = basis["orbit -x"]
    truth = basis["orbit -y"] + torch.tensor([0, 0, 0, 0, 0, 0.5 * RATE], dtype=torch.float64)

    def fake_score(state, hyp, reporter):
        a = 0.5 + float(((hyp.twist - shallow) / RATE).square().sum())
        return min(a, 4.0 * float(((hyp.twist - truth) / RATE).square().sum()))

    monkeypatch.setattr(motion_search, "score", fake_score)
    sets = [f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}", "init.search_polls=32"]
    basis_scores = {name: fake_score(None, Hypothesis(name, tw), None) for name, tw in basis.items()}
    assert sorted(basis_scores, key=basis_scores.get)[:2] == ["orbit -x", "orbit -y"]
    one = search_motion(synth_state(synth, *sets, "init.search_sized=2", "init.search_starts=1"))
    assert one.best.name.startswith("orbit -x") and one.score >= 0.5
    two = search_motion(synth_state(synth, *sets, "init.search_sized=2", "init.search_starts=2"))
    assert two.best.name.startswith("orbit -y") and two.score < 0.05
    assert float((two.best.twist - truth).norm()) < 0.1 * float(truth.norm())
    # 11 basis scores, 4 sizes of the 2 best orbits and of the 2 best translations, then 32 new polls
    # from each start.
    assert len(two.tried) == 11 + 16 + 2 * 32
    with pytest.raises(ValueError, match="search_starts"):
        synth_state(synth, *sets, "init.search_sized=1", "init.search_starts=3")
    with pytest.raises(ValueError, match="search_tilt < 90"):
        synth_state(synth, *sets, "init.search_tilt=90")


def test_a_slow_motion_is_sized_before_it_is_compared_with_no_motion(synth, monkeypatch):
    """With ``search_half_rate``, a slow approach (docking_good's is half the nominal rate): at 0.4× the
    nominal rate, every basis motion at the nominal rate scores worse than standing still; the half rate
    must still be tried, and wins."""
    sets = ["init.search_polls=24", "init.search_half_rate=true", "init.search_sized=2"]
    state = synth_state(synth, f"gaussians.init_depth={DEPTH}", f"init.search_rate={RATE}", *sets)
    truth = 0.4 * next(h for h in directions(RATE, DEPTH) if h.name == "translate +z").twist
    monkeypatch.setattr(
        motion_search, "score", lambda state, hyp, reporter: float((hyp.twist - truth).norm())
    )
    found = search_motion(state)
    nominal = {name: s for name, s in found.tried[:21] if "×" not in name}
    assert len(nominal) == 11 and min(nominal, key=nominal.get) == "still"
    # No motion, 10 directions at two rates, 4 sizes of the 2 best of each family (some already scored),
    # the compass polls.
    assert 1 + 20 + 24 < len(found.tried) <= 1 + 20 + 4 * 4 + 24
    assert found.best.name.startswith("translate +z ×0.5")
    assert float((found.best.twist - truth).norm()) < 0.2 * float(truth.norm())


def test_hypotheses_are_fitted_on_some_chunks_and_scored_on_them_and_the_next(synth):
    state = synth_state(synth, "init.num_frames=3", "init.search_frames=4", "init.search_holdout=2")
    n = state.data.n_chunks
    assert n >= 7
    assert search_chunks(state) == (4, 2)
    short = synth_state(synth, "init.num_frames=3", f"init.search_frames={n}", "init.search_holdout=4")
    assert search_chunks(short) == (n - 1, 1)  # at least one chunk is left to score on
    assert (
        search_chunks(
            synth_state(synth, "init.num_frames=5", "init.search_frames=2", "init.search_holdout=1")
        )[0]
        == 5
    )
    # Scored on the fitted chunks only: all of the sequence can be fitted.
    assert search_chunks(synth_state(synth, f"init.search_frames={n}", "init.search_holdout=0")) == (n, 0)


def test_refit_score_prefers_the_true_motion(synth):
    """The principle the search rests on: with the knots frozen, the map refitted to the true motion
    explains the fitted chunks' events better than the map refitted to no motion or the reversed motion;
    scored on the next chunk too, also better than twice the motion."""
    _, scene = synth
    still = Hypothesis("still", torch.zeros(6, dtype=torch.float64))
    # One chunk ahead: the synthetic path accelerates, so a constant velocity extrapolates only so far.
    for holdout, wrong in ((0, (0.0, -1.0)), (1, (0.0, -1.0, 2.0))):
        state = synth_state(synth, "init.search_steps=60", f"init.search_holdout={holdout}")
        m = state.num_init_chunks()
        P = torch.as_tensor(scene.poses)
        truth = Hypothesis("truth", se3_log(se3_inverse(P[0]) @ P[m]) / m)
        s_true = score(state, truth, None)
        for f in wrong:
            assert s_true < score(state, truth.scaled(f) if f else still, None), (holdout, f)


def test_search_sets_the_init_knots_and_records_its_choice(synth):
    state = synth_state(synth, "init.search_steps=5", "init.search_polls=2")
    before = state.gaussians.state()
    found, record = search(state)
    start_from(state, found.best)
    m = state.num_init_chunks()
    assert record.stage == "search" and record.note.startswith("best of ")
    chosen, then = record.note.split(": ", 1)[1].split("; then ")
    assert state.history[-1] is record and chosen == found.best.name
    # The two runners-up with their scores: how close the choice was.
    (_, s1), (_, s2) = sorted(found.tried, key=lambda t: t[1])[1:3]
    assert then.count(", ") == 1 and then.endswith(f"{s2:.5f}") and f"{s1:.5f}" in then
    # Every motion scored, the best first (the branches of init.branches take them in this order).
    assert [h.name for h in found.ranked] == [name for name, _ in sorted(found.tried, key=lambda t: t[1])]
    with torch.no_grad():
        knots = state.traj.knots()
    assert torch.allclose(knots[0], torch.eye(4, dtype=torch.float64))
    assert torch.allclose(knots, found.best.knots(m + 1).to(knots.dtype))
    # The map the initialization starts from is the seeded one, untouched by the trial fits.
    for k, v in state.gaussians.state().items():
        assert torch.equal(v, before[k])
    assert np.isfinite(record.loss)


def test_smooth_refits_run_a_fixed_schedule_and_score_nearby_motions_alike(synth):
    """``init.search_smooth``: no densification, pruning or early switch, so every refit runs all its
    steps on the seeded Gaussians, and motions 2 % apart score far closer than the truth and no motion."""
    _, scene = synth
    state = synth_state(synth, "init.search_steps=60", "init.search_smooth=true", "strategy.refine_start=10")
    m = state.num_init_chunks()
    P = torch.as_tensor(scene.poses)
    truth = Hypothesis("truth", se3_log(se3_inverse(P[0]) @ P[m]) / m)
    trial = motion_search.fit(state, truth.knots(m + 1), None)
    assert len(trial.gaussians) == len(state.gaussians)
    assert trial.history[-1].iterations == 60 and trial.history[-1].pruned_blockers == 0
    s = {f: score(state, truth.scaled(f), None) for f in (0.98, 1.0, 1.02)}
    still = score(state, Hypothesis("still", torch.zeros(6, dtype=torch.float64)), None)
    assert max(abs(s[0.98] - s[1.0]), abs(s[1.02] - s[1.0])) < 0.1 * (still - s[1.0]), (s, still)


def test_the_range_meter_adds_to_the_score_and_leaves_the_refit_alone(synth):
    """``init.search_range_weight``: a meter that contradicts the motion (it reads the camera receding
    5 % per frame) raises the score by the weight times the range term; the refit does not see the
    term (the knots are frozen, the Gaussians are the events'), so the event part is unchanged and the
    score is linear in the weight."""
    from evgs.slam.range_prior import RangePrior

    _, scene = synth
    metres = 5.0 * (1 + 0.05 * np.arange(len(scene.frames_us)))
    P = torch.as_tensor(scene.poses)
    scores = {}
    for weight in (0.0, 10.0, 20.0):
        state = synth_state(synth, "init.search_steps=30")  # the sequence has no meter: added below
        init = dataclasses.replace(state.cfg.init, search_range_weight=weight)
        state.cfg = dataclasses.replace(state.cfg, init=init)
        state.data = dataclasses.replace(state.data, ranges=(scene.frames_us.copy(), metres))
        state.range_prior = RangePrior.for_run(state.cfg, state.data)
        m = state.num_init_chunks()
        scores[weight] = score(state, Hypothesis("truth", se3_log(se3_inverse(P[0]) @ P[m]) / m), None)
    added = scores[10.0] - scores[0.0]
    assert added > 1e-4, scores
    assert scores[20.0] - scores[0.0] == pytest.approx(2 * added, rel=1e-3)


def test_states_are_compared_on_the_event_term_alone(synth):
    """The search's and the branches' score is eq. 8 without its SSIM term, ``(1 − λ)·L_event``: that term
    compares a window's two renders with each other, so it would favour whichever motion changes the view
    least. On a moving trajectory, whose renders differ (SSIM term > 0), the score is that of the event
    term alone, whatever λ."""
    from evgs.slam.loss import event_loss
    from evgs.slam.optimize import fixed_window_loss, fixed_windows

    _, scene = synth
    state = synth_state(synth)
    m = state.num_init_chunks()
    P = torch.as_tensor(scene.poses)
    start_from(state, Hypothesis("truth", se3_log(se3_inverse(P[0]) @ P[m]) / m))
    span, seed = state.data.span(0, m), 7
    terms = [
        event_loss(win.frames, gray[:1], gray[1:], state.cfg.loss)
        for win, gray in fixed_windows(state, span, seed, 4)
    ]
    assert min(float(t.ssim) for t in terms) > 1e-4  # the renders move: the SSIM term would count
    lam = state.cfg.loss.lambda_ssim
    assert lam > 0
    event = float(np.mean([float(t.event) for t in terms]))
    assert fixed_window_loss(state, span, seed, 4) == pytest.approx((1 - lam) * event, rel=1e-6)
    state.cfg = dataclasses.replace(state.cfg, loss=dataclasses.replace(state.cfg.loss, lambda_ssim=0.5))
    assert fixed_window_loss(state, span, seed, 4) == pytest.approx(0.5 * event, rel=1e-6)

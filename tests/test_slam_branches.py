"""The run's start in branches (``init.branches``): each motion runs the initialization and
``init.branch_frames`` tracked frames, the branch that explains those chunks best goes on."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("evgs.render")

from evgs.config import ConfigError, load_config  # noqa: E402
from evgs.slam.branches import branch_score, run_branches  # noqa: E402
from evgs.slam.lie import se3_inverse, se3_log  # noqa: E402
from evgs.slam.motion_search import Hypothesis  # noqa: E402
from evgs.slam.stages import initialize, start_from, step_chunk  # noqa: E402
from evgs.slam.state import StageRecord  # noqa: E402
from slam_synth import make_sequence, search_state  # noqa: E402

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


def test_branch_settings_are_checked():
    with pytest.raises(ConfigError, match="init.branches must be >= 1"):
        load_config("synthetic/tiny", ["init.branches=0"])
    with pytest.raises(ConfigError, match="init.branch_frames >= 0"):
        load_config("synthetic/tiny", ["init.branch_frames=-1"])
    with pytest.raises(ConfigError, match="init.branches > 1 needs init.motion_search"):
        load_config("synthetic/tiny", ["init.branches=2", "init.motion_search=false"])

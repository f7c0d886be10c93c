"""Everything a SLAM run carries from stage to stage, and where it is in the sequence.

Every random choice draws from ``generator`` (Gaussians, initial knots, splits, new Gaussians) or from a
sampler seeded by :func:`stage_seed`, so restoring the generator's state at a stage boundary makes the
continuation of a run identical to an uninterrupted one.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from evgs.config import Config
from evgs.slam.gaussians import Gaussians
from evgs.slam.guards import BrightnessAnchor
from evgs.slam.range_prior import RangePrior
from evgs.slam.trajectory import Trajectory
from evgs.slam.windows import EventData

if TYPE_CHECKING:
    from evgs.slam.metric_scale import ScaleEstimate

STAGES = ("init", "track", "map", "gba", "final", "search", "branch", "rate", "seeding")


def stage_seed(seed: int, stage: str, frame: int) -> int:
    """A sampler seed per (run seed, stage, frame): independent streams, no state to checkpoint."""
    return int(np.random.SeedSequence([seed, STAGES.index(stage), frame]).generate_state(1, np.uint64)[0])


@dataclass
class Position:
    """Where the run is: ``next_chunk`` is the next chunk to track (== number of knots − 1)."""

    initialized: bool = False
    next_chunk: int = 0
    since_mapping: int = 0
    finished: bool = False


@dataclass
class StageRecord:
    """One finished stage, for the log and metrics.json."""

    stage: str
    frame: int
    iterations: int
    loss: float
    seconds: float
    events: int
    stopped_early: bool
    n_gaussians: int
    pruned_blockers: int = 0
    added: int = 0
    note: str = ""  # what the stage chose (the motion search's hypothesis)


@dataclass
class SlamState:
    cfg: Config
    data: EventData
    traj: Trajectory
    gaussians: Gaussians
    generator: torch.Generator
    anchor: BrightnessAnchor
    position: Position = field(default_factory=Position)
    history: list[StageRecord] = field(default_factory=list)
    metric: dict = field(default_factory=dict)  # the metric-scale estimate applied to the outputs
    range_prior: RangePrior | None = None  # the range meter's loss term (scale.range_weight > 0)
    surface_scale: ScaleEstimate | None = None  # the first-surface scale read before the final global BA
    branch: str = ""  # a branch of the run's start (evgs.slam.branches) names its diagnostics; "" = the run
    seeding: int = 0  # whose draws seeded the map: 0 the run's own, j > 0 restart j's (evgs.slam.seeding)

    def with_relief_prior(self, depth_tv: float) -> SlamState:
        """This state with ``loss.depth_tv`` = ``depth_tv`` when that is >= 0, else this state itself: a
        stage's refits under their own relief prior, which bends a speed's score (docs/ablations.md
        §78, §93)."""
        if depth_tv < 0:
            return self
        return replace(self, cfg=replace(self.cfg, loss=replace(self.cfg.loss, depth_tv=depth_tv)))

    def num_init_chunks(self) -> int:
        """``m``: chunks of the initialization (fewer when the sequence is shorter)."""
        return min(self.cfg.init.num_frames, self.data.n_chunks)

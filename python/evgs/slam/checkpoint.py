"""Checkpoints at stage boundaries: everything a run needs to continue exactly as if never stopped.

Taken only between frames, where no optimizer or densification statistics are alive (every stage
builds its own Adam and strategy, and the trajectory is rebased), so the state is the trajectory
knots, the Gaussians, the random generator, the brightness reference, the position in the sequence,
the map's seeding (a refit from scratch redraws it) and, once read, the first-surface scale (read before
the final global BA: the final map reads another). Window samplers are re-seeded per stage from the run
seed, so they need no state.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from evgs.config import Config
from evgs.io_util import atomic_path
from evgs.slam.gaussians import Gaussians
from evgs.slam.guards import BrightnessAnchor
from evgs.slam.metric_scale import ScaleEstimate
from evgs.slam.range_prior import RangePrior
from evgs.slam.state import Position, SlamState, StageRecord
from evgs.slam.trajectory import Trajectory
from evgs.slam.windows import EventData

VERSION = 1
CHECKPOINT_NAME = "latest.pt"


def snapshot(state: SlamState) -> dict:
    """A detached copy of the state (cheap; kept in memory at every boundary for Ctrl-C)."""
    return {
        "version": VERSION,
        "trajectory": state.traj.state(),
        "gaussians": state.gaussians.state(),
        "generator": state.generator.get_state().clone(),
        "anchor_reference": state.anchor.reference,
        "position": asdict(state.position),
        "history": [asdict(r) for r in state.history],
        "dropped_events": state.data.dropped,
        "surface_scale": None if state.surface_scale is None else asdict(state.surface_scale),
        "seeding": state.seeding,
    }


def save(path: str | Path, snap: dict) -> None:
    with atomic_path(path) as tmp:
        torch.save(snap, tmp)


def load(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no checkpoint (the run stopped before its first stage boundary)")
    try:
        snap = torch.load(path, weights_only=True)
    except Exception as e:  # torch raises several types for damaged files
        raise ValueError(f"{path}: unreadable checkpoint: {e}") from None
    if not isinstance(snap, dict) or snap.get("version") != VERSION:
        raise ValueError(f"{path}: not an evgs checkpoint of version {VERSION}")
    return snap


def restore(snap: dict, cfg: Config, data: EventData) -> SlamState:
    generator = torch.Generator()
    generator.set_state(snap["generator"])
    data.dropped = int(snap["dropped_events"])
    return SlamState(
        cfg=cfg,
        data=data,
        traj=Trajectory.from_state(snap["trajectory"]),
        gaussians=Gaussians.from_state(snap["gaussians"]),
        generator=generator,
        anchor=BrightnessAnchor(cfg.guards.brightness_weight, snap["anchor_reference"]),
        position=Position(**snap["position"]),
        history=[StageRecord(**r) for r in snap["history"]],
        range_prior=RangePrior.for_run(cfg, data),
        # .get: a checkpoint written before the key existed read the scale at the end (the fallback)
        surface_scale=None if snap.get("surface_scale") is None else ScaleEstimate(**snap["surface_scale"]),
        seeding=snap.get("seeding", 0),  # .get: written before the key existed, the run's own seeding
    )

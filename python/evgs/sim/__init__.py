"""The event-sequence simulator: procedural spacecraft (or any mesh), lights, trajectories, a float
renderer and ESIM event generation (Rust), written as canonical sequences with ground truth.

Attributes load on first use so that ``evgs --help`` does not pay for scipy, trimesh and moderngl.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from evgs.sim.driver import ensure_sequence, simulate
    from evgs.sim.presets import PRESETS, SimConfig, preset

_LAZY = {
    "PRESETS": "evgs.sim.presets",
    "SimConfig": "evgs.sim.presets",
    "preset": "evgs.sim.presets",
    "ensure_sequence": "evgs.sim.driver",
    "simulate": "evgs.sim.driver",
}

__all__ = ["PRESETS", "SimConfig", "ensure_sequence", "preset", "simulate"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'evgs.sim' has no attribute {name!r}")

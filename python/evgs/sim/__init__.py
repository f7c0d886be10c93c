"""The event-sequence simulator: procedural spacecraft (or any mesh), lights, trajectories, a float
renderer and ESIM event generation (Rust), written as canonical sequences with ground truth."""

from evgs.sim.presets import PRESETS, SimConfig, preset
from evgs.sim.simulate import ensure_sequence, simulate

__all__ = ["PRESETS", "SimConfig", "ensure_sequence", "preset", "simulate"]

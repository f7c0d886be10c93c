"""A deterministic synthetic event stream (for the demo, tests and benchmarks; not a camera model)."""

from __future__ import annotations

import numpy as np

from evgs.events.arrays import EventArray


def synthetic_events(
    n: int, width: int = 640, height: int = 480, seed: int = 0, rate_hz: float = 2e6
) -> EventArray:
    """``n`` sorted events around a blob circling the sensor: Poisson arrivals at ``rate_hz``,
    Gaussian spatial spread, random polarity. Identical for identical arguments."""
    rng = np.random.default_rng(seed)
    t = np.floor(np.cumsum(rng.exponential(1e6 / rate_hz, n))).astype(np.int64)
    phase = t * (2 * np.pi * 0.5e-6)
    cx = width / 2 + width / 4 * np.cos(phase)
    cy = height / 2 + height / 4 * np.sin(phase)
    x = np.clip(np.rint(cx + rng.normal(0, width / 30, n)), 0, width - 1).astype(np.uint16)
    y = np.clip(np.rint(cy + rng.normal(0, height / 30, n)), 0, height - 1).astype(np.uint16)
    p = np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8)
    return EventArray(t, x, y, p, width, height)

"""The Python face of an event stream: four numpy columns plus the sensor size."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evgs import _core


@dataclass(frozen=True)
class EventArray:
    """Events as struct-of-arrays: ``t`` int64 µs, ``x``/``y`` uint16, ``p`` int8 (±1).

    Columns are usually views of buffers the Rust core allocated (no copy on hand-off).
    ``width``/``height`` are the sensor size (0 when unknown).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    p: np.ndarray
    width: int = 0
    height: int = 0

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @classmethod
    def from_columns(cls, cols: dict) -> EventArray:
        """Build from a mapping with t/x/y/p (and optionally width/height), casting to canonical dtypes."""
        return cls(
            t=np.ascontiguousarray(cols["t"], dtype=np.int64),
            x=np.ascontiguousarray(cols["x"], dtype=np.uint16),
            y=np.ascontiguousarray(cols["y"], dtype=np.uint16),
            p=np.ascontiguousarray(cols["p"], dtype=np.int8),
            width=int(cols.get("width", 0)),
            height=int(cols.get("height", 0)),
        )

    def slice(self, start: int, stop: int) -> EventArray:
        """Events ``start:stop`` (views, no copy)."""
        s = slice(start, stop)
        return EventArray(self.t[s], self.x[s], self.y[s], self.p[s], self.width, self.height)

    def validate(self, source: str) -> None:
        """Raise ValueError (naming ``source`` and the event index) if an invariant is broken."""
        _core.validate_events(self.t, self.x, self.y, self.p, self.width, self.height, source)

    @property
    def duration_us(self) -> int:
        return int(self.t[-1] - self.t[0]) if len(self) else 0

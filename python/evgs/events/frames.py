"""Chunks, event windows and event frames: a thin typed layer over the Rust core (``src/events/``).

- ``chunk_ranges``: chunk ``k`` holds the events with ``frame_t[k] <= t < frame_t[k+1]`` (half-open, so
  no event on a frame timestamp is lost or counted twice; the paper's eq. 5 writes strict inequalities).
- ``WindowSampler``: the paper's §3.1 windows counted in events (``mode="paper"``) or the public
  reference code's variant (``mode="reference"``), seeded and reproducible on every platform.
- ``accumulate``: ``E = c_on * n_on - c_off * n_off`` for a batch of windows, optionally undistorted
  (bilinear splat at each pixel's undistorted position) and downsampled.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, overload

import numpy as np

from evgs import _core
from evgs.data.sequence import Camera
from evgs.events.arrays import EventArray


def chunk_ranges(t: np.ndarray, frame_t: np.ndarray) -> np.ndarray:
    """``(F-1, 2)`` int64 half-open event index ranges ``[start, end)`` between consecutive frame times.

    ``t`` must be sorted and ``frame_t`` strictly increasing (ValueError otherwise). Events before
    ``frame_t[0]`` or at/after ``frame_t[-1]`` are in no chunk: ``ranges[0, 0]`` and
    ``len(t) - ranges[-1, 1]`` count them.
    """
    bounds = _core.chunk_bounds(
        np.ascontiguousarray(t, dtype=np.int64), np.ascontiguousarray(frame_t, dtype=np.int64)
    )
    return np.stack([bounds[:-1], bounds[1:]], axis=1)


class WindowSampler:
    """Seeded batches of event windows ``[start, end)`` within an event index range.

    ``events`` is the number of events ``N`` (range ``[0, N)``) or a ``(start, end)`` index range, e.g. a
    chunk from ``chunk_ranges`` or a sliding window of chunks. Paper mode clamps ``max_n_winsize`` to the
    events available and raises ValueError when ``min_n_winsize`` cannot be met; reference mode uses
    ``seg_num`` candidate ends ``linspace(10, N - 10, seg_num)`` and raises when none survive.
    """

    def __init__(
        self,
        events: int | tuple[int, int],
        min_n_winsize: int,
        max_n_winsize: int,
        seed: int,
        mode: Literal["paper", "reference"] = "paper",
        seg_num: int = 100,
    ) -> None:
        start, end = (0, events) if isinstance(events, int | np.integer) else events
        self._core = _core.WindowSampler(
            int(start), int(end), int(min_n_winsize), int(max_n_winsize), int(seed), mode, int(seg_num)
        )

    @property
    def sizes(self) -> tuple[int, int]:
        """Effective ``(min, max)`` window size in events (max after clamping)."""
        return self._core.sizes

    def sample(self, batch: int) -> tuple[np.ndarray, np.ndarray]:
        """``(starts, ends)``, each ``(batch,)`` int64 absolute event indices."""
        return self._core.sample(int(batch))


@dataclass(frozen=True)
class UndistortMap:
    """Undistorted position ``uv[y, x] = (u, v)`` of every sensor pixel centre (NaN where the OpenCV
    ``k1 k2 p1 p2 k3`` model cannot be inverted). Built once per camera, reused for every frame."""

    uv: np.ndarray  # (H, W, 2) float32

    @classmethod
    def from_camera(cls, camera: Camera) -> UndistortMap:
        flat = _core.undistort_map(
            camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, list(camera.distortion)
        )
        return cls(flat.reshape(camera.height, camera.width, 2))

    @property
    def width(self) -> int:
        return int(self.uv.shape[1])

    @property
    def height(self) -> int:
        return int(self.uv.shape[0])

    @property
    def n_invalid(self) -> int:
        """Pixels whose undistortion failed (their events are always dropped)."""
        return int(np.isnan(self.uv[..., 0]).sum())


@overload
def accumulate(
    ev: EventArray,
    starts: np.ndarray,
    ends: np.ndarray,
    *,
    c_on: float = ...,
    c_off: float | None = ...,
    undistort: UndistortMap | None = ...,
    downsample: int = ...,
    out: np.ndarray | None = ...,
    return_dropped: Literal[False] = ...,
) -> np.ndarray: ...
@overload
def accumulate(
    ev: EventArray,
    starts: np.ndarray,
    ends: np.ndarray,
    *,
    c_on: float = ...,
    c_off: float | None = ...,
    undistort: UndistortMap | None = ...,
    downsample: int = ...,
    out: np.ndarray | None = ...,
    return_dropped: Literal[True],
) -> tuple[np.ndarray, np.ndarray]: ...
def accumulate(
    ev: EventArray,
    starts: np.ndarray,
    ends: np.ndarray,
    *,
    c_on: float = 1.0,
    c_off: float | None = None,
    undistort: UndistortMap | None = None,
    downsample: int = 1,
    out: np.ndarray | None = None,
    return_dropped: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Event frames ``(B, H, W)`` float32 of the windows ``[starts[b], ends[b])``.

    ``E = c_on * n_on - c_off * n_off`` per pixel (``c_off`` defaults to ``c_on``: the paper's single C).
    ``undistort`` moves events to their undistorted positions (bilinear splat); events that land outside
    the image are counted per window, returned as ``(B,)`` int64 when ``return_dropped`` is true.
    ``downsample`` (a power of two) sums ``f x f`` pixel blocks; the frame is ``ceil(H/f) x ceil(W/f)``.
    ``out``: a C-contiguous float32 ``(B, H, W)`` array to overwrite and return (reusing one across
    iterations avoids the page faults of fresh output memory, which dominate for small windows).
    """
    if downsample < 1 or downsample & (downsample - 1):
        raise ValueError(f"event frames: downsample must be a power of two, got {downsample}")
    uv = None
    if undistort is not None:
        if (undistort.height, undistort.width) != (ev.height, ev.width):
            raise ValueError(
                f"event frames: undistortion map is {undistort.width}x{undistort.height} "
                f"but the events are {ev.width}x{ev.height}"
            )
        uv = np.ascontiguousarray(undistort.uv, dtype=np.float32).reshape(-1)
    starts = np.ascontiguousarray(starts, dtype=np.int64)
    out_flat = None
    if out is not None:
        shape = (len(starts), -(-ev.height // downsample), -(-ev.width // downsample))
        if out.dtype != np.float32 or out.shape != shape or not out.flags.c_contiguous:
            raise ValueError(
                f"event frames: out must be a C-contiguous float32 array of shape {shape}, "
                f"got {out.dtype} {out.shape}"
            )
        out_flat = out.reshape(-1)
    flat, w, h, dropped = _core.accumulate_frames(
        ev.t, ev.x, ev.y, ev.p, ev.width, ev.height, starts, np.ascontiguousarray(ends, dtype=np.int64),
        float(c_on), float(c_on if c_off is None else c_off), downsample.bit_length() - 1, uv, out_flat,
    )  # fmt: skip
    frames = flat.reshape(-1, h, w) if out is None else out
    return (frames, dropped.astype(np.int64)) if return_dropped else frames

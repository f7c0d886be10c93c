"""The event side of an optimisation step: a sequence's events cut into chunks at frame timestamps, event
windows drawn by the Rust sampler over an index range, and their event frames from Rust accumulation.

A window ``[start, end)`` is observed between the timestamps of its first and last event; the frame
``E = C·Σp`` is what the renders at those two times must explain. At a coarse level ``f`` the frame sums
``f×f`` pixel blocks, so it is divided by ``f²`` to stay a per-pixel log-intensity change, and the camera
is the same pinhole with its intrinsics scaled by ``1/f``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from evgs.config import DataConfig
from evgs.data.sequence import Camera, Sequence
from evgs.events.arrays import EventArray
from evgs.events.frames import UndistortMap, WindowSampler, accumulate, chunk_ranges


@dataclass(frozen=True)
class Windows:
    """A batch of B event windows and their event frames."""

    starts: np.ndarray  # (B,) int64 first event index
    ends: np.ndarray  # (B,) int64 one past the last event
    t_start: np.ndarray  # (B,) µs of the first event
    t_end: np.ndarray  # (B,) µs of the last event
    frames: Tensor  # (B, h, w) float32 event frames E at the level's resolution

    @property
    def n_events(self) -> int:
        return int((self.ends - self.starts).sum())


def scaled_camera(camera: Camera, factor: int) -> Camera:
    """The pinhole camera of a ``factor``-times downsampled image (``ceil`` size, as accumulation): coarse
    pixel ``j`` gathers fine pixels ``j·factor … j·factor + factor − 1``, so its centre (OpenCV, as
    ``camera``) is at fine ``j·factor + (factor − 1) / 2``."""
    if factor == 1:
        return camera
    return replace(
        camera,
        width=math.ceil(camera.width / factor),
        height=math.ceil(camera.height / factor),
        fx=camera.fx / factor,
        fy=camera.fy / factor,
        cx=(camera.cx + 0.5) / factor - 0.5,
        cy=(camera.cy + 0.5) / factor - 0.5,
    )


@dataclass
class EventData:
    """Events and chunks of the frames a run uses (``data.start_frame``, ``data.num_frames``)."""

    events: EventArray
    frames_us: np.ndarray  # (F,) frame timestamps used; chunk k lies between frames k and k+1
    chunks: np.ndarray  # (F-1, 2) half-open event index ranges
    camera: Camera
    contrast: float
    cfg: DataConfig
    undistort: UndistortMap | None = None
    ranges: tuple[np.ndarray, np.ndarray] | None = None  # range meter (t_us, metres), for metric scale
    dropped: int = field(default=0)  # events undistorted outside the image, over every frame made

    @classmethod
    def from_sequence(cls, seq: Sequence, cfg: DataConfig) -> EventData:
        frames = seq.frames_us()
        # data.start_frame counts in the data set's own numbering (the paper's frame ranges); an import
        # with --frames A:B renumbers from 0 and records A as frame_offset.
        offset = int(seq.meta.get("frame_offset", 0))
        first = cfg.start_frame - offset
        if first < 0:
            raise ValueError(
                f"{seq.root / 'sequence.toml'}: data.start_frame = {cfg.start_frame} lies before the "
                f"imported range, which starts at frame {offset} (frame_offset)"
            )
        last = len(frames) if cfg.num_frames == 0 else min(len(frames), first + cfg.num_frames + 1)
        frames = frames[first:last]
        if len(frames) < 2:
            raise ValueError(
                f"{seq.root / 'frames.csv'}: data.start_frame = {cfg.start_frame} leaves "
                f"{len(frames)} frame(s); at least 2 are needed for one chunk of events"
            )
        events = seq.events()
        undistort = UndistortMap.from_camera(seq.camera) if any(seq.camera.distortion) else None
        return cls(
            events, frames, chunk_ranges(events.t, frames), seq.camera, cfg.event_contrast, cfg, undistort,
            ranges=seq.range_samples(),
        )  # fmt: skip

    @property
    def n_chunks(self) -> int:
        return len(self.chunks)

    def span(self, first: int, stop: int) -> tuple[int, int]:
        """Event index range of chunks ``first .. stop-1``."""
        return int(self.chunks[first, 0]), int(self.chunks[stop - 1, 1])

    def span_with_min(self, first: int, stop: int) -> tuple[int, int]:
        """Like :meth:`span`, extended backwards by whole chunks (not before chunk 0) until it holds at
        least ``min_n_winsize`` events, so a sparse chunk can still be sampled."""
        while first > 0 and self.span(first, stop)[1] - self.span(first, stop)[0] < self.cfg.min_n_winsize:
            first -= 1
        return self.span(first, stop)

    def time_span(self, span: tuple[int, int]) -> tuple[int, int]:
        """µs of the frames enclosing the events of index range ``span`` (its chunks' boundaries)."""
        t, f = self.events.t, self.frames_us
        first = max(int(np.searchsorted(f, t[span[0]], side="right")) - 1, 0)
        last = min(int(np.searchsorted(f, t[span[1] - 1], side="right")), len(f) - 1)
        return int(f[first]), int(f[last])

    def sampler(self, span: tuple[int, int], seed: int, max_window: int = 0) -> WindowSampler:
        """Windows of the events ``span``, at most ``max_window`` events long (0 = ``data.max_n_winsize``)."""
        c = self.cfg
        try:
            longest = max_window or c.max_n_winsize
            return WindowSampler(span, c.min_n_winsize, longest, seed, c.window_mode, c.seg_num)
        except ValueError as e:
            raise ValueError(
                f"events {span[0]}..{span[1]} ({span[1] - span[0]} events): {e}; lower data.min_n_winsize"
            ) from None

    def frames_of(self, starts: np.ndarray, ends: np.ndarray, factor: int = 1) -> Tensor:
        """(B, h, w) event frames of the windows at level ``factor`` (dropped events are counted)."""
        frames, dropped = accumulate(
            self.events, starts, ends, c_on=self.contrast, undistort=self.undistort,
            downsample=factor, return_dropped=True,
        )  # fmt: skip
        self.dropped += int(dropped.sum())
        return torch.from_numpy(frames) / float(factor * factor)

    def activity(self, span: tuple[int, int]) -> Tensor:
        """(H, W) number of events per pixel over an index range (both polarities counted)."""
        counts = accumulate(
            self.events, np.array([span[0]]), np.array([span[1]]), c_on=1.0, c_off=-1.0,
            undistort=self.undistort,
        )  # fmt: skip
        return torch.from_numpy(counts[0])

    def windows(self, sampler: WindowSampler, batch: int, factor: int = 1) -> Windows:
        starts, ends = sampler.sample(batch)
        t = self.events.t
        return Windows(starts, ends, t[starts], t[ends - 1], self.frames_of(starts, ends, factor))

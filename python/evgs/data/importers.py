"""What every data-set adapter shares: the in-memory result of reading a raw download, frame-range
selection, and the atomic write of the canonical layout (``evgs.data.sequence``) plus extra tables.

An adapter module has ``DESCRIPTION``, ``RAW_PATH_HELP``, ``add_arguments(parser)`` and
``load(path, progress, **options) -> Imported`` (the options are its arguments' ``dest`` names);
``ADAPTERS`` maps the ``evgs import`` name to it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import polars as pl
from rich.progress import Progress

from evgs.data.sequence import Camera, Sequence, write_sequence
from evgs.events.arrays import EventArray
from evgs.events.io import open_events

ADAPTERS = {
    "seenic": "evgs.data.seenic",
    "ems": "evgs.data.ems",
    "elope": "evgs.data.elope",
    "replica": "evgs.data.replica",
    "rpg": "evgs.data.rpg",
}


# Images are imported as the data sets store them, so image metrics compare with published numbers.
IMAGE_NOTE = "source pixel values scaled to [0, 1], grey; not linearised"


@dataclass
class Imported:
    """A raw sequence converted to evgs conventions, before it is written.

    ``images`` are file paths aligned with ``frames_us`` (read one at a time when writing); ``tables``
    are extra CSVs with a ``t_us`` column (e.g. ``velocities_gt.csv``), cropped with the frames;
    ``notes`` are counts and choices reported to the user.
    """

    name: str
    camera: Camera
    events: EventArray
    frames_us: np.ndarray
    poses_gt: tuple[np.ndarray, np.ndarray] | None = None
    images: list[Path] | None = None
    range_samples: tuple[np.ndarray, np.ndarray] | None = None
    tables: dict[str, pl.DataFrame] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def finish_events(ev: EventArray, camera: Camera, source: str, notes: list[str]) -> EventArray:
    """Attach the sensor size, validate (polarity, bounds) and sort by time if needed (stable, counted)."""
    ev = EventArray(ev.t, ev.x, ev.y, ev.p, camera.width, camera.height)
    ev.validate(source)
    if len(ev) == 0:
        raise ValueError(f"{source}: no events")
    unsorted = int(np.count_nonzero(np.diff(ev.t) < 0))
    if unsorted:
        order = np.argsort(ev.t, kind="stable")
        ev = EventArray(ev.t[order], ev.x[order], ev.y[order], ev.p[order], ev.width, ev.height)
        notes.append(f"{source}: {unsorted} out-of-order timestamps; events sorted by time (none dropped)")
    return ev


def read_events_tracked(path: Path, fmt: str, progress: Progress, notes: list[str], **options) -> EventArray:
    """Read a whole event file in batches, advancing a progress bar by file position; anything the
    reader skipped goes into ``notes``."""
    source = open_events(path, fmt, **options)
    task = progress.add_task(f"reading {path.name}", total=1.0)
    parts = []
    for batch in source.batches():
        parts.append(batch)
        progress.update(task, completed=source.progress)
    progress.update(task, completed=1.0)
    skipped = {k: v for k, v in source.skipped.items() if v}
    if skipped:
        notes.append(f"{path}: reader skipped {', '.join(f'{v} {k}' for k, v in skipped.items())}")
    if not parts:
        raise ValueError(f"{path}: no events")
    return EventArray(*(np.concatenate([getattr(b, c) for b in parts]) for c in "txyp"))


def check_frames(frames_us: np.ndarray, source: str) -> np.ndarray:
    frames_us = np.asarray(frames_us, np.int64)
    if len(frames_us) < 2:
        raise ValueError(f"{source}: need at least 2 frame timestamps, got {len(frames_us)}")
    bad = np.diff(frames_us) <= 0
    if np.any(bad):
        i = int(np.argmax(bad)) + 1
        raise ValueError(f"{source}: frame {i}: timestamps must be strictly increasing")
    return frames_us


def parse_frames(spec: str) -> tuple[int | None, int | None]:
    """``"A:B"`` (either side may be empty) → a half-open frame-index range."""
    parts = spec.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a, b = (int(s) if s.strip() else None for s in parts)
    except ValueError:
        raise ValueError(f"--frames {spec!r}: expected A:B with frame indices (e.g. 375:426)") from None
    return a, b


def select_frames(seq: Imported, first: int | None, stop: int | None) -> Imported:
    """Keep frames ``first:stop`` (Python slice, re-indexed from 0) and everything timed between the
    first and the last kept frame; the original index of frame 0 goes to ``meta["frame_offset"]``."""
    n = len(seq.frames_us)
    a, b, _ = slice(first, stop).indices(n)
    if b - a < 2:
        raise ValueError(f"--frames {first}:{stop}: selects {max(b - a, 0)} of {n} frames; need at least 2")
    t0, t1 = int(seq.frames_us[a]), int(seq.frames_us[b - 1])

    def window(t: np.ndarray) -> np.ndarray:
        return (t >= t0) & (t <= t1)

    lo = int(np.searchsorted(seq.events.t, t0, side="left"))
    hi = int(np.searchsorted(seq.events.t, t1, side="right"))
    notes = [
        *seq.notes,
        f"--frames {a}:{b}: kept {hi - lo} of {len(seq.events)} events, {b - a} of {n} frames",
    ]
    poses = None
    if seq.poses_gt is not None:
        keep = window(seq.poses_gt[0])
        poses = (seq.poses_gt[0][keep], seq.poses_gt[1][keep])
        notes.append(f"--frames {a}:{b}: kept {int(keep.sum())} of {len(keep)} ground-truth poses")
    rng = None
    if seq.range_samples is not None:
        keep = window(seq.range_samples[0])
        rng = (seq.range_samples[0][keep], seq.range_samples[1][keep])
    tables = {k: df.filter(pl.col("t_us").is_between(t0, t1)) for k, df in seq.tables.items()}
    return replace(
        seq,
        events=seq.events.slice(lo, hi),
        frames_us=seq.frames_us[a:b],
        poses_gt=poses,
        images=None if seq.images is None else seq.images[a:b],
        range_samples=rng,
        tables=tables,
        meta={**seq.meta, "frame_offset": seq.meta.get("frame_offset", 0) + a},
        notes=notes,
    )


def float_list(n: int) -> Callable[[str], tuple[float, ...]]:
    """An argparse ``type`` for ``n`` comma-separated numbers."""

    def parse(s: str) -> tuple[float, ...]:
        vals = tuple(float(v) for v in s.split(","))
        if len(vals) != n:
            raise ValueError(f"{s!r}: expected {n} comma-separated numbers")
        return vals

    parse.__name__ = f"list of {n} numbers"
    return parse


def parse_size(s: str) -> tuple[int, int]:
    """An argparse ``type`` for ``WxH``."""
    w, _, h = s.lower().partition("x")
    return int(w), int(h)


def read_gray(path: Path, camera: Camera) -> np.ndarray:
    """An image file as float32 grey in [0, 1] (8- or 16-bit, grey or colour), checked against the camera."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: unreadable image")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.shape != (camera.height, camera.width):
        raise ValueError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]}, the camera is {camera.width}x{camera.height}"
        )
    return img.astype(np.float32) / float(np.iinfo(img.dtype).max if img.dtype.kind == "u" else 1.0)


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: unreadable image")
    return int(img.shape[1]), int(img.shape[0])


def write_imported(seq: Imported, out: Path, progress: Progress) -> Sequence:
    """Write ``seq`` to ``out`` as a canonical sequence folder (all or nothing, see ``write_sequence``),
    reading the images one at a time."""
    images = None
    if seq.images is not None:
        task = progress.add_task("writing images", total=len(seq.images))
        images = _track_images(seq.images, seq.camera, progress, task)
    meta = seq.meta if images is None else {**seq.meta, "images": IMAGE_NOTE}
    return write_sequence(
        out, seq.name, seq.camera, seq.events, seq.frames_us, poses_gt=seq.poses_gt,
        images=images, range_samples=seq.range_samples, meta=meta, tables=seq.tables,
    )  # fmt: skip


def _track_images(paths: list[Path], camera: Camera, progress: Progress, task) -> Iterator[np.ndarray]:
    for p in paths:
        yield read_gray(p, camera)
        progress.advance(task)

"""ESIM / RPG event-camera data set layout.

A folder with ``events.txt`` (``t x y p``: t in seconds, p ∈ {0, 1}), ``groundtruth.txt`` (TUM-like
``t tx ty tz qx qy qz qw``, the camera in the world), ``calib.txt`` (``fx fy cx cy`` then optional
OpenCV ``k1 k2 p1 p2 [k3]``) and optionally ``images.txt`` (``t path`` per line) with ``images/``.

Frames are the image timestamps, or the ground-truth timestamps when there are no images. The size comes
from the images, or ``--size`` without them (DAVIS240: 240x180).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from rich.progress import Progress

from evgs.data.importers import (
    Imported,
    check_frames,
    finish_events,
    image_size,
    parse_size,
    read_events_tracked,
)
from evgs.data.rawtext import read_rows, seconds_to_us
from evgs.data.sequence import Camera
from evgs.data.tum import read_tum

DESCRIPTION = "ESIM/RPG folder (events.txt, groundtruth.txt, calib.txt, images.txt + images/)"
RAW_PATH_HELP = "a folder holding events.txt, groundtruth.txt and calib.txt"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--size", type=parse_size, metavar="WxH", help="sensor size (default: from images/)")


def load(path: Path, progress: Progress, *, size: tuple[int, int] | None = None) -> Imported:
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: folder not found ({RAW_PATH_HELP})")
    calib, _ = read_rows(path / "calib.txt", (4, 8, 9), "fx fy cx cy [k1 k2 p1 p2 [k3]]")
    gt_path = path / "groundtruth.txt"
    if not gt_path.is_file():
        raise FileNotFoundError(f"{gt_path}: not found (expected t tx ty tz qx qy qz qw per line)")
    t_gt, T_wc = read_tum(gt_path)
    t_gt_us = seconds_to_us(t_gt)

    images: list[Path] = []
    if (path / "images.txt").is_file():
        t_img, images = _read_image_list(path / "images.txt")
        frames = check_frames(t_img, str(path / "images.txt"))
    else:
        frames = check_frames(t_gt_us, str(gt_path))
    if size is None:
        if not images:
            raise ValueError(f"{path}: no images.txt to take the sensor size from; pass --size WxH")
        size = image_size(images[0])
    camera = Camera(size[0], size[1], *calib[0, :4], tuple(calib[0, 4:]))

    notes: list[str] = []
    ev_path = path / "events.txt"
    if not ev_path.is_file():
        raise FileNotFoundError(f"{ev_path}: not found (expected t[s] x y p per line)")
    raw = read_events_tracked(
        ev_path, "txt", progress, notes, columns="txyp", time_unit="s", width=camera.width,
        height=camera.height,
    )  # fmt: skip
    events = finish_events(raw, camera, str(ev_path), notes)
    meta = {"source": "rpg", "raw_path": str(path.resolve())}
    return Imported(
        path.resolve().name, camera, events, frames, poses_gt=(t_gt_us, T_wc),
        images=images or None, meta=meta, notes=notes,
    )  # fmt: skip


def _read_image_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    """``images.txt``: ``t[s] relative/path.png`` per line → (t µs, absolute paths that exist)."""
    times, files = [], []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        try:
            if len(parts) != 2:
                raise ValueError
            t = float(parts[0])
        except ValueError:
            raise ValueError(f"{path}: line {lineno}: expected 't[s] image-path', got {s!r}") from None
        f = path.parent / parts[1]
        if not f.is_file():
            raise FileNotFoundError(f"{path}: line {lineno}: image {f} not found")
        times.append(t)
        files.append(f)
    if not files:
        raise ValueError(f"{path}: no images listed (expected 't[s] image-path' lines)")
    return seconds_to_us(np.asarray(times)), files

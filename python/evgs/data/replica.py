"""IncEventGS / Replica-event layout (the reference implementation's "custom data" format).

A folder with ``poses_ts.txt`` (one timestamp in seconds per line: the frames), ``traj.txt`` (one
camera-to-world 4×4 matrix per line, 16 values row-major, aligned with ``poses_ts.txt``),
``event_threshold_<C>/gray_events_data.npy`` (float N×4: x, y, t[s], p ±1) and optionally ``images/``
(one image per frame, in name order).

Intrinsics are not part of the layout (the reference keeps them in its config): ``--intrinsics`` is
required. The size comes from the images, or ``--size`` without them. Camera axes default to OpenCV
(``--axes opengl`` flips y and z for Blender/NeRF-style poses).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.progress import Progress

from evgs.data.importers import (
    Imported,
    check_frames,
    finish_events,
    float_list,
    image_size,
    parse_size,
    read_events_tracked,
)
from evgs.data.poses import AXES, Axes, rows_to_pose, to_opencv_axes
from evgs.data.rawtext import read_rows, seconds_to_us
from evgs.data.sequence import Camera

DESCRIPTION = "IncEventGS/Replica-event folder (poses_ts.txt, traj.txt, event_threshold_*/, images/)"
RAW_PATH_HELP = "a folder holding poses_ts.txt, traj.txt and event_threshold_<C>/gray_events_data.npy"

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--intrinsics", required=True, metavar="FX,FY,CX,CY", type=float_list(4),
                        help="pinhole intrinsics in pixels")  # fmt: skip
    parser.add_argument("--size", type=parse_size, metavar="WxH", help="sensor size (default: from images/)")
    parser.add_argument(
        "--threshold", help="which event_threshold_<C> folder (needed when there are several)"
    )
    parser.add_argument("--axes", choices=AXES, default="opencv", help="camera axes of traj.txt (opencv)")


def load(
    path: Path,
    progress: Progress,
    *,
    intrinsics: tuple[float, float, float, float],
    size: tuple[int, int] | None = None,
    threshold: str | None = None,
    axes: Axes = "opencv",
) -> Imported:
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: folder not found ({RAW_PATH_HELP})")
    ts, _ = read_rows(path / "poses_ts.txt", 1, "t[s]")
    frames = check_frames(seconds_to_us(ts[:, 0]), str(path / "poses_ts.txt"))
    mats, lines = read_rows(path / "traj.txt", 16, "16 values of a row-major 4x4 camera-to-world matrix")
    if len(mats) != len(frames):
        raise ValueError(
            f"{path / 'traj.txt'}: {len(mats)} poses but poses_ts.txt has {len(frames)} timestamps"
        )
    T_wc = to_opencv_axes(rows_to_pose(mats, str(path / "traj.txt"), int(lines[0])), axes)

    image_dir = path / "images"
    images = (
        sorted(p for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if image_dir.is_dir()
        else []
    )
    if images and len(images) != len(frames):
        raise ValueError(f"{image_dir}: {len(images)} images but poses_ts.txt has {len(frames)} timestamps")
    if size is None:
        if not images:
            raise ValueError(f"{path}: no images/ to take the sensor size from; pass --size WxH")
        size = image_size(images[0])
    camera = Camera(size[0], size[1], *intrinsics)

    npy = _events_file(path, threshold)
    notes: list[str] = []
    raw = read_events_tracked(npy, "npy", progress, notes, width=camera.width, height=camera.height)
    events = finish_events(raw, camera, str(npy), notes)
    meta = {
        "source": "replica",
        "raw_path": str(path.resolve()),
        "axes": axes,
        "event_threshold": npy.parent.name,
    }
    return Imported(
        path.resolve().name, camera, events, frames, poses_gt=(frames, T_wc),
        images=images or None, meta=meta, notes=notes,
    )  # fmt: skip


def _events_file(path: Path, threshold: str | None) -> Path:
    folders = sorted(p for p in path.glob("event_threshold_*") if p.is_dir())
    if threshold is not None:
        folders = [p for p in folders if p.name == f"event_threshold_{threshold}"]
    if len(folders) != 1:
        found = ", ".join(sorted(p.name for p in path.glob("event_threshold_*"))) or "none"
        want = f"event_threshold_{threshold}" if threshold is not None else "exactly one event_threshold_<C>"
        raise FileNotFoundError(f"{path}: expected {want} folder (found: {found}); pick one with --threshold")
    npy = folders[0] / "gray_events_data.npy"
    if not npy.is_file():
        raise FileNotFoundError(f"{npy}: not found (expected float N×4 x, y, t[s], p)")
    return npy

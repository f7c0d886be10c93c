"""SEENIC (Zenodo 7370076): a DVXplorer (640×480) on a UR5e arm around a foil-wrapped Hubble model.

One folder per sequence (e.g. ``hubble-orbit-slow-ambient``) holding ``events.csv`` (``t, x, y, p``, t in
µs, p ∈ {0, 1}, header row or not) and ``cam-poses.csv`` (``t[µs], rx, ry, rz, x, y, z``: a Rodrigues
axis-angle vector and a translation, header row or not).

Frames are the pose timestamps (the ground truth's own clock).

Distortion: the DVXplorer's OpenCV distortion is stored in ``sequence.toml`` and the events are kept
at their recorded (distorted) pixels. Undistortion happens in the event-frame path (the undistortion
map built from ``sequence.toml``'s camera, applied as events are accumulated into frames), where each
event keeps its sub-pixel undistorted position. Doing it here would round those positions back to
the integer pixel grid (the canonical x/y are uint16), which biases them, and would have to drop the
border events that undistort outside the sensor. Keeping the recorded pixels makes the import lossless
and reversible.

Pose direction is *unconfirmed*; the default ``c2w`` treats the poses as the camera in the target
(world) frame, which is how the thesis code that produced the paper's numbers used them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.progress import Progress

from evgs.data.importers import Imported, check_frames, finish_events, read_events_tracked
from evgs.data.poses import DIRECTIONS, Direction, rodrigues_to_rotmat, to_c2w
from evgs.data.rawtext import read_rows
from evgs.data.sequence import Camera
from evgs.geometry import make_pose

DESCRIPTION = "SEENIC sequence folder (events.csv + cam-poses.csv)"
RAW_PATH_HELP = "a SEENIC sequence folder, e.g. hubble-orbit-slow-ambient/"

# DVXplorer calibration used by the thesis code (OpenCV k1, k2, p1, p2, k3).
CAMERA = Camera(
    640, 480, 561.5819, 560.6470, 315.4104, 248.8996, (-0.40594, 0.27925, 7.26e-4, -3.75e-4, -0.13890)
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--pose-direction", choices=DIRECTIONS, default="c2w",
        help="what cam-poses.csv holds: camera-in-target (c2w, default, as the thesis code used it) or "
        "target-in-camera (w2c)",
    )  # fmt: skip


def load(path: Path, progress: Progress, *, pose_direction: Direction = "c2w") -> Imported:
    events_path, poses_path = path / "events.csv", path / "cam-poses.csv"
    for p, what in (
        (events_path, "events: t[µs], x, y, p"),
        (poses_path, "poses: t[µs], rx, ry, rz, x, y, z"),
    ):
        if not p.is_file():
            raise FileNotFoundError(
                f"{p}: not found; a SEENIC sequence folder holds events.csv and cam-poses.csv ({what})"
            )
    notes: list[str] = []
    raw = read_events_tracked(
        events_path, "csv", progress, notes, columns="txyp", time_unit="us", width=CAMERA.width,
        height=CAMERA.height,
    )  # fmt: skip
    events = finish_events(raw, CAMERA, str(events_path), notes)

    rows, lines = read_rows(poses_path, 7, "t[µs] rx ry rz x y z")
    t_us = rows[:, 0].round().astype("int64")
    T = make_pose(rodrigues_to_rotmat(rows[:, 1:4]), rows[:, 4:7])
    T_wc = to_c2w(T, pose_direction)
    frames = check_frames(t_us, f"{poses_path} (line {lines[0]} on)")
    outside = int(((t_us < events.t[0]) | (t_us > events.t[-1])).sum())
    if outside:
        notes.append(f"{poses_path}: {outside} of {len(t_us)} pose timestamps lie outside the event stream")
    meta = {
        "source": "seenic",
        "raw_path": str(path.resolve()),
        "pose_direction": pose_direction,
        "undistortion": "event-frames",
    }
    return Imported(
        path.resolve().name, CAMERA, events, frames, poses_gt=(t_us, T_wc), meta=meta, notes=notes
    )

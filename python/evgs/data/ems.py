"""E-M-S, Event-Monocular Spacecraft (Zenodo 14774652): Unreal Engine 4 renders, events by v2e, 640×480.

Each split (``training/``, ``validation/``, ``testing/``) holds ``Event/event_stream/<i>.csv``
(``timestamp,x,y,polarity``: the events of frame i), ``Event/pose/<i>.txt`` (``r1..r9 tx ty tz``: a
row-major rotation and a translation) and ``RGB/img/<i>.jpg``; images, CSVs and poses share the index
``i`` (the last number in the file name). ``--sequence S`` picks one sequence when the folder holds
several, either as a subfolder ``event_stream/S/`` or as files named ``S_<i>.csv``.

The per-frame CSVs are joined into one stream. Frame i's timestamp is the last event of CSV i, so the
events of frame i are exactly those after frame i−1 and up to frame i; a frame without events gets a
time interpolated linearly from its neighbours (counted in the report).

Time unit (not published) is detected once for the whole sequence from the magnitudes: decimals mean
seconds; for integers the median spacing of consecutive files' first timestamps decides: < 10³ → ms,
< 10⁶ → µs, else ns (frame rates between ~1 and 1000 Hz). ``--time-unit`` overrides it.

Intrinsics are not published: ``--intrinsics fx,fy,cx,cy`` is required. Pose direction is
*unconfirmed*; the default ``w2c`` reads the poses as target-in-camera, the usual convention of
pose-estimation data sets.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
from rich.progress import Progress

from evgs.data.importers import Imported, check_frames, finish_events, float_list, parse_size
from evgs.data.poses import DIRECTIONS, Direction, rows_to_pose, to_c2w
from evgs.data.rawtext import read_numbers
from evgs.data.sequence import Camera
from evgs.events.arrays import EventArray
from evgs.events.io import read_events

DESCRIPTION = "E-M-S sequence (Event/event_stream/*.csv + Event/pose/*.txt, RGB/img/*.jpg)"
RAW_PATH_HELP = "an E-M-S split folder (holding Event/ and RGB/) or its Event/ folder"

TIME_UNITS = ("s", "ms", "us", "ns")
_INT = re.compile(r"\d+")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--intrinsics", required=True, metavar="FX,FY,CX,CY", type=float_list(4),
        help="pinhole intrinsics in pixels (E-M-S does not publish them)",
    )  # fmt: skip
    parser.add_argument(
        "--size", default="640x480", metavar="WxH", type=parse_size, help="sensor size (640x480)"
    )
    parser.add_argument("--sequence", help="sequence id when the folder holds several")
    parser.add_argument(
        "--pose-direction", choices=DIRECTIONS, default="w2c",
        help="what pose/*.txt holds: target-in-camera (w2c, default) or camera-in-target (c2w)",
    )  # fmt: skip
    parser.add_argument("--time-unit", choices=TIME_UNITS, help="time unit of the CSVs (default: detected)")
    parser.add_argument("--no-images", action="store_true", help="do not import RGB/img")


def load(
    path: Path,
    progress: Progress,
    *,
    intrinsics: tuple[float, float, float, float],
    size: tuple[int, int] = (640, 480),
    sequence: str | None = None,
    pose_direction: Direction = "w2c",
    time_unit: str | None = None,
    no_images: bool = False,
) -> Imported:
    event_dir = path / "Event" if (path / "Event").is_dir() else path
    split = event_dir.parent if event_dir.name == "Event" else event_dir  # holds Event/ and RGB/
    camera = Camera(size[0], size[1], *intrinsics)
    csvs = _indexed_files(event_dir / "event_stream", "csv", sequence)
    poses = _indexed_files(event_dir / "pose", "txt", sequence)
    missing = sorted(set(csvs) - set(poses))
    if missing:
        raise FileNotFoundError(
            f"{event_dir / 'pose'}: no pose file for frame {missing[0]} (expected <i>.txt)"
        )
    idx = sorted(csvs)
    notes: list[str] = []
    gaps = sorted(set(range(idx[0], idx[-1] + 1)) - set(idx))
    if gaps:
        notes.append(f"{event_dir / 'event_stream'}: no CSV for frame indices {gaps[:10]}; frames re-indexed")
    unit = time_unit or detect_time_unit([csvs[i] for i in idx])
    if time_unit is None:
        notes.append(f"time unit of the event CSVs detected as {unit}")

    parts = []
    for i in progress.track(idx, description="reading event CSVs"):
        parts.append(read_events(csvs[i], "csv", time_unit=unit, width=camera.width, height=camera.height))
    frames = _frame_times(parts, [csvs[i] for i in idx], notes)
    events = EventArray(*(np.concatenate([getattr(p, c) for p in parts]) for c in "txyp"))
    events = finish_events(events, camera, str(event_dir / "event_stream"), notes)

    T = np.stack(
        [rows_to_pose(read_numbers(poses[i], 12, "r1..r9 tx ty tz")[None], str(poses[i]))[0] for i in idx]
    )
    T_wc = to_c2w(T, pose_direction)

    images = None
    img_dir = split / "RGB" / "img"
    if not no_images and img_dir.is_dir():
        imgs = _indexed_files(img_dir, "jpg", sequence)
        lacking = [i for i in idx if i not in imgs]
        if lacking:
            raise FileNotFoundError(
                f"{img_dir}: no image for frame {lacking[0]} (pass --no-images to skip them)"
            )
        images = [imgs[i] for i in idx]
    name = sequence if sequence is not None else split.resolve().name
    meta = {
        "source": "ems",
        "raw_path": str(path.resolve()),
        "pose_direction": pose_direction,
        "time_unit": unit,
    }
    return Imported(
        name, camera, events, frames, poses_gt=(frames, T_wc), images=images, meta=meta, notes=notes
    )


def _indexed_files(folder: Path, ext: str, sequence: str | None) -> dict[int, Path]:
    """Files of one sequence keyed by their frame index (the last number in the name)."""
    if sequence is not None and (folder / sequence).is_dir():
        folder, sequence = folder / sequence, None
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: folder not found (expected E-M-S per-frame *.{ext} files)")
    out: dict[int, Path] = {}
    for f in folder.glob(f"*.{ext}"):
        nums = _INT.findall(f.stem)
        if not nums or (sequence is not None and (len(nums) < 2 or int(nums[0]) != int(sequence))):
            continue
        i = int(nums[-1])
        if i in out:
            raise ValueError(f"{folder}: frame {i} appears twice ({out[i].name}, {f.name}); pass --sequence")
        out[i] = f
    if not out:
        which = f" of sequence {sequence}" if sequence is not None else ""
        raise FileNotFoundError(f"{folder}: no numbered *.{ext} files{which}")
    return out


def _first_time_field(path: Path) -> str | None:
    """The raw text of the first event's timestamp (column ``timestamp`` or the first), None if empty."""
    with open(path, errors="replace") as f:
        col = 0
        for line in f:
            fields = [s.strip() for s in re.split(r"[,;\s]+", line.strip()) if s.strip()]
            if not fields or fields[0].startswith("#"):
                continue
            try:
                float(fields[col])
            except (ValueError, IndexError):
                names = [s.lower() for s in fields]
                col = next((names.index(n) for n in ("timestamp", "t", "ts", "time") if n in names), 0)
                continue
            return fields[col]
    return None


def detect_time_unit(csvs: list[Path]) -> str:
    firsts = [(i, s) for i, f in enumerate(csvs) if (s := _first_time_field(f)) is not None]
    if not firsts:
        raise ValueError(f"{csvs[0].parent}: all {len(csvs)} event CSVs are empty")
    if any(c in s for _, s in firsts for c in ".eE"):
        return "s"
    if len(firsts) < 2:
        return "us"
    idx = np.array([i for i, _ in firsts], np.float64)
    t = np.array([float(s) for _, s in firsts])
    spacing = float(np.median(np.diff(t) / np.diff(idx)))
    return "ms" if spacing < 1e3 else "us" if spacing < 1e6 else "ns"


def _frame_times(parts: list[EventArray], files: list[Path], notes: list[str]) -> np.ndarray:
    """Frame i = the last event of CSV i; empty frames interpolated; overlapping CSVs are an error."""
    ends = np.array([p.t.max() if len(p) else -1 for p in parts], np.int64)
    starts = np.array([p.t.min() if len(p) else -1 for p in parts], np.int64)
    full = np.flatnonzero(ends >= 0)
    if len(full) < 2:
        raise ValueError(f"{files[0].parent}: need at least 2 non-empty event CSVs, found {len(full)}")
    for a, b in zip(full[:-1], full[1:], strict=True):
        if starts[b] < ends[a]:
            raise ValueError(
                f"{files[b]}: first event at {starts[b]} µs precedes the last event of {files[a].name} "
                f"({ends[a]} µs); per-frame CSVs must not overlap"
            )
    empty = np.flatnonzero(ends < 0)
    if len(empty):
        ends[empty] = _extrapolate(empty, full, ends[full])
        shown = ", ".join(files[i].name for i in empty[:5]) + (", ..." if len(empty) > 5 else "")
        notes.append(f"{len(empty)} event CSVs hold no events ({shown}); their frame times are interpolated")
    return check_frames(ends, str(files[0].parent))


def _extrapolate(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Piecewise-linear through (xp, fp), extended linearly beyond both ends."""
    y = np.interp(x, xp, fp)
    lo, hi = x < xp[0], x > xp[-1]
    y[lo] = fp[0] + (x[lo] - xp[0]) * (fp[1] - fp[0]) / (xp[1] - xp[0])
    y[hi] = fp[-1] + (x[hi] - xp[-1]) * (fp[-1] - fp[-2]) / (xp[-1] - xp[-2])
    return np.round(y).astype(np.int64)

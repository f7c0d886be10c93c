"""ELOPE (ESA lunar-descent challenge): PANGU renders → simulated events, 200×200, one ``.npz`` per sequence.

The archive holds ``events`` (structured: x, y, p bool, t µs), ``timestamps`` (s, the frames),
``traj`` (N×12 at those timestamps: x, y, z, vx, vy, vz, φ, θ, ψ (roll, pitch, yaw, rad), p, q, r) and
``range_meter`` (N×2: t s, distance m from the camera centre to the surface point at pixel [100, 100]).
Only the training sequences carry ``traj`` and ``range_meter``; without them no ground truth is written.

Conventions (*unconfirmed*, each an option with this default):

- world: z is negative above the ground (altitude = |z|), i.e. z points down, as in a north-east-down
  frame;
- attitude: the aerospace 3-2-1 sequence, ``R_wb = Rz(ψ) Ry(θ) Rx(φ)`` mapping body to world
  (``--euler-order xyz``, extrinsic; ``--attitude-direction c2w``);
- camera mount: camera axes = body axes (``--camera-rotation`` = identity), i.e. the optical axis is the
  body z axis, which points at the ground at zero attitude in the z-down world.

Poses go to ``poses_gt.txt`` (camera-to-world), the velocities and body rates to ``velocities_gt.csv``
(``t_us, vx, vy, vz, p, q, r``; metres per second in the world frame, rad/s), the range meter to
``range.csv``.

Intrinsics are not published: the default focal length is 100 px (the value the thesis configs used)
with the principal point at pixel (100, 100), the pixel the range meter names as the image centre.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import polars as pl
from rich.progress import Progress

from evgs.data.importers import Imported, check_frames, finish_events, float_list, read_events_tracked
from evgs.data.poses import DIRECTIONS, Direction, check_rotations, euler_to_rotmat
from evgs.data.rawtext import seconds_to_us
from evgs.data.sequence import Camera
from evgs.geometry import make_pose

DESCRIPTION = "ELOPE sequence (.npz with events, timestamps, traj, range_meter)"
RAW_PATH_HELP = "an ELOPE .npz file, e.g. 0000.npz"

SIZE = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--focal", type=float, default=100.0, help="focal length in px (default 100)")
    parser.add_argument(
        "--principal", type=float_list(2), default=(100.0, 100.0), metavar="CX,CY",
        help="principal point in px (default 100,100)",
    )  # fmt: skip
    parser.add_argument(
        "--euler-order", default="xyz",
        help="axis order of (φ, θ, ψ): lower case extrinsic, upper case intrinsic (default xyz = Rz·Ry·Rx)",
    )  # fmt: skip
    parser.add_argument(
        "--attitude-direction", choices=DIRECTIONS, default="c2w",
        help="the Euler rotation maps body to world (c2w, default) or world to body (w2c)",
    )  # fmt: skip
    parser.add_argument(
        "--camera-rotation", type=float_list(9), default=None, metavar="R11,...,R33",
        help="camera-to-body rotation, row-major (default identity: camera axes = body axes)",
    )  # fmt: skip


def load(
    path: Path,
    progress: Progress,
    *,
    focal: float = 100.0,
    principal: tuple[float, float] = (100.0, 100.0),
    euler_order: str = "xyz",
    attitude_direction: Direction = "c2w",
    camera_rotation: tuple[float, ...] | None = None,
) -> Imported:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found (expected an ELOPE .npz)")
    camera = Camera(SIZE, SIZE, focal, focal, principal[0], principal[1])
    notes: list[str] = []
    raw = read_events_tracked(path, "npz", progress, notes, width=SIZE, height=SIZE)
    events = finish_events(raw, camera, f"{path}: events", notes)
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in ("timestamps", "traj", "range_meter") if k in npz.files}
    if "timestamps" not in arrays:
        raise ValueError(f"{path}: no 'timestamps' array (expected frame times in seconds)")
    frames = check_frames(seconds_to_us(arrays["timestamps"].ravel()), f"{path}: timestamps")
    meta = {"source": "elope", "raw_path": str(path.resolve())}

    seq = Imported(path.stem, camera, events, frames, meta=meta, notes=notes)
    if "traj" in arrays:
        traj = np.asarray(arrays["traj"], np.float64)
        if traj.ndim != 2 or traj.shape[1] != 12 or len(traj) != len(frames):
            raise ValueError(
                f"{path}: 'traj' has shape {traj.shape}; expected ({len(frames)}, 12), one "
                "x y z vx vy vz φ θ ψ p q r row per timestamp"
            )
        if not np.isfinite(traj).all():
            row = int(np.argmax(~np.isfinite(traj).all(axis=1)))
            raise ValueError(f"{path}: 'traj' row {row}: non-finite value")
        R_bc = np.eye(3) if camera_rotation is None else np.asarray(camera_rotation).reshape(3, 3)
        R_bc = check_rotations(R_bc, "--camera-rotation")
        R_wb = euler_to_rotmat(traj[:, 6:9], euler_order)
        if attitude_direction == "w2c":
            R_wb = np.swapaxes(R_wb, -1, -2)
        seq.poses_gt = (frames, make_pose(R_wb @ R_bc, traj[:, 0:3]))
        cols = ("vx", "vy", "vz", "p", "q", "r")
        seq.tables["velocities_gt.csv"] = pl.DataFrame(
            {"t_us": frames, **{c: traj[:, j] for c, j in zip(cols, (3, 4, 5, 9, 10, 11), strict=True)}}
        )
        meta.update(
            euler_order=euler_order,
            attitude_direction=attitude_direction,
            camera_rotation=R_bc.ravel().tolist(),
        )
    else:
        notes.append(f"{path}: no 'traj' (a test sequence?): no ground-truth poses or velocities written")
    if "range_meter" in arrays:
        rm = np.asarray(arrays["range_meter"], np.float64)
        if rm.ndim != 2 or rm.shape[1] != 2 or not np.isfinite(rm).all():
            raise ValueError(
                f"{path}: 'range_meter' has shape {rm.shape}; expected finite (N, 2) rows of t[s], m"
            )
        seq.range_samples = (seconds_to_us(rm[:, 0]), rm[:, 1])
    return seq

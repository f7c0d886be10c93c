"""Synthetic trajectories and run directories for the evaluation tests (not a test module)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tomli_w
from evgs.data.sequence import Camera, Sequence, write_sequence
from evgs.data.tum import write_tum
from evgs.eval.align import Sim3
from evgs.events.arrays import EventArray
from evgs.geometry import make_pose
from scipy.spatial.transform import Rotation


def random_sim3(rng: np.random.Generator) -> Sim3:
    return Sim3(
        Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 3.0, float(rng.uniform(0.2, 5))
    )


def orbit(n: int, rng: np.random.Generator, *, radius: float = 2.0) -> np.ndarray:
    """(n, 4, 4) camera-to-world poses on a wobbly helix around the origin, cameras roughly looking
    at it, with some extra rotation noise so every Euler angle varies."""
    a = np.linspace(0, 1.5 * np.pi, n)
    c = np.stack([radius * np.cos(a), radius * np.sin(a), 0.3 * np.sin(3 * a) + 0.1 * a], axis=1)
    z = -c / np.linalg.norm(c, axis=1, keepdims=True)
    x = np.cross(np.array([0.0, 0.0, 1.0]), z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=2) @ Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.05).as_matrix()
    return make_pose(R, c)


def perturb(T: np.ndarray, sim3: Sim3, rng: np.random.Generator, *, pos_sigma: float, rot_sigma: float):
    """An "estimate": noisy poses expressed through the inverse of ``sim3`` (so ``sim3`` maps it back)."""
    noisy = make_pose(
        T[:, :3, :3] @ Rotation.from_rotvec(rng.normal(size=(len(T), 3)) * rot_sigma).as_matrix(),
        T[:, :3, 3] + rng.normal(size=(len(T), 3)) * pos_sigma,
    )
    return sim3.inverse().apply_poses(noisy)


def write_fake_sequence(
    root: Path,
    name: str,
    T_gt: np.ndarray,
    images: np.ndarray,
    *,
    focal: float = 40.0,
    source: str = "synthetic",
) -> Sequence:
    """A sequence folder with GT poses and images at frames 50 ms apart (one dummy event)."""
    n, size = len(T_gt), images.shape[-1]
    frames_us = 1_000_000 + np.arange(n, dtype=np.int64) * 50_000
    zero = np.zeros(1, np.uint16)
    ev = EventArray(frames_us[:1], zero, zero, np.ones(1, np.int8), size, size)
    return write_sequence(
        root / "seqs" / name, name, Camera(size, size, focal, focal, size / 2, size / 2), ev, frames_us,
        poses_gt=(frames_us, T_gt), images=images, meta={"source": source},
    )  # fmt: skip


def write_fake_run(root: Path, seq: Sequence, T_est: np.ndarray) -> Path:
    """``runs/<seq>/<timestamp>/`` with config.toml and traj_est.txt at the sequence's frame times."""
    run = root / "runs" / seq.name / "20260101-000000"
    run.mkdir(parents=True)
    (run / "config.toml").write_text(tomli_w.dumps({"seq": str(seq.root), "batch_size": 1}))
    write_tum(run / "traj_est.txt", seq.frames_us() / 1e6, T_est)
    return run


def fake_run(
    root: Path,
    name: str,
    rng: np.random.Generator,
    *,
    n: int = 30,
    source: str = "synthetic",
    z_offset: float = 0.0,
) -> Path:
    """A sequence (orbit GT, smooth 48×48 images) and a run whose estimate is the GT seen through a random
    Sim(3), with 1 cm / 0.01 rad noise. Returns the run directory."""
    T_gt = orbit(n, rng)
    T_gt[:, 2, 3] += z_offset
    yy, xx = np.mgrid[0:48, 0:48] / 48
    images = np.stack([0.5 + 0.4 * np.sin(6 * xx + 0.2 * i) * np.cos(5 * yy) for i in range(n)])
    seq = write_fake_sequence(root, name, T_gt, images, source=source)
    return write_fake_run(root, seq, perturb(T_gt, random_sim3(rng), rng, pos_sigma=0.01, rot_sigma=0.01))


SH_C0 = 0.28209479177387814
FIELDS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
          "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip


def write_ply(path, means, log_scales, quats_wxyz, opacity_logits, grey):
    """A 3DGS PLY (grey colour in the DC band, no higher SH) of the given Gaussians."""
    rows = np.zeros(len(means), dtype=[(f, "<f4") for f in FIELDS])
    for i, a in enumerate("xyz"):
        rows[a] = means[:, i]
        rows[f"scale_{i}"] = log_scales[:, i]
    for i in range(3):
        rows[f"f_dc_{i}"] = (grey - 0.5) / SH_C0
    for i in range(4):
        rows[f"rot_{i}"] = quats_wxyz[:, i]
    rows["opacity"] = opacity_logits
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(rows)}"]
    header += [f"property float {f}" for f in FIELDS] + ["end_header"]
    path.write_bytes(("\n".join(header) + "\n").encode() + rows.tobytes())

"""Shared pieces of the data-set adapter tests: a known scene (camera-to-world poses around a target
point) and random event streams, written by each test in its data set's own format."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from evgs.cli import main
from evgs.data.sequence import Camera, Sequence
from evgs.geometry import make_pose

# A point on the target, in the world (= target) frame.
POINT = np.array([0.3, -0.2, 0.1])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)  # right = forward × up-vector, since image y points down
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def orbit_poses(n: int, radius: float = 5.0) -> np.ndarray:
    """``n`` camera-to-world poses on a tilted orbit, all looking at the world origin."""
    a = np.linspace(0.0, 1.5, n)
    eyes = np.stack([radius * np.cos(a), radius * np.sin(a), 0.5 + 0.3 * a], axis=1)
    return np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in eyes])


def project(T_wc: np.ndarray, camera: Camera, point: np.ndarray) -> np.ndarray:
    """Pixel of a world point in each camera (pinhole, no distortion): (N, 2)."""
    R, t = T_wc[:, :3, :3], T_wc[:, :3, 3]
    pc = np.einsum("nji,nj->ni", R, point - t)  # Rᵀ (P − t)
    assert np.all(pc[:, 2] > 0), "point behind the camera"
    return np.stack(
        [camera.fx * pc[:, 0] / pc[:, 2] + camera.cx, camera.fy * pc[:, 1] / pc[:, 2] + camera.cy], 1
    )


def random_events(rng: np.random.Generator, n: int, t0: int, t1: int, width: int, height: int) -> dict:
    """Sorted events with integer µs times in [t0, t1], polarity ±1."""
    return {
        "t": np.sort(rng.integers(t0, t1 + 1, n)).astype(np.int64),
        "x": rng.integers(0, width, n),
        "y": rng.integers(0, height, n),
        "p": rng.choice(np.array([-1, 1]), n),
    }


def run_import(*argv: str | Path) -> int:
    return main(["import", *map(str, argv)])


def assert_projects_as_truth(seq: Sequence, T_true: np.ndarray, t_true_us: np.ndarray) -> None:
    """The imported ground truth sees ``POINT`` where the known camera-to-world poses do."""
    t_us, T = seq.poses_gt()
    np.testing.assert_array_equal(t_us, t_true_us)
    np.testing.assert_allclose(project(T, seq.camera, POINT), project(T_true, seq.camera, POINT), atol=1e-4)
    np.testing.assert_allclose(T, T_true, atol=1e-6)

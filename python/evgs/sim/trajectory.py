"""Camera trajectories around the target: straight approach, swirl (sinusoidal bent approach, half a
cycle), circular orbit, or a replayed TUM file. All return camera-to-world poses (OpenCV camera axes,
world = target frame, +z up) at any time in seconds since the start; generated ones look at the origin.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from evgs.data.tum import read_tum
from evgs.geometry import make_pose

KINDS = ("approach", "swirl", "orbit")
UP = np.array([0.0, 0.0, 1.0])


def look_at(eye: np.ndarray, target: np.ndarray | None = None) -> np.ndarray:
    """(…, 4, 4) camera-to-world poses at ``eye`` (…, 3) looking at ``target`` with world +z up in the
    image (OpenCV: x right, y down, z forward)."""
    eye = np.asarray(eye, np.float64)
    target = np.zeros(3) if target is None else np.asarray(target, np.float64)
    z = target - eye
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, UP)
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    if np.any(norm < 1e-6):
        raise ValueError("camera looks straight up or down: the image 'up' direction is undefined")
    x /= norm
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=-1), eye)


@dataclass(frozen=True)
class Trajectory:
    """A generated trajectory. ``distance`` is the start distance (orbit: the radius) in metres,
    ``speed`` the camera's speed along the path in m/s, ``elevation_deg``/``azimuth_deg`` the start
    direction seen from the target; ``amplitude`` is the swirl's sideways excursion (default: a
    quarter of the distance)."""

    kind: str
    distance: float
    speed: float
    duration: float
    elevation_deg: float = 15.0
    azimuth_deg: float = 0.0
    amplitude: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown trajectory {self.kind!r} (choose from {', '.join(KINDS)})")
        if not (self.distance > 0 and self.duration > 0 and self.speed >= 0):
            raise ValueError("trajectory needs distance > 0, duration > 0 and speed ≥ 0")
        if self.kind != "orbit" and self.speed * self.duration >= 0.9 * self.distance:
            raise ValueError(
                f"{self.kind}: speed × duration = {self.speed * self.duration:.3g} m would reach the target "
                f"(start distance {self.distance:.3g} m)"
            )

    @property
    def t_end(self) -> float:
        return self.duration

    def _direction(self, azimuth: np.ndarray) -> np.ndarray:
        el = np.radians(self.elevation_deg)
        return np.stack(
            [np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.full_like(azimuth, np.sin(el))],
            -1,
        )

    def positions(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, np.float64)
        az0 = np.radians(self.azimuth_deg)
        if self.kind == "orbit":
            radius = self.distance * np.cos(np.radians(self.elevation_deg))  # of the horizontal circle
            return self.distance * self._direction(az0 + self.speed / radius * t)
        d = self._direction(np.full_like(t, az0))
        along = (self.distance - self.speed * t)[..., None] * d
        if self.kind == "approach":
            return along
        side = np.cross(d, UP)
        side /= np.linalg.norm(side, axis=-1, keepdims=True)
        amp = 0.25 * self.distance if self.amplitude is None else self.amplitude
        return along + (amp * np.sin(np.pi * t / self.duration))[..., None] * side

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        """Camera-to-world poses (…, 4, 4) at times ``t`` (s since the start)."""
        return look_at(self.positions(t))


class ReplayTrajectory:
    """A TUM trajectory (camera-to-world), interpolated linearly in position and by slerp in rotation.
    Time 0 is the file's first pose."""

    def __init__(self, path: str | Path) -> None:
        t, T = read_tum(path)
        if len(t) < 2 or np.any(np.diff(t) <= 0):
            raise ValueError(f"{path}: need ≥ 2 poses with strictly increasing timestamps")
        self.t0 = float(t[0])
        self.t = t - t[0]
        self.T = T
        self.slerp = Slerp(self.t, Rotation.from_matrix(T[:, :3, :3]))

    @property
    def t_end(self) -> float:
        return float(self.t[-1])

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        t = np.clip(np.asarray(t, np.float64), 0.0, self.t_end)
        flat = t.reshape(-1)
        pos = np.stack([np.interp(flat, self.t, self.T[:, i, 3]) for i in range(3)], -1)
        R = self.slerp(flat).as_matrix()
        return make_pose(R, pos).reshape(t.shape + (4, 4))

"""Camera trajectories around the target: straight approach, swirl (sinusoidal bent approach, half a
cycle), circular orbit, a lander's descent over a surface, or a replayed TUM file. All return
camera-to-world poses (OpenCV camera axes, world = target frame, +z up) at any time in seconds since the
start; the approaches and the orbit look at the origin, the descent looks down.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from evgs.data.tum import read_tum
from evgs.geometry import make_pose

KINDS = ("approach", "swirl", "orbit", "descent")
UP = np.array([0.0, 0.0, 1.0])
DESCENT_TILT_DEG = 10.0
"""The descent camera's optical axis is tilted this far from nadir towards the direction of travel
(a lander's camera looks slightly ahead at the landing site)."""


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


def look_down(eye: np.ndarray, heading: np.ndarray, tilt_deg: float) -> np.ndarray:
    """(…, 4, 4) camera-to-world poses at ``eye`` (…, 3) looking down, tilted ``tilt_deg`` from nadir
    towards the horizontal unit vector ``heading``, which points "up" in the image."""
    eye = np.asarray(eye, np.float64)
    tilt = np.radians(tilt_deg)
    z = np.cos(tilt) * -UP + np.sin(tilt) * heading
    y = -(np.cos(tilt) * heading + np.sin(tilt) * UP)  # image down: backwards and down
    x = np.cross(y, z)
    R = np.stack([x, y, z], axis=-1)
    return make_pose(np.broadcast_to(R, eye.shape[:-1] + (3, 3)), eye)


@dataclass(frozen=True)
class Trajectory:
    """A generated trajectory. ``distance`` is the start distance (orbit: the radius) in metres,
    ``speed`` the camera's speed along the path in m/s, ``elevation_deg``/``azimuth_deg`` the start
    direction seen from the target; ``amplitude`` is the swirl's sideways excursion (default: a
    quarter of the distance).

    The descent is a straight glide over the surface z = 0: ``distance`` is the start altitude,
    ``elevation_deg`` the flight-path angle below the horizontal (90: straight down) and
    ``azimuth_deg`` the heading of the horizontal travel; the ground track is centred on the origin."""

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
        if self.kind == "descent":
            self._check_descent()
        elif self.kind != "orbit" and self.speed * self.duration >= 0.9 * self.distance:
            raise ValueError(
                f"{self.kind}: speed × duration = {self.speed * self.duration:.3g} m would reach the target "
                f"(start distance {self.distance:.3g} m)"
            )

    def _check_descent(self) -> None:
        if not 0.0 < self.elevation_deg <= 90.0:
            raise ValueError(
                f"descent: elevation_deg = {self.elevation_deg:g} must be in (0, 90] (the glide angle)"
            )
        drop = self.speed * self.duration * np.sin(np.radians(self.elevation_deg))
        if drop >= 0.9 * self.distance:
            raise ValueError(
                f"descent: the camera would drop {drop:.3g} m and reach the surface (start altitude "
                f"{self.distance:.3g} m; keep the end altitude above 10 % of it)"
            )

    @property
    def t_end(self) -> float:
        return self.duration

    def _heading(self) -> np.ndarray:
        az = np.radians(self.azimuth_deg)
        return np.array([np.cos(az), np.sin(az), 0.0])

    def _direction(self, azimuth: np.ndarray) -> np.ndarray:
        el = np.radians(self.elevation_deg)
        return np.stack(
            [np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.full_like(azimuth, np.sin(el))],
            -1,
        )

    def positions(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, np.float64)
        az0 = np.radians(self.azimuth_deg)
        if self.kind == "descent":
            el = np.radians(self.elevation_deg)
            along = self.speed * np.cos(el) * (t - 0.5 * self.duration)
            altitude = self.distance - self.speed * np.sin(el) * t
            return along[..., None] * self._heading() + altitude[..., None] * UP
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
        if self.kind == "descent":
            return look_down(self.positions(t), self._heading(), DESCENT_TILT_DEG)
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

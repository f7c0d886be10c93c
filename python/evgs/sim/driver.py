"""The simulator driver: render the target along a trajectory at an adaptive rate, turn the frames into
events (Rust ESIM), and write a canonical sequence folder with its ground truth."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from evgs import _core
from evgs.data.sequence import Camera, Sequence, write_sequence
from evgs.events.arrays import EventArray
from evgs.geometry import invert_pose
from evgs.sim.lights import LIGHTING
from evgs.sim.presets import SimConfig, preset
from evgs.sim.render import Renderer
from evgs.sim.scene import Scene, make_scene
from evgs.sim.trajectory import ReplayTrajectory

# Vertices used to bound image motion per frame (an even subsample of the ones in view).
MAX_MOTION_VERTICES = 4000
# Time step (s) of the finite difference that estimates the image motion rate.
MOTION_PROBE_S = 1e-3
# Vertices this far outside the image (fraction of its larger side) still bound the motion: they may
# enter the view within the step.
VIEW_MARGIN = 0.25


def project(camera: Camera, T_wc: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of world points seen from ``T_wc`` (NaN behind the camera)."""
    T_cw = invert_pose(T_wc)
    pc = points @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = np.where(pc[:, 2] > 1e-6, pc[:, 2], np.nan)
    return np.stack([camera.fx * pc[:, 0] / z + camera.cx, camera.fy * pc[:, 1] / z + camera.cy], -1)


def _regular_times(rate_hz: float, t_end_us: int) -> np.ndarray:
    step = round(1e6 / rate_hz)
    return np.arange(0, t_end_us + 1, step, dtype=np.int64)


class _MotionBound:
    """Largest time step keeping the image motion of every vertex in (or near) the view under ``max_px``
    pixels. Vertices far outside the view make no events; on a terrain that fills the view they would
    otherwise set the bound (ground near the horizon sweeps across the image plane far off-screen)."""

    def __init__(self, scene: Scene, camera: Camera, trajectory, max_px: float) -> None:
        self.points = scene.vertices
        self.camera, self.trajectory, self.max_px = camera, trajectory, max_px
        m = VIEW_MARGIN * max(camera.width, camera.height)
        self.lo, self.hi = np.array([-m, -m]), np.array([camera.width - 1 + m, camera.height - 1 + m])

    def dt_us(self, t_s: float) -> float:
        T0, T1 = self.trajectory(np.array([t_s, t_s + MOTION_PROBE_S]))
        uv0 = project(self.camera, T0, self.points)
        near = np.flatnonzero(np.all((uv0 >= self.lo) & (uv0 <= self.hi), axis=1))  # NaN: behind
        near = near[:: max(1, len(near) // MAX_MOTION_VERTICES)]
        uv1 = project(self.camera, T1, self.points[near])
        rate = np.nanmax(np.linalg.norm(uv1 - uv0[near], axis=1), initial=0.0) / MOTION_PROBE_S
        return self.max_px / rate * 1e6 if rate > 0 else np.inf


def simulate(cfg: SimConfig, out: str | Path, *, progress: bool = True) -> Sequence:
    """Simulate ``cfg`` into the sequence folder ``out`` (written atomically) and return it. Timing and
    counts land in ``sequence.toml`` under ``[simulator.stats]``."""
    cfg.validate()
    camera = cfg.camera
    scene = make_scene(cfg.target, cfg.material, cfg.mesh_scale, cfg.seed)
    trajectory = cfg.make_trajectory()
    t_end_us = round(trajectory.t_end * 1e6)
    frames_us = _regular_times(cfg.frame_rate, t_end_us)
    range_us = _regular_times(cfg.range_rate, t_end_us)
    required = np.union1d(np.union1d(frames_us, range_us), [t_end_us])
    frame_set, range_set = set(frames_us.tolist()), set(range_us.tolist())
    if len(frames_us) < 2:
        raise ValueError(f"duration {trajectory.t_end} s gives fewer than 2 frames at {cfg.frame_rate} Hz")
    sim = _core.EventSimulator(
        camera.width, camera.height, c_on=cfg.c_on, c_off=cfg.c_off, sigma_c=cfg.sigma_c,
        refractory_us=cfg.refractory_us, log_eps=cfg.log_eps, shot_rate_hz=cfg.shot_rate_hz,
        shot_dark_level=cfg.shot_dark_level, leak_rate_hz=cfg.leak_rate_hz,
        hot_pixel_fraction=cfg.hot_pixel_fraction, hot_pixel_rate_hz=cfg.hot_pixel_rate_hz, seed=cfg.seed,
    )  # fmt: skip
    motion = _MotionBound(scene, camera, trajectory, cfg.max_px_per_frame)
    target_change = cfg.change_fraction * min(cfg.c_on, cfg.c_off)
    min_level = 5.0 * cfg.log_eps
    images: list[np.ndarray] = []
    ranges: list[tuple[int, float]] = []
    range_misses = 0
    stats = {"renders": 0, "rejected_renders": 0, "render_s": 0.0, "events_s": 0.0}

    def render(t_us: int) -> np.ndarray:
        t0 = time.perf_counter()
        img = r.render(trajectory(t_us * 1e-6))
        stats["render_s"] += time.perf_counter() - t0
        stats["renders"] += 1
        return img

    def record(t_us: int, img: np.ndarray) -> None:
        nonlocal range_misses
        if t_us in frame_set:
            images.append(img.copy())
        if t_us in range_set:
            T = trajectory(t_us * 1e-6)
            d = scene.ray_distance(T[:3, 3], T[:3, 2])
            if np.isfinite(d):
                ranges.append((t_us, d))
            else:
                range_misses += 1

    columns = (TextColumn(f"simulate {cfg.name}"), BarColumn(), TextColumn("{task.fields[info]}"))
    with (
        Renderer(scene, camera, LIGHTING[cfg.lighting], msaa=cfg.msaa, shadow_size=cfg.shadow_size) as r,
        Progress(*columns, TimeElapsedColumn(), disable=not progress, transient=True) as bar,
    ):
        task = bar.add_task("sim", total=t_end_us, info="")
        t = 0
        img = render(0)
        sim.push_frame(0, img.ravel())
        record(0, img)
        dt_change = float(cfg.dt_max_us)
        while t < t_end_us:
            next_required = int(required[np.searchsorted(required, t, side="right")])
            step = min(dt_change, motion.dt_us(t * 1e-6), cfg.dt_max_us)
            t_next = min(t + max(int(step), cfg.dt_min_us), next_required)
            img = render(t_next)
            dt = t_next - t
            # Far too coarse (unless already at the minimum step): refuse and retry nearer.
            limit = 2.0 * target_change if dt > cfg.dt_min_us else np.inf
            e0 = time.perf_counter()
            change, added = sim.push_frame_if_smooth(
                t_next, img.ravel(), cfg.change_quantile, min_level, limit
            )
            stats["events_s"] += time.perf_counter() - e0
            if added is None:
                dt_change = max(cfg.dt_min_us, dt * target_change / change)
                stats["rejected_renders"] += 1
                continue
            dt_change = min(dt * target_change / max(change, 1e-12), 2.0 * max(dt_change, dt))
            record(t_next, img)
            t = t_next
            bar.update(task, completed=t, info=f"{sim.num_events:,} events")
    e0 = time.perf_counter()
    ev = EventArray.from_columns(sim.take_events())
    stats["events_s"] += time.perf_counter() - e0
    stats.update(
        events=len(ev), hot_pixels=sim.hot_pixel_count, range_samples=len(ranges), range_misses=range_misses
    )
    poses = trajectory(frames_us * 1e-6)
    meta = {
        "source": "evgs simulate",
        "simulator": {**dataclasses.asdict(cfg), "stats": stats},
    }
    if isinstance(trajectory, ReplayTrajectory):
        meta["simulator"]["poses_t0_s"] = trajectory.t0  # sequence time 0 = the file's first pose
    rng = (np.array([t for t, _ in ranges], np.int64), np.array([d for _, d in ranges]))
    return write_sequence(
        out, cfg.name, camera, ev, frames_us, poses_gt=(frames_us, poses), images=np.stack(images),
        range_samples=rng, meta=meta,
    )  # fmt: skip


def ensure_sequence(name: str, root: Path = Path("data")) -> Path:
    """The folder of the built-in sequence ``synthetic/<preset>`` under ``root``, simulated first if it
    is missing."""
    preset_name = name.removeprefix("synthetic/")
    folder = Path(root) / "synthetic" / preset_name
    if not (folder / "sequence.toml").is_file():
        simulate(preset(preset_name), folder)
    return folder

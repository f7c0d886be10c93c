"""A tiny synthetic event sequence for the SLAM tests (not a test module).

A cloud of textured Gaussians around the origin is rendered with ``evgs.render`` along a known camera
path (a short, slightly accelerating arc looking at the target); events are the crossings of the log
intensity ``log(I + 1/255)`` through multiples of the contrast ``C`` between consecutive renders, spread
evenly in time. So the scene, the poses and the event model are exactly the pipeline's own, and a
stage's result can be checked against the truth.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from evgs.config import load_config
from evgs.data.sequence import Camera, Sequence, write_sequence
from evgs.events.arrays import EventArray
from evgs.geometry import invert_pose, make_pose
from evgs.render import render
from evgs.slam.gaussians import Gaussians
from evgs.slam.guards import BrightnessAnchor
from evgs.slam.pipeline import new_state
from evgs.slam.state import SlamState
from evgs.slam.trajectory import Trajectory
from evgs.slam.windows import EventData

CAMERA = Camera(80, 60, 70.0, 70.0, 40.0, 30.0)
CONTRAST = 0.2
LOG_EPS = 1.0 / 255.0
FRAME_US = 50_000


@dataclass
class Scene:
    gaussians: Gaussians
    frames_us: np.ndarray  # (F,)
    poses: np.ndarray  # (F, 4, 4) GT camera-to-world at the frames


def make_gaussians(n: int = 400, seed: int = 0) -> Gaussians:
    """A lumpy textured target: Gaussians on a 0.5-radius sphere and a flat panel, varied gray."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    pts = 0.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    panel = rng.uniform(-1, 1, size=(n // 3, 3)) * [0.9, 0.25, 0.02] + [0.0, 0.0, 0.2]
    means = np.concatenate([pts, panel])
    m = len(means)
    quats = np.zeros((m, 4))
    quats[:, 0] = 1
    return Gaussians(
        torch.tensor(means),
        torch.full((m, 3), float(np.log(0.07))),
        torch.tensor(quats),
        torch.full((m,), 2.5),
        torch.tensor(rng.uniform(0.15, 1.0, size=(m, 1))),
    )


def look_at(centres: np.ndarray) -> np.ndarray:
    """Camera-to-world poses at ``centres`` with the optical axis (+z) through the origin."""
    z = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=2), centres)


def path(t_s: np.ndarray) -> np.ndarray:
    """A slightly accelerating arc at ~2.2 units from the target, with a little vertical wobble."""
    a = 0.5 * t_s + 0.6 * t_s**2
    c = np.stack([2.2 * np.sin(a), 0.15 * np.sin(4 * t_s), -2.2 * np.cos(a)], axis=1)
    return look_at(c)


@torch.no_grad()
def render_gray(g: Gaussians, T_wc: np.ndarray, camera: Camera = CAMERA) -> np.ndarray:
    viewmats = torch.from_numpy(invert_pose(T_wc)).float()[None]
    out = render(**g.render_inputs(), viewmats=viewmats, camera=camera)
    return out.color[0, ..., 0].numpy().astype(np.float64)


def events_from_log(L: np.ndarray, t_us: np.ndarray, contrast: float) -> EventArray:
    """Events of the log-intensity frames ``L`` (S, H, W) at times ``t_us`` (S,): every crossing of the
    reference ± C, the k-th of n crossings in an interval at its (k+1)/(n+1) point, sorted stably."""
    h, w = L.shape[1:]
    ref = L[0].copy()
    ts, xs, ys, ps = [], [], [], []
    for j in range(1, len(L)):
        n = np.trunc((L[j] - ref) / contrast).astype(np.int64)
        ref += n * contrast
        idx = np.flatnonzero(n)
        cnt = np.abs(n.reshape(-1)[idx])
        rep = np.repeat(idx, cnt)
        k = np.arange(len(rep)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        dt = t_us[j] - t_us[j - 1]
        ts.append(t_us[j - 1] + (k + 1) * dt // (np.repeat(cnt, cnt) + 1))
        ys.append(rep // w)
        xs.append(rep % w)
        ps.append(np.sign(np.repeat(n.reshape(-1)[idx], cnt)))
    t = np.concatenate(ts)
    order = np.argsort(t, kind="stable")
    cat = {"t": t, "x": np.concatenate(xs), "y": np.concatenate(ys), "p": np.concatenate(ps)}
    return EventArray.from_columns({k: v[order] for k, v in cat.items()} | {"width": w, "height": h})


def make_sequence(root: Path, n_frames: int = 9, substeps: int = 12, seed: int = 0) -> tuple[Sequence, Scene]:
    g = make_gaussians(seed=seed)
    frames_us = 1_000_000 + np.arange(n_frames, dtype=np.int64) * FRAME_US
    t_fine = np.linspace(frames_us[0], frames_us[-1], (n_frames - 1) * substeps + 1).round().astype(np.int64)
    T_fine = path((t_fine - frames_us[0]) / 1e6)
    L = np.stack([np.log(render_gray(g, T) + LOG_EPS) for T in T_fine])
    events = events_from_log(L, t_fine, CONTRAST)
    poses = path((frames_us - frames_us[0]) / 1e6)
    seq = write_sequence(
        root, "synth", CAMERA, events, frames_us, poses_gt=(t_fine, T_fine), meta={"source": "test"}
    )
    return seq, Scene(g, frames_us, poses)


def search_state(seq: Sequence, *sets: str) -> SlamState:
    """A fresh run state on ``seq`` with the tiny config set up for the motion search's tests (4 init
    chunks, the plain basis of hypotheses: the tilted one has its own test) and ``sets`` on top."""
    base = [
        "data.event_contrast=0.2",
        "gaussians.bounding_size=1.0",
        "gaussians.init_depth=2.2",
        "gaussians.init_depth_spread=0.5",
        "scale.source=none",
        "init.num_frames=4",
        "init.search_tilt=0",
    ]
    cfg = load_config("synthetic/tiny", [*base, *sets])
    cfg = dataclasses.replace(cfg, seq=str(seq.root))
    return new_state(cfg, EventData.from_sequence(seq, cfg.data))


def gt_state(seq: Sequence, scene: Scene, *sets: str) -> SlamState:
    """A run's state holding the scene itself: its map and its GT knots (tiny config, ``sets`` on top)."""
    cfg = load_config("synthetic/tiny", ["data.event_contrast=0.2", *sets])
    traj, g = Trajectory(scene.frames_us, scene.poses), Gaussians.from_state(scene.gaussians.state())
    data = EventData.from_sequence(seq, cfg.data)
    return SlamState(cfg, data, traj, g, torch.Generator().manual_seed(0), BrightnessAnchor(0.0))

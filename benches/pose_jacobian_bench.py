"""Tracking's pose Jacobian benchmark (not a test): one Levenberg–Marquardt linearisation of 4 views (2
windows × 2 ends) by the rasterizer's forward-mode pose pass (``evgs.render.render_pose_jvp``, what
``tracking.lm_jacobian = "analytic"`` runs) beside the 13 renders of central differences it replaces
(the views and ±ε along each of the six twists, one batched ``render`` call, ``"central"``), on the
spacecraft cloud of ``raster_bench.py``. Prints the time per linearisation and the speed-up.

Run: ``make dev && PYTHONPATH=python:benches $VENV/bin/python benches/pose_jacobian_bench.py [--quick]``
"""

from __future__ import annotations

import argparse
import os
import time
from functools import partial

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the evgs command sets it

import numpy as np  # noqa: E402
import torch  # noqa: E402
from evgs.data.sequence import Camera  # noqa: E402
from evgs.render import render, render_pose_jvp  # noqa: E402
from evgs.slam.lie import se3_hat  # noqa: E402
from raster_bench import spacecraft  # noqa: E402


def views(b: int) -> torch.Tensor:
    """B cameras 9 m from the spacecraft, looking down by 40°, a degree apart in yaw."""
    out = []
    for k in range(b):
        pitch, yaw = np.radians(40.0), np.radians(k)
        rx = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
        ry = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        m = np.eye(4)
        m[:3, :3], m[2, 3] = rx @ ry, 9.0
        out.append(m)
    return torch.tensor(np.array(out), dtype=torch.float32)


def best_of(f, repeats: int) -> float:
    f()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one size, fewer repeats")
    args = ap.parse_args()
    repeats = 3 if args.quick else 7
    sizes = [(160, 120)] if args.quick else [(160, 120), (320, 240)]
    print(f"torch threads: {torch.get_num_threads()}; one linearisation of 4 views, best of {repeats}")
    heads = f"{'image':>9} {'Gaussians':>9} | {'forward-mode JVP':>16} | {'13 renders (central)':>20}"
    print(f"{heads} | speed-up")
    for width, height in sizes:
        f = 0.5 * width / np.tan(np.radians(30.0))
        cam = Camera(width=width, height=height, fx=f, fy=f, cx=width / 2 - 0.5, cy=height / 2 - 0.5)
        vm = views(4)
        tangents = se3_hat(torch.eye(6))[None] @ vm[:, None]  # d(exp(ε·ξ̂)·V)/dε for the six unit twists
        moved = 1e-3 * tangents.transpose(0, 1)  # (6, B, 4, 4)
        variants = torch.cat([vm[None], vm + moved, vm - moved]).reshape(-1, 4, 4)
        for n in (10_000, 50_000):
            g = spacecraft(n)
            jvp = best_of(partial(render_pose_jvp, **g, viewmats=vm, tangents=tangents, camera=cam), repeats)
            central = best_of(partial(render, **g, viewmats=variants, camera=cam), repeats)
            print(f"{width:>4}×{height:<4} {n:>9} | {1e3 * jvp:>13.1f} ms | {1e3 * central:>17.1f} ms | "
                  f"{central / jvp:>6.2f}×")  # fmt: skip


if __name__ == "__main__":
    main()

"""Rasterizer benchmark (not a test): forward and backward time per view and pixel–Gaussian evaluations
per second for the Rust rasterizer, 1 and 2 threads, beside two pure-torch float32 baselines: the dense
reference and the tile-based torch rasterizer.

Pixel–Gaussian evaluations are counted two ways, side by side:
- "std" (the standard 3DGS/gsplat count, the sense of the speed targets): forward, every in-image pixel ×
  every entry of its tile's depth-sorted list up to and including the one at which the pixel saturated
  (or the whole list); backward, every pixel × the entries up to and including its last contributor.
- "seg" (what this rasterizer really computes): for each tile and each splat in its list until the
  tile's pixels all stopped, the in-image pixels of the 8-pixel row segments (one AVX2 register) that
  the splat's ellipse reaches and that still had a live pixel (``raster::Forward::evaluations``).
The dense reference (tests/raster_reference.py) evaluates every Gaussian at every pixel; the tile-based
torch rasterizer (tests/raster_tile_torch.py) runs the tiled algorithm with torch ops, every Gaussian of
a tile against every pixel of it. Both are compared by wall time for the same image (speed-up columns).

Run: ``make dev && PYTHONPATH=python:tests $VENV/bin/python benches/raster_bench.py [--quick]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from evgs.data.sequence import Camera


def spacecraft(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A satellite-like cloud (body 1.6×1.6×2.4 m plus two 4×1.2 m solar panels) of ``n`` Gaussians on
    the surfaces, sized to tile them; grey levels in (0.2, 0.9), opacities in (0.5, 0.95)."""
    rng = np.random.default_rng(seed)
    parts = [  # (centre, half-extent) boxes; the panels are thin
        ((0.0, 0.0, 0.0), (0.8, 0.8, 1.2)),
        ((-2.9, 0.0, 0.0), (2.0, 0.6, 0.02)),
        ((2.9, 0.0, 0.0), (2.0, 0.6, 0.02)),
    ]
    areas = np.array([8 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2]) for _, e in parts])
    counts = rng.multinomial(n, areas / areas.sum())
    pts = []
    for (centre, ext), k in zip(parts, counts, strict=True):
        ext = np.array(ext)
        p = rng.uniform(-1, 1, (k, 3)) * ext
        # Push each point to the face along its largest normalised coordinate.
        axis = np.argmax(np.abs(p) / ext, axis=1)
        p[np.arange(k), axis] = np.sign(p[np.arange(k), axis]) * ext[axis]
        pts.append(p + centre)
    means = np.concatenate(pts)
    spacing = np.sqrt(areas.sum() / max(n, 1))
    log_scales = np.log(spacing * rng.uniform(0.4, 0.9, (n, 3)))
    quats = rng.normal(size=(n, 4))
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return {
        "means": t(means),
        "log_scales": t(log_scales),
        "quats": t(quats),
        "opacities": t(rng.uniform(0.5, 0.95, n)),
        "colors": t(rng.uniform(0.2, 0.9, (n, 1))),
    }


def camera_for(width: int, height: int) -> tuple[Camera, torch.Tensor]:
    """A 60° camera 9 m from the spacecraft, looking down at it by 40°: the panels span most of the
    image width, the rest is black background."""
    f = 0.5 * width / np.tan(np.radians(30))
    cam = Camera(width, height, f, f, width / 2, height / 2)
    a = np.radians(40)
    rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    vm = np.eye(4)
    vm[:3, :3], vm[:3, 3] = rot, (0.0, 0.0, 9.0)
    return cam, torch.tensor(vm, dtype=torch.float32)[None]


SIZES = [(320, 240), (640, 480)]
COUNTS = [10_000, 30_000, 100_000, 1_000_000]
REF_SUBSET = 100  # Gaussians the dense reference really renders; its cost is linear in N


def _median_ms(f, reps: int) -> tuple[float, float]:
    """Median wall and CPU (all threads of the process) milliseconds of ``f()``."""
    wall, cpu = [], []
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        f()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def measure_rust(quick: bool) -> list[dict]:
    """Time forward and backward of one view for every size and count (in this process's thread count)."""
    from evgs import _core
    from evgs.render import _flat

    rows = []
    for n in COUNTS[:2] if quick else COUNTS:
        g = spacecraft(n)
        flat = [_flat(g[k]) for k in ("means", "log_scales", "quats", "opacities", "colors")]
        for w, h in SIZES:
            cam, vm = camera_for(w, h)
            args = [*flat, 1, _flat(vm), w, h, cam.fx, cam.fy, cam.cx, cam.cy, 0.01, 1e10]
            args.append(np.zeros(1, np.float32))
            reps = 3 if n >= 1_000_000 else 7
            out = _core.rasterize_forward(*args)  # warm-up
            fwd_ms, fwd_cpu = _median_ms(lambda a=args: _core.rasterize_forward(*a), reps)
            rng = np.random.default_rng(1)
            up = [rng.normal(size=w * h).astype(np.float32) for _ in range(3)]
            back = lambda o=out, a=args, u=up: _core.rasterize_backward(o[4], *a[:7], *u)  # noqa: E731
            bwd_evals = back()[-1]
            bwd_ms, bwd_cpu = _median_ms(back, reps)
            rows.append(
                {"n": n, "w": w, "h": h, "fwd_ms": fwd_ms, "bwd_ms": bwd_ms,
                 "fwd_cpu": fwd_cpu, "bwd_cpu": bwd_cpu,
                 "fwd_evals": out[4].forward_evaluations, "bwd_evals": int(bwd_evals),
                 "fwd_std": out[4].forward_evaluations_standard,
                 "bwd_std": out[4].backward_evaluations_standard,
                 "coverage": float(out[2].mean())}
            )  # fmt: skip
    return rows


def measure_reference(w: int, h: int) -> tuple[float, float]:
    """Dense float32 torch reference (tests/raster_reference.py) on REF_SUBSET Gaussians: forward and
    backward ms for one view, the best over 1 and 2 torch threads and two runs each."""
    from raster_reference import render_reference

    g = {k: v.requires_grad_() for k, v in spacecraft(REF_SUBSET).items()}
    cam, vm = camera_for(w, h)
    best = (np.inf, np.inf)
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for _ in range(2):
            t0 = time.perf_counter()
            color, depth, alpha, _ = render_reference(**g, viewmats=vm, camera=cam)
            t1 = time.perf_counter()
            (color.sum() + depth.sum() + alpha.sum()).backward()
            t2 = time.perf_counter()
            best = (min(best[0], 1e3 * (t1 - t0)), min(best[1], 1e3 * (t2 - t1)))
    return best


def measure_tile_torch(n: int, w: int, h: int) -> tuple[float, float]:
    """Tile-based torch rasterizer on all ``n`` Gaussians: forward and backward ms for one view, the best
    over 1 and 2 torch threads (one run each). At 1 M Gaussians only the forward pass is timed (without
    autograd: the saved per-tile tensors would need tens of GB); the backward is then NaN."""
    from raster_tile_torch import render_tiles

    cam, vm = camera_for(w, h)
    with_grad = n < 1_000_000
    g = {k: v.requires_grad_(with_grad) for k, v in spacecraft(n).items()}
    best = (np.inf, np.inf if with_grad else np.nan)
    for threads in (1, 2):
        torch.set_num_threads(threads)
        with torch.set_grad_enabled(with_grad):
            t0 = time.perf_counter()
            color, depth, alpha, _ = render_tiles(**g, viewmats=vm, camera=cam)
            t1 = time.perf_counter()
        if with_grad:
            (color.sum() + depth.sum() + alpha.sum()).backward()
            best = (best[0], min(best[1], 1e3 * (time.perf_counter() - t1)))
        best = (min(best[0], 1e3 * (t1 - t0)), best[1])
        del color, depth, alpha
    return best


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only 10 K and 30 K Gaussians")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(measure_rust(args.quick)))
        return
    results = {}
    for threads in (1, 2):
        env = {**os.environ, "RAYON_NUM_THREADS": str(threads)}
        cmd = [sys.executable, __file__, "--worker"] + (["--quick"] if args.quick else [])
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
        results[threads] = json.loads(out)
    ref = {(w, h): measure_reference(w, h) for w, h in SIZES}
    tiled = {(r["n"], r["w"], r["h"]): measure_tile_torch(r["n"], r["w"], r["h"]) for r in results[2]}

    print(f"CPU: {cpu_model()}, {os.cpu_count()} logical CPUs; load average {os.getloadavg()[0]:.1f}")
    print("evals: 'std' = standard 3DGS/gsplat count, 'seg' = pairs this rasterizer evaluates (module")
    print(
        "docstring); G/s = G evals per wall second (std/seg) with 1 thread (1T) and 2 threads (2T); 'cpu' ="
    )
    print("CPU ms of the 1-thread run (meaningful when the machine is shared); dense torch float32 reference")
    print(
        f"extrapolated linearly from {REF_SUBSET} Gaussians; tile-based torch float32 (all Gaussians; at 1 M"
    )
    print("forward only); speed-up = torch ms / Rust 2T ms, forward/backward, vs dense and vs tile-torch\n")
    head = (
        f"{'image':>7} {'N':>7} {'cov':>4} | {'fwd evals std/seg':>17} {'ms 1T':>7} {'cpu':>6} {'2T':>6} "
        f"{'G/s 1T':>9} {'G/s 2T':>9} | {'bwd evals std/seg':>17} {'ms 1T':>7} {'cpu':>6} {'2T':>6} "
        f"{'G/s 1T':>9} {'G/s 2T':>9} | {'dense fwd/bwd ms':>16} {'tile-torch':>13} | "
        f"{'x vs dense':>11} {'x vs tiled':>11}"
    )
    print(head)
    print("-" * len(head))

    def ratio(torch_ms: float, rust_ms: float, width: int) -> str:
        return f"{torch_ms / rust_ms:>{width}.0f}x" if np.isfinite(torch_ms) else f"{'-':>{width + 1}}"

    def rate(evals: int, ms: float) -> str:
        return f"{evals / ms / 1e6:.2f}"

    for r1, r2 in zip(results[1], results[2], strict=True):
        rf, rb = ref[(r2["w"], r2["h"])]
        scale = r2["n"] / REF_SUBSET
        dense_f, dense_b = rf * scale, rb * scale
        cols = [f"{r2['w']:>3}x{r2['h']:<3} {r2['n']:>7} {r2['coverage']:>4.2f}"]
        for d in ("fwd", "bwd"):
            std, seg = r2[f"{d}_std"], r2[f"{d}_evals"]
            cols.append(
                f"{std / 1e6:>7.1f}M/{seg / 1e6:>6.1f}M {r1[f'{d}_ms']:>7.2f} {r1[f'{d}_cpu']:>6.2f} "
                f"{r2[f'{d}_ms']:>6.2f} "
                f"{rate(std, r1[f'{d}_ms']):>4}/{rate(seg, r1[f'{d}_ms']):<4} "
                f"{rate(std, r2[f'{d}_ms']):>4}/{rate(seg, r2[f'{d}_ms']):<4}"
            )
        tf, tb = tiled[(r2["n"], r2["w"], r2["h"])]
        tb_text = f"{tb:<6.0f}" if np.isfinite(tb) else f"{'-':<6}"
        cols.append(f"{dense_f:>8.0f}/{dense_b:<7.0f} {tf:>6.0f}/{tb_text}")
        cols.append(
            f"{ratio(dense_f, r2['fwd_ms'], 5)}/{ratio(dense_b, r2['bwd_ms'], 4)} "
            f"{ratio(tf, r2['fwd_ms'], 4)}/{ratio(tb, r2['bwd_ms'], 4)}"
        )
        print(" | ".join(cols))


if __name__ == "__main__":
    main()

"""Event-frame accumulation rate: evgs (Rust, rayon) side by side with numpy ``np.bincount`` / ``np.add.at``.

Run: ``make dev && PYTHONPATH=python $VENV/bin/python benches/frames_bench.py`` (or ``make bench``).
Prints M events/s (wall clock, best of a few runs) for batches of windows on a 640×480 sensor, for
uniformly random events (worst case for caches) and for events on the edge of a moving disc (a target
on a black background, closer to real space data). ``cpu`` is events per CPU-second of the whole
process (all threads): on a shared machine it shows the code's speed independent of the load.
"""

from __future__ import annotations

import os
import time

import numpy as np
from evgs.data.sequence import Camera
from evgs.events.arrays import EventArray
from evgs.events.frames import UndistortMap, WindowSampler, accumulate

W, H, N = 640, 480, 20_000_000
C = 0.1


def uniform_events(rng: np.random.Generator) -> EventArray:
    x = rng.integers(0, W, N).astype(np.uint16)
    y = rng.integers(0, H, N).astype(np.uint16)
    p = rng.choice(np.array([-1, 1], np.int8), N)
    return EventArray(np.arange(N, dtype=np.int64), x, y, p, W, H)


def edge_events(rng: np.random.Generator) -> EventArray:
    """Events within ~2 px of a disc's rim (radius 120 px) whose centre drifts across the image."""
    t = np.arange(N, dtype=np.int64)
    cx = 200 + 240 * t / N
    angle = rng.uniform(0, 2 * np.pi, N)
    r = 120 + rng.normal(0, 2, N)
    x = np.clip(cx + r * np.cos(angle), 0, W - 1).astype(np.uint16)
    y = np.clip(H / 2 + r * np.sin(angle), 0, H - 1).astype(np.uint16)
    p = np.where(np.cos(angle) > 0, 1, -1).astype(np.int8)
    return EventArray(t, x, y, p, W, H)


def best(fn, reps: int) -> tuple[float, float]:
    """Best wall and CPU seconds of ``reps`` calls (after one warm-up)."""
    fn()
    wall, cpu = [], []
    for _ in range(reps):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return min(wall), min(cpu)


def numpy_bincount(ev: EventArray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    out = np.empty((len(starts), H, W), np.float32)
    for b, (s, e) in enumerate(zip(starts, ends, strict=True)):
        idx = ev.y[s:e].astype(np.int64) * W + ev.x[s:e]
        out[b] = (C * np.bincount(idx, weights=ev.p[s:e], minlength=H * W)).reshape(H, W)
    return out


def numpy_add_at(ev: EventArray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    out = np.zeros((len(starts), H * W), np.float32)
    for b, (s, e) in enumerate(zip(starts, ends, strict=True)):
        np.add.at(out[b], ev.y[s:e].astype(np.int64) * W + ev.x[s:e], C * ev.p[s:e].astype(np.float32))
    return out.reshape(-1, H, W)


def rates(ev: EventArray, umap: UndistortMap, starts: np.ndarray, ends: np.ndarray) -> list[float]:
    """M events/s of every column for one batch of windows."""
    n_ev = float((ends - starts).sum())
    out = np.empty((len(starts), H, W), np.float32)
    wall, cpu = best(lambda: accumulate(ev, starts, ends, c_on=C, out=out), 3)
    fresh, _ = best(lambda: accumulate(ev, starts, ends, c_on=C), 3)
    asym, _ = best(lambda: accumulate(ev, starts, ends, c_on=C, c_off=0.2, out=out), 3)
    und, _ = best(lambda: accumulate(ev, starts, ends, c_on=C, undistort=umap, out=out), 3)
    bc, _ = best(lambda: numpy_bincount(ev, starts, ends), 1)
    k = min(len(starts), 2)  # np.add.at is slow: time two windows
    aa, _ = best(lambda: numpy_add_at(ev, starts[:k], ends[:k]), 1)
    n_aa = float((ends[:k] - starts[:k]).sum())
    return [
        x / 1e6
        for x in (n_ev / wall, n_ev / cpu, n_ev / fresh, n_ev / asym, n_ev / und, n_ev / bc, n_aa / aa)
    ]


def main() -> None:
    rng = np.random.default_rng(0)
    threads = os.environ.get("RAYON_NUM_THREADS", str(os.cpu_count()))
    print(f"event frames, {W}x{H}, C = {C}, rayon threads = {threads}; M events/s (best of 3)")
    cols = {
        "evgs out=": 10,
        "(cpu)": 7,
        "evgs new": 9,
        "C_on≠C_off": 11,
        "undist.": 8,
        "bincount": 9,
        "add.at": 7,
    }
    print(f"{'events':<8} {'windows':<16} " + " ".join(f"{k:>{w}}" for k, w in cols.items()))
    umap = UndistortMap.from_camera(Camera(W, H, 500.0, 500.0, 319.5, 239.5, (-0.2, 0.05, 0.0, 0.0, 0.0)))
    for dist, ev in (("uniform", uniform_events(rng)), ("edge", edge_events(rng))):
        for w_lo, w_hi, batch in ((50_000, 50_000, 32), (200_000, 200_000, 16), (2_000_000, 2_000_000, 4),
                                  (50_000, 2_000_000, 8), (2_000_000, 2_000_000, 1)):  # fmt: skip
            starts, ends = WindowSampler(N, w_lo, w_hi, seed=1).sample(batch)
            label = f"{w_lo // 1000}k" + (f"-{w_hi // 1000}k" if w_hi != w_lo else "") + f" x{batch}"
            row = rates(ev, umap, starts, ends)
            print(
                f"{dist:<8} {label:<16} "
                + " ".join(f"{r:>{w}.0f}" for r, w in zip(row, cols.values(), strict=True))
            )


if __name__ == "__main__":
    main()

"""Simulator benchmark: 2 s of the 640×480 ``orbit`` preset at the adaptive render rate, split into
rendering and event generation (target ≤ 60 s on 2 cores). Prints a table to paste into an issue.

Run: ``PYTHONPATH=python python benches/sim_bench.py [--duration S] [--preset NAME]``
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path

from evgs.sim import preset, simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="orbit")
    ap.add_argument("--duration", type=float, default=2.0)
    args = ap.parse_args()
    cfg = dataclasses.replace(preset(args.preset), duration=args.duration)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        seq = simulate(cfg, Path(tmp) / "seq", progress=False)
        total = time.perf_counter() - t0
    s = seq.meta["simulator"]["stats"]
    rows = [
        ("preset", f"{cfg.name} {cfg.width}x{cfg.height}, {cfg.duration:g} s"),
        ("threads (RAYON_NUM_THREADS)", os.environ.get("RAYON_NUM_THREADS", f"all ({os.cpu_count()} cpus)")),
        ("renders (rejected)", f"{s['renders']} ({s['rejected_renders']})"),
        ("render time", f"{s['render_s']:.2f} s ({s['render_s'] / s['renders'] * 1e3:.1f} ms/frame)"),
        ("event generation time", f"{s['events_s']:.2f} s"),
        ("events", f"{s['events']:,}"),
        ("events/s generated", f"{s['events'] / s['events_s']:,.0f}"),
        ("total wall time (incl. writing)", f"{total:.2f} s"),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"| {k:<{width}} | {v} |")


if __name__ == "__main__":
    main()

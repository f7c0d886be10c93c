"""Event-file decode rates, ours beside reference readers, in one table (a benchmark, not a test).

    PYTHONPATH=python python benches/events_io.py [--events 10000000]

Files are generated once (``synthetic_events``, seed 0) and cached under ``$EVGS_BENCH_CACHE``
(default ``~/.cache/evgs/bench-events``). Each rate is the best of ``--repeat`` wall-clock runs.
The comparison readers faery, aedat and evlib are optional bench-only extras, looked up on the normal
path and in ``$EVGS_BENCH_EXTRAS`` (default ``~/.cache/evgs/bench-extras``), where
``pip install --no-deps --target ~/.cache/evgs/bench-extras faery aedat evlib`` puts them without
touching the project's environment.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import polars as pl
from evgs.events.io import read_events, write_events
from evgs.events.synthetic import synthetic_events
from rich.console import Console
from rich.table import Table

FILES = {
    "CSV": ("csv", "events.csv"),
    "NPY": ("npy", "events.npy"),
    "Parquet": ("parquet", "events.parquet"),
    "EVT2": ("evt2", "events_evt2.raw"),
    "EVT3": ("evt3", "events_evt3.raw"),
    "AEDAT4 LZ4": ("aedat4", "events_lz4.aedat4"),
    "AEDAT4 ZSTD": ("aedat4-zstd", "events_zstd.aedat4"),
}


def optional(name: str):
    extras = os.environ.get("EVGS_BENCH_EXTRAS", str(Path.home() / ".cache/evgs/bench-extras"))
    if Path(extras).is_dir() and extras not in sys.path:
        sys.path.append(extras)
    try:
        return importlib.import_module(name)
    except Exception:
        return None


def rate(fn: Callable[[], int], repeat: int) -> float:
    """Best-of-``repeat`` events per second of ``fn`` (which returns the event count)."""
    best, n = float("inf"), 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        n = fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def aedat_count(path: Path, aedat) -> int:
    return sum(len(p["events"]) for p in aedat.Decoder(str(path)) if "events" in p)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=10_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cache = Path(os.environ.get("EVGS_BENCH_CACHE", Path.home() / ".cache/evgs/bench-events")) / str(
        args.events
    )
    ev = None
    for fmt, name in FILES.values():
        if not (cache / name).exists():
            ev = ev if ev is not None else synthetic_events(args.events, seed=0)
            write_events(cache / name, ev, fmt)

    faery, aedat, evlib = optional("faery"), optional("aedat"), optional("evlib")
    na = "n/a (not installed)"
    faery_fn = faery and (lambda p: len(faery.events_stream_from_file(p).to_array()))
    evlib_fn = evlib and (lambda p: len(evlib.load_events(str(p), sort=False).collect()))
    aedat_fn = aedat and (lambda p: aedat_count(p, aedat))
    camera = [("faery", faery_fn), ("evlib", evlib_fn)]
    refs: dict[str, list[tuple[str, Callable[[Path], int] | None]]] = {
        "CSV": [("polars.read_csv", lambda p: len(pl.read_csv(p)))],
        "NPY": [("numpy.load", lambda p: len(np.load(p)))],
        "Parquet": [("polars.read_parquet", lambda p: len(pl.read_parquet(p)))],
        "EVT2": camera,
        "EVT3": camera,
        "AEDAT4 LZ4": [*camera, ("aedat", aedat_fn)],
        "AEDAT4 ZSTD": [*camera, ("aedat", aedat_fn)],
    }
    cores = len(os.sched_getaffinity(0))
    table = Table(title=f"event decode, {args.events / 1e6:g} M events, {cores} cores, best of {args.repeat}")
    for col in ("format", "MB", "evgs M ev/s", "reference", "ref M ev/s", "evgs / ref"):
        table.add_column(col, justify="left" if col in ("format", "reference") else "right")
    for label, (_, name) in FILES.items():
        path = cache / name
        ours = rate(lambda p=path: len(read_events(p)), args.repeat)
        for i, (ref, fn) in enumerate(refs[label]):
            try:
                r = rate(lambda p=path, f=fn: f(p), args.repeat) if fn else None
                ref_cell, ratio = (f"{r / 1e6:.1f}", f"{ours / r:.2f}x") if r else (na, "")
            except Exception as e:  # a reference reader that cannot read this file is reported, not fatal
                ref_cell, ratio = f"failed: {type(e).__name__}", ""
            head = (
                (label, f"{path.stat().st_size / 1e6:.0f}", f"{ours / 1e6:.1f}") if i == 0 else ("", "", "")
            )
            table.add_row(*head, ref, ref_cell, ratio)
    Console(width=110).print(table)


if __name__ == "__main__":
    main()

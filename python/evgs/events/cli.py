"""``evgs events ...``: inspect, convert, slice event files, and the preprocessing demo.

All commands stream in bounded memory (except into camera formats, encoded at close); outputs are
written atomically; every event not written is counted and reported.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from evgs.events.arrays import EventArray
from evgs.events.io import (
    DEFAULT_BATCH,
    READ_FORMATS,
    WRITE_FORMATS,
    EventSource,
    EventWriter,
    open_events,
    read_events,
    write_events,
)
from evgs.events.synthetic import synthetic_events

_err = Console(stderr=True)


def _read_options(args: argparse.Namespace, require_sorted: bool) -> dict:
    """Reader options from the command line; only those given (formats reject ones they lack)."""
    opts = {
        "width": args.width,
        "height": args.height,
        "time_unit": args.time_unit,
        "delimiter": args.delimiter,
        "columns": args.columns,
        "has_header": args.header,
        "time_shift": args.time_shift or None,
        "drop_outside": getattr(args, "drop_outside", False) or None,
        "require_sorted": require_sorted or None,
    }
    return {k: v for k, v in opts.items() if v is not None}


def _add_read_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("input options")
    g.add_argument("--from", dest="fmt_in", choices=(*READ_FORMATS, "csv", "txt"), help="input format")
    g.add_argument("--width", type=int, help="sensor width (overrides the file's)")
    g.add_argument("--height", type=int, help="sensor height (overrides the file's)")
    g.add_argument("--time-unit", choices=("s", "ms", "us", "ns"), help="time unit of text/npy/hdf5 input")
    g.add_argument("--delimiter", help="text: field delimiter (one character or 'whitespace')")
    g.add_argument("--columns", help="text/npy: column roles, one of t,x,y,p,_ per column (e.g. xytp)")
    g.add_argument("--header", action=argparse.BooleanOptionalAction, default=None, help="text: header row")
    g.add_argument("--time-shift", action="store_true", help="EVT: times relative to the first time base")


def _open(args: argparse.Namespace, path: str, require_sorted: bool) -> EventSource:
    try:
        return open_events(path, args.fmt_in, **_read_options(args, require_sorted))
    except TypeError as e:
        raise ValueError(f"{path}: {e}") from None


def _batches(src: EventSource, batch: int, label: str) -> Iterator[EventArray]:
    """The source's batches under a progress bar (on stderr, only when it is a terminal)."""
    columns = (TextColumn(label), BarColumn(), TextColumn("{task.percentage:>5.1f}%"), TimeElapsedColumn())
    with Progress(*columns, console=_err, transient=True, disable=not _err.is_terminal) as bar:
        task = bar.add_task(label, total=1.0)
        for ev in src.batches(batch):
            bar.update(task, completed=src.progress)
            yield ev


@dataclass
class Selection:
    """Which events to keep: a time range [t0, t1) in µs, an index range, a region of interest."""

    t0: int | None = None
    t1: int | None = None
    start: int | None = None
    stop: int | None = None
    roi: tuple[int, int, int, int] | None = None
    counts: dict[str, int] = field(default_factory=lambda: {"time range": 0, "index range": 0, "roi": 0})
    seen: int = 0

    def apply(self, ev: EventArray) -> EventArray:
        n = len(ev)
        keep = np.ones(n, bool)
        if self.start is not None or self.stop is not None:
            idx = np.arange(self.seen, self.seen + n)
            m = (idx >= (self.start or 0)) & (idx < (self.stop if self.stop is not None else np.inf))
            self.counts["index range"] += int(np.count_nonzero(keep & ~m))
            keep &= m
        self.seen += n
        if self.t0 is not None or self.t1 is not None:
            m = np.ones(n, bool)
            if self.t0 is not None:
                m &= ev.t >= self.t0
            if self.t1 is not None:
                m &= ev.t < self.t1
            self.counts["time range"] += int(np.count_nonzero(keep & ~m))
            keep &= m
        width, height, x, y = ev.width, ev.height, ev.x, ev.y
        if self.roi is not None:
            x0, y0, x1, y1 = self.roi
            m = (ev.x >= x0) & (ev.x < x1) & (ev.y >= y0) & (ev.y < y1)
            self.counts["roi"] += int(np.count_nonzero(keep & ~m))
            keep &= m
            x, y, width, height = x - np.uint16(x0), y - np.uint16(y0), x1 - x0, y1 - y0
        if keep.all() and self.roi is None:
            return ev
        return EventArray(ev.t[keep], x[keep], y[keep], ev.p[keep], width, height)


def _report(counts: dict[str, int], skipped: dict[str, int]) -> str:
    parts = [f"{v} outside the {k}" for k, v in counts.items() if v]
    parts += [f"{v} {k.replace('_', ' ')}" for k, v in skipped.items() if v]
    return "; ".join(parts) if parts else "none"


def _stream(args: argparse.Namespace, sel: Selection, label: str) -> int:
    src = _open(args, args.input, require_sorted=not args.allow_unsorted)
    out_fmt = args.fmt_out
    if sel.roi is not None:
        x0, y0, x1, y1 = sel.roi
        if not (0 <= x0 < x1 and 0 <= y0 < y1):
            raise ValueError(f"--roi {x0} {y0} {x1} {y1}: need 0 <= x0 < x1 and 0 <= y0 < y1")
        width, height = x1 - x0, y1 - y0
    else:
        width, height = src.width, src.height
    t_start = time.perf_counter()
    with EventWriter(args.output, out_fmt, width, height) as w:
        for ev in _batches(src, args.batch, label):
            w.write(sel.apply(ev))
    dt = time.perf_counter() - t_start
    print(f"{args.output}: wrote {w.count} events ({w.format}) from {src.format} in {dt:.2f} s")
    print(f"not written: {_report(sel.counts, src.skipped)}")
    return 0


def _sec_to_us(s: float | None) -> int | None:
    return None if s is None else round(s * 1e6)


def cmd_convert(args: argparse.Namespace) -> int:
    sel = Selection(t0=_sec_to_us(args.t0), t1=_sec_to_us(args.t1), roi=tuple(args.roi) if args.roi else None)
    return _stream(args, sel, "convert")


def cmd_slice(args: argparse.Namespace) -> int:
    if (args.t0 is not None or args.t1 is not None) and (args.start is not None or args.stop is not None):
        raise ValueError("give a time range (--t0/--t1) or an index range (--start/--stop), not both")
    sel = Selection(t0=_sec_to_us(args.t0), t1=_sec_to_us(args.t1), start=args.start, stop=args.stop)
    return _stream(args, sel, "slice")


def describe(src: EventSource, batch: int = DEFAULT_BATCH) -> dict:
    """Streaming summary of an event file (what ``evgs events info`` prints)."""
    n = on = 0
    t_first = t_last = t_min = t_max = None
    xmax = ymax = -1
    first_decrease = None
    for ev in _batches(src, batch, "info"):
        if not len(ev):
            continue
        if first_decrease is None:
            prev = np.concatenate([[t_last if t_last is not None else ev.t[0]], ev.t[:-1]])
            bad = np.flatnonzero(ev.t < prev)
            first_decrease = n + int(bad[0]) if bad.size else None
        t_first = int(ev.t[0]) if t_first is None else t_first
        t_last = int(ev.t[-1])
        t_min = min(int(ev.t.min()), t_min if t_min is not None else int(ev.t[0]))
        t_max = max(int(ev.t.max()), t_max if t_max is not None else int(ev.t[0]))
        xmax, ymax = max(xmax, int(ev.x.max())), max(ymax, int(ev.y.max()))
        on += int(np.count_nonzero(ev.p > 0))
        n += len(ev)
    duration = (t_max - t_min) / 1e6 if n else 0.0
    return {
        "format": src.format,
        "text_layout": src.text_layout,
        "events": n,
        "t_first_us": t_first,
        "t_last_us": t_last,
        "duration_s": duration,
        "rate_ev_per_s": n / duration if duration > 0 else None,
        "sensor": (src.width, src.height),
        "max_xy": (xmax, ymax),
        "on": on,
        "off": n - on,
        "sorted": first_decrease is None,
        "first_decrease": first_decrease,
        "skipped": src.skipped,
    }


def cmd_info(args: argparse.Namespace) -> int:
    d = describe(_open(args, args.file, require_sorted=False), args.batch)
    fmt = d["format"]
    if d["text_layout"]:
        lay = d["text_layout"]
        header = "yes" if lay["has_header"] else "no"
        fmt += (
            f" (delimiter {lay['delimiter']!r}, header {header}, columns {lay['columns']}, "
            f"time unit {lay['time_unit']})"
        )
    n = d["events"]
    w, h = d["sensor"]
    sensor = f"{w}x{h}" if w and h else f"unknown (max x {d['max_xy'][0]}, max y {d['max_xy'][1]})"
    rate = f"{d['rate_ev_per_s'] / 1e6:.3f} M ev/s" if d["rate_ev_per_s"] else "n/a"
    sorted_ = "yes" if d["sorted"] else f"no (first decrease at event {d['first_decrease']})"
    print(f"file:      {args.file}")
    print(f"format:    {fmt}")
    print(f"events:    {n}")
    print(f"time:      {d['t_first_us']} .. {d['t_last_us']} us (duration {d['duration_s']:.6f} s)")
    print(f"rate:      {rate}")
    print(f"sensor:    {sensor}")
    if n:
        print(f"polarity:  on {d['on']} ({100 * d['on'] / n:.1f}%), off {d['off']}")
    print(f"sorted:    {sorted_}")
    print(f"skipped:   {_report({}, d['skipped'])}")
    return 0


def _same(a: EventArray, b: EventArray) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in "txyp")


def cmd_demo(args: argparse.Namespace) -> int:
    """Write a synthetic stream in every format, read each back, convert each to Parquet, compare."""
    out = Path(args.out)
    ev = synthetic_events(args.events, seed=args.seed)
    files = {
        "parquet": "events.parquet",
        "csv": "events.csv",
        "txt": "events.txt",
        "npy": "events.npy",
        "hdf5": "events.h5",
        "evt2": "events_evt2.raw",
        "evt3": "events_evt3.raw",
        "aedat4": "events.aedat4",
    }
    table = Table(
        title=f"evgs events demo: {len(ev)} synthetic events, {ev.width}x{ev.height}, seed {args.seed}"
    )
    for col in ("format", "MB", "write s", "read s", "read M ev/s", "round trip", "→ parquet"):
        table.add_column(col, justify="left" if col == "format" else "right")
    ok = True
    for fmt, name in files.items():
        path = out / name
        t0 = time.perf_counter()
        write_events(path, ev, fmt)
        t1 = time.perf_counter()
        back = read_events(path)
        t2 = time.perf_counter()
        conv = out / "converted" / f"{name}.parquet"
        with EventWriter(conv, "parquet", ev.width, ev.height) as w:
            for b in open_events(path, require_sorted=True).batches(len(ev) // 7 + 1):
                w.write(b)
        same, same_conv = _same(ev, back), _same(ev, read_events(conv))
        ok &= same and same_conv
        table.add_row(
            fmt,
            f"{path.stat().st_size / 1e6:.1f}",
            f"{t1 - t0:.3f}",
            f"{t2 - t1:.3f}",
            f"{len(ev) / (t2 - t1) / 1e6:.1f}",
            "ok" if same else "MISMATCH",
            "ok" if same_conv else "MISMATCH",
        )
    Console().print(table)
    for name in files.values():
        print()
        cmd_info(argparse.Namespace(file=str(out / name), batch=DEFAULT_BATCH, **_no_read_options()))
    return 0 if ok else 1


def _no_read_options() -> dict:
    keys = ("fmt_in", "width", "height", "time_unit", "delimiter", "columns", "header")
    return {**dict.fromkeys(keys), "time_shift": False}


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("events", help="inspect, convert and slice event files")
    esub = parser.add_subparsers(dest="events_command", metavar="SUBCOMMAND")
    esub.required = True
    batch = {"type": int, "default": DEFAULT_BATCH, "help": "events per streamed batch"}

    p = esub.add_parser("info", help="format, count, duration, rate, sensor size, polarity, sortedness")
    p.add_argument("file")
    p.add_argument("--batch", **batch)
    _add_read_args(p)
    p.set_defaults(func=cmd_info)

    for name, func, help_ in (
        ("convert", cmd_convert, "convert between formats, optionally cutting a time range or ROI"),
        ("slice", cmd_slice, "cut a time range (--t0/--t1) or event-index range (--start/--stop)"),
    ):
        p = esub.add_parser(name, help=help_)
        p.add_argument("input")
        p.add_argument("output")
        p.add_argument("--to", dest="fmt_out", choices=(*WRITE_FORMATS, "aedat4-zstd"), help="output format")
        p.add_argument("--t0", type=float, help="keep events with t >= t0 (seconds, the file's time base)")
        p.add_argument("--t1", type=float, help="keep events with t < t1 (seconds)")
        if name == "convert":
            p.add_argument(
                "--roi", type=int, nargs=4, metavar=("X0", "Y0", "X1", "Y1"), help="keep x0<=x<x1, y0<=y<y1"
            )
        else:
            p.add_argument("--start", type=int, help="first event index to keep")
            p.add_argument("--stop", type=int, help="event index to stop before")
        p.add_argument(
            "--drop-outside", action="store_true", help="drop (and count) events outside the sensor"
        )
        p.add_argument("--allow-unsorted", action="store_true", help="do not require non-decreasing time")
        p.add_argument("--batch", **batch)
        _add_read_args(p)
        p.set_defaults(func=func)

    p = esub.add_parser("demo", help="synthetic stream → every format → read back, convert, verify")
    p.add_argument("--out", default="data/demo", help="output folder")
    p.add_argument("--events", type=int, default=1_000_000)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_demo)

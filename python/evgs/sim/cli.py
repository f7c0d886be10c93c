"""``evgs simulate``: simulate a preset (optionally modified) into a sequence folder."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from evgs.sim.presets import SimConfig

# Shortcut flags: (flag, config field).
_SHORTCUTS = (
    ("--seed", "seed"),
    ("--duration", "duration"),
    ("--target", "target"),
    ("--material", "material"),
    ("--trajectory", "trajectory"),
    ("--poses", "poses"),
    ("--light", "lighting"),
    ("--distance", "distance"),
    ("--speed", "speed"),
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate an event sequence of a spacecraft (presets mirror the paper's scenarios)",
        description="Render a target along a trajectory, generate events (ESIM) and write a sequence "
        "folder with ground-truth poses, images and range.",
    )
    p.add_argument("--preset", default="orbit_ambient", help="preset name (see --list)")
    p.add_argument("--out", type=Path, help="output folder (default: data/synthetic/<preset>)")
    for flag, field in _SHORTCUTS:
        p.add_argument(flag, dest=field, help=f"override the preset's {field}")
    p.add_argument("--resolution", metavar="WxH", help="sensor size; intrinsics keep the field of view")
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override any setting (repeatable)"
    )
    p.add_argument("--list", action="store_true", help="list the presets and settings, then exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def configure(args: argparse.Namespace) -> SimConfig:
    """The preset with every command-line override applied."""
    from evgs.sim.presets import preset

    cfg = preset(args.preset)
    if args.resolution:
        try:
            w, h = (int(v) for v in args.resolution.lower().split("x"))
        except ValueError:
            raise ValueError(f"--resolution {args.resolution!r}: expected WIDTHxHEIGHT") from None
        cfg = cfg.with_resolution(w, h)
    for _, field in _SHORTCUTS:
        if getattr(args, field) is not None:
            cfg = cfg.override(field, getattr(args, field))
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE")
        cfg = cfg.override(key.strip(), value.strip())
    return cfg


def run(args: argparse.Namespace) -> int:
    # Imported here: scipy, trimesh and moderngl load only when simulating.
    from evgs.sim.driver import simulate
    from evgs.sim.presets import PRESETS, SimConfig

    if args.list:
        for name, cfg in PRESETS.items():
            print(f"{name:18s} {cfg.target:9s} {cfg.trajectory:8s} {cfg.lighting:11s} "
                  f"{cfg.width}x{cfg.height} {cfg.duration:g} s")  # fmt: skip
        print("settings:", ", ".join(f.name for f in dataclasses.fields(SimConfig)))
        return 0
    cfg = configure(args)
    out = args.out or Path("data") / "synthetic" / args.preset
    seq = simulate(cfg, out, progress=not args.no_progress)
    s = seq.meta["simulator"]["stats"]
    print(
        f"{seq.root}: {s['events']:,} events, {len(seq.frames_us())} frames, {s['renders']} renders "
        f"({s['rejected_renders']} rejected), render {s['render_s']:.1f} s, events {s['events_s']:.1f} s"
    )
    return 0

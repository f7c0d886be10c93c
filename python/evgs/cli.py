"""The ``evgs`` command line. Each stage's module adds its own subcommands through ``register``."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from evgs import __version__

# torch's OpenMP threads spin between parallel regions by default. evgs's optimizer issues many small ops,
# so two runs (or a run and a build) sharing the cores spin against each other's work: two runs side by side
# took 32 min each spinning, 14 min sleeping. A run alone is as fast either way (docs/ablations.md §51).
# Set before any subcommand module imports torch; a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# Modules that contribute subcommands; each has ``register(subparsers) -> None`` and sets
# ``func`` on its parsers (a callable taking the parsed namespace, returning an exit code).
COMMAND_MODULES = [
    "evgs.events.cli",
    "evgs.eval.cli",
    "evgs.sim.cli",
    "evgs.data.cli",
    "evgs.slam.cli",
    "evgs.bench.cli",
]


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evgs",
        description="Event-only SLAM with 3D Gaussian Splatting for spacecraft proximity operations.",
    )
    parser.add_argument("--version", action="version", version=f"evgs {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UserError, ValueError, OSError) as e:
        print(f"evgs: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("evgs: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    # As `python -m evgs.cli` this file runs as `__main__`, a second copy of the module whose UserError
    # is not the one the subcommands raise (they import evgs.cli): hand over to the imported module.
    from evgs.cli import main as imported_main

    sys.exit(imported_main())

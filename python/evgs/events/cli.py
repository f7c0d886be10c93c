"""``evgs events ...``: the event-file preprocessing commands."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("events", help="inspect, convert and slice event files")
    parser.set_defaults(func=lambda args: parser.print_help())

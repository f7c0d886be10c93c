"""The canonical on-disk event format: Parquet with ``t:int64, x:uint16, y:uint16, p:int8``, sorted by t.

Sensor size travels in the file's key-value metadata (key ``evgs``, JSON ``{"width", "height"}``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl

from evgs.events.arrays import EventArray
from evgs.io_util import atomic_path

SCHEMA = {"t": pl.Int64, "x": pl.UInt16, "y": pl.UInt16, "p": pl.Int8}


def read_parquet(path: str | Path) -> EventArray:
    """Read a canonical event Parquet file (columns zero-copy where polars allows)."""
    path = Path(path)
    df = pl.read_parquet(path, columns=list(SCHEMA))
    for name, dtype in SCHEMA.items():
        if df.schema[name] != dtype:
            raise ValueError(f"{path}: column {name!r} has type {df.schema[name]}, expected {dtype}")
    meta = pl.read_parquet_metadata(path)
    size = json.loads(meta.get("evgs", "{}"))
    return EventArray(
        t=df["t"].to_numpy(),
        x=df["x"].to_numpy(),
        y=df["y"].to_numpy(),
        p=df["p"].to_numpy(),
        width=int(size.get("width", 0)),
        height=int(size.get("height", 0)),
    )


def write_parquet(path: str | Path, ev: EventArray) -> None:
    """Write events atomically (temp file + rename) in the canonical schema."""
    df = pl.DataFrame(
        {
            "t": np.asarray(ev.t, np.int64),
            "x": np.asarray(ev.x, np.uint16),
            "y": np.asarray(ev.y, np.uint16),
            "p": np.asarray(ev.p, np.int8),
        },
        schema=SCHEMA,
    )
    with atomic_path(path) as tmp:
        df.write_parquet(
            tmp,
            compression="zstd",
            metadata={"evgs": json.dumps({"width": ev.width, "height": ev.height})},
        )

"""Small numeric text tables of the data sets (poses, calibration, timestamps), read with errors that
name the file and line. Event files are not read here: they go through ``evgs.events.io``."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

_SPLIT = re.compile(r"[,;\s]+")


def _fields(line: str) -> list[str]:
    return [f for f in _SPLIT.split(line.strip()) if f]


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def read_rows(path: Path, ncols: int | tuple[int, ...], expected: str) -> tuple[np.ndarray, np.ndarray]:
    """Read a table of numbers separated by commas, semicolons or whitespace.

    Blank lines and ``#`` comments are skipped; a first line that is not all numbers is a header (so
    files with and without one both work). ``expected`` describes a row for error messages, e.g.
    ``"t rx ry rz x y z"``. Returns ``(values (N, ncols), line_numbers (N,))``.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found (expected {expected})")
    allowed = (ncols,) if isinstance(ncols, int) else ncols
    rows: list[list[float]] = []
    lines: list[int] = []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        fields = _fields(line)
        if not fields or fields[0].startswith("#"):
            continue
        if not rows and not all(_is_number(f) for f in fields):
            if lines:  # a second non-numeric line is not a header
                raise ValueError(
                    f"{path}: line {lineno}: expected numbers ({expected}), got {line.strip()!r}"
                )
            lines.append(lineno)
            continue
        if len(fields) not in allowed or (rows and len(fields) != len(rows[0])):
            want = len(rows[0]) if rows else " or ".join(map(str, allowed))
            raise ValueError(f"{path}: line {lineno}: expected {want} values ({expected}), got {len(fields)}")
        try:
            vals = [float(f) for f in fields]
        except ValueError:
            raise ValueError(
                f"{path}: line {lineno}: expected numbers ({expected}), got {line.strip()!r}"
            ) from None
        if not all(np.isfinite(vals)):
            raise ValueError(f"{path}: line {lineno}: non-finite value")
        rows.append(vals)
        lines.append(lineno)
    if not rows:
        raise ValueError(f"{path}: no data rows (expected {expected})")
    line_numbers = np.asarray(lines[-len(rows) :])
    return np.asarray(rows, np.float64), line_numbers


def read_numbers(path: Path, count: int, expected: str) -> np.ndarray:
    """All numbers of a small file (any line breaks), which must be exactly ``count`` of them."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found (expected {expected})")
    vals: list[float] = []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        fields = _fields(line)
        if not fields or fields[0].startswith("#"):
            continue
        try:
            vals.extend(float(f) for f in fields)
        except ValueError:
            raise ValueError(
                f"{path}: line {lineno}: expected numbers ({expected}), got {line.strip()!r}"
            ) from None
    if len(vals) != count:
        raise ValueError(f"{path}: expected {count} numbers ({expected}), found {len(vals)}")
    if not all(np.isfinite(vals)):
        raise ValueError(f"{path}: non-finite value")
    return np.asarray(vals, np.float64)


def seconds_to_us(t: np.ndarray) -> np.ndarray:
    """Seconds (float) → integer µs, rounded to nearest."""
    return np.round(np.asarray(t, np.float64) * 1e6).astype(np.int64)

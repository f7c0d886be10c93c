"""TUM trajectory files: one pose per line, ``t[s] tx ty tz qx qy qz qw`` (camera-to-world)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evgs.geometry import make_pose, quat_to_rotmat, rotmat_to_quat
from evgs.io_util import atomic_path


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(t_seconds (N,), T_wc (N, 4, 4))``. Comment lines (``#``) and blank lines are skipped."""
    path = Path(path)
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise ValueError(
                f"{path}: line {lineno}: expected 8 values (t tx ty tz qx qy qz qw), got {len(parts)}"
            )
        try:
            vals = [float(v) for v in parts]
        except ValueError as e:
            raise ValueError(f"{path}: line {lineno}: {e}") from None
        if not np.all(np.isfinite(vals)):
            raise ValueError(f"{path}: line {lineno}: non-finite value")
        rows.append(vals)
    if not rows:
        raise ValueError(f"{path}: no poses")
    a = np.asarray(rows)
    return a[:, 0], make_pose(quat_to_rotmat(a[:, 4:8]), a[:, 1:4])


def write_tum(path: str | Path, t_seconds: np.ndarray, T_wc: np.ndarray) -> None:
    """Write poses atomically in TUM format (9 decimals: sub-µs time, sub-nm translation)."""
    q = rotmat_to_quat(T_wc[:, :3, :3])
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw  (camera-to-world)\n")
        for ti, T, qi in zip(t_seconds, T_wc, q, strict=True):
            vals = [ti, *T[:3, 3], *qi]
            f.write(" ".join(f"{v:.9f}" for v in vals) + "\n")

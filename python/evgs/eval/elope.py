"""ELOPE challenge metric (paper §5.4): velocities by first differences and the altitude-normalised
velocity error, plus the challenge's JSON submission format.

Conventions: positions in metres, times in seconds; ``z`` of the ground truth is the altitude (negative
by ELOPE convention, hence ``|z|``); the velocity of interval ``[t_i, t_i+1]`` is attributed to ``t_i``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from evgs.io_util import atomic_path


def velocities(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Eq. 18: ``v_i = (p_i+1 − p_i) / (t_i+1 − t_i)`` → (N−1, 3)."""
    t = np.asarray(t, np.float64)
    dt = np.diff(t)
    if np.any(dt <= 0):
        i = int(np.argmax(dt <= 0))
        raise ValueError(f"velocities: timestamps must be strictly increasing (sample {i + 1})")
    return np.diff(np.asarray(p, np.float64), axis=0) / dt[:, None]


def elope_errors(t: np.ndarray, p_est: np.ndarray, p_gt: np.ndarray) -> np.ndarray:
    """Per-interval ``‖v_est,i − v_gt,i‖ / |z_gt,i|`` (the terms of eq. 19)."""
    z = np.abs(np.asarray(p_gt, np.float64)[:-1, 2])
    if np.any(z == 0):
        raise ValueError("elope score: ground-truth altitude z is 0 at some sample")
    return np.linalg.norm(velocities(t, p_est) - velocities(t, p_gt), axis=1) / z


def elope_score(t: np.ndarray, p_est: np.ndarray, p_gt: np.ndarray) -> float:
    """Eq. 19: mean over the N−1 intervals of the altitude-normalised velocity error."""
    return float(np.mean(elope_errors(t, p_est, p_gt)))


def submission_velocities(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """One velocity per timestamp as the challenge requires: eq. 18 forward differences, the last
    timestamp repeating the last interval's velocity → (N, 3)."""
    v = velocities(t, p)
    return np.concatenate([v, v[-1:]], axis=0)


def write_submission(path: str | Path, entries: Mapping[str, np.ndarray]) -> None:
    """Write ``{"<seq>": {"vx": [...], "vy": [...], "vz": [...]}}`` atomically; ``entries`` maps the
    sequence identifier (e.g. ``"28"``) to its (N, 3) velocities, one row per given timestamp."""
    doc = {}
    for seq, v in entries.items():
        v = np.asarray(v, np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"submission {seq}: velocities must be (N, 3), got {v.shape}")
        if not np.all(np.isfinite(v)):
            row = int(np.argmin(np.isfinite(v).all(axis=1)))
            raise ValueError(f"submission {seq}: non-finite velocity at row {row}")
        doc[str(seq)] = {k: [float(x) for x in v[:, a]] for a, k in enumerate(("vx", "vy", "vz"))}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1, allow_nan=False))


def sequence_id(name: str) -> str:
    """Challenge identifier of a sequence name: ``"0028"`` or ``"elope_0028"`` → ``"28"``."""
    digits = "".join(ch for ch in name.rsplit("_", 1)[-1] if ch.isdigit())
    if not digits:
        raise ValueError(f"cannot derive an ELOPE sequence number from {name!r}")
    return str(int(digits))

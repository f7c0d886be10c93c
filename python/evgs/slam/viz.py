"""Diagnostic grids like the paper's Fig. 3 / Fig. 4: one row per sampled window with the render at the
window's start, the render at its end, the measured event frame in colour (red = positive, blue =
negative polarity) and in gray, the predicted event frame likewise, and the squared error map.

Event frames and errors of one grid share one scale (the 99th percentile of the measured |E|), so rows
and columns are comparable.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from evgs.io_util import atomic_path
from evgs.slam.loss import predicted_events

COLUMNS = ("render start", "render end", "events", "events (gray)", "predicted", "predicted (gray)",
           "squared error")  # fmt: skip
_LABEL_H = 18


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)


def gray_bgr(img: np.ndarray) -> np.ndarray:
    """(H, W) intensity in [0, 1] → BGR uint8."""
    g = _u8(img)
    return np.stack([g, g, g], -1)


def events_color(e: np.ndarray, scale: float) -> np.ndarray:
    """Positive values red, negative blue, on black (BGR uint8)."""
    v = np.clip(e / scale, -1.0, 1.0)
    out = np.zeros((*e.shape, 3), np.uint8)
    out[..., 2] = _u8(np.maximum(v, 0))
    out[..., 0] = _u8(np.maximum(-v, 0))
    return out


def events_gray(e: np.ndarray, scale: float) -> np.ndarray:
    """Mid-gray for no change, brighter for positive, darker for negative (BGR uint8)."""
    return gray_bgr(0.5 + 0.5 * np.clip(e / scale, -1.0, 1.0))


def error_map(sq: np.ndarray, scale: float) -> np.ndarray:
    return cv2.applyColorMap(_u8(np.clip(sq / scale, 0.0, 1.0)), cv2.COLORMAP_INFERNO)


def grid(start: np.ndarray, end: np.ndarray, events: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """(B, H, W) renders and event frames → one BGR image, a row per window, labelled columns."""
    scale = max(float(np.percentile(np.abs(events), 99)), 1e-6)
    rows = []
    for s, e, m, p in zip(start, end, events, predicted, strict=True):
        err = error_map((m - p) ** 2, scale * scale)
        tiles = [gray_bgr(s), gray_bgr(e), events_color(m, scale), events_gray(m, scale),
                 events_color(p, scale), events_gray(p, scale), err]  # fmt: skip
        rows.append(np.concatenate(tiles, axis=1))
    body = np.concatenate(rows, axis=0)
    width = start.shape[2]
    header = np.zeros((_LABEL_H, body.shape[1], 3), np.uint8)
    for i, name in enumerate(COLUMNS):
        cv2.putText(header, name, (i * width + 3, _LABEL_H - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
    return np.concatenate([header, body], axis=0)


def write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


@torch.no_grad()
def diagnostics_image(start: torch.Tensor, end: torch.Tensor, events: torch.Tensor, cfg) -> np.ndarray:
    """The grid of a batch: gray renders (B, H, W), measured frames (B, H, W), loss config for Ê."""
    pred = predicted_events(start, end, cfg)
    return grid(start.numpy(), end.numpy(), events.numpy(), pred.numpy())

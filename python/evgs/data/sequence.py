"""The canonical sequence layout: one folder that every importer and the simulator write and the
pipeline and the evaluator read.

```
sequence.toml    name, source, [camera] width height fx fy cx cy distortion, anything else
events.parquet   t:int64 µs, x:uint16, y:uint16, p:int8 (±1), sorted by t
frames.csv       frame,t_us — chunk boundaries (and GT image times)
poses_gt.txt     optional, TUM, camera-to-world, world = target frame
images/          optional, 16-bit linear PNG per frame: images/000123.png ↔ frame 123
range.csv        optional, t_us,range_m (range finder along the optical axis)
```
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import polars as pl
import tomli_w
import tomllib

from evgs.data.tum import read_tum, write_tum
from evgs.events.arrays import EventArray
from evgs.events.parquet import read_parquet, write_parquet


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics with optional OpenCV distortion ``(k1, k2, p1, p2, k3)``."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in ("width", "height", "fx", "fy", "cx", "cy")}
        d["distortion"] = list(self.distortion)
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera") -> Camera:
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in d]
        if missing:
            raise ValueError(f"{source}: [camera] is missing {', '.join(missing)}")
        return cls(
            int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
            float(d["cx"]), float(d["cy"]), tuple(float(v) for v in d.get("distortion", ())),
        )  # fmt: skip


@dataclass
class Sequence:
    """A sequence folder on disk. Large data (events, images) is read on demand."""

    root: Path
    name: str
    camera: Camera
    meta: dict = field(default_factory=dict)

    @classmethod
    def load(cls, root: str | Path) -> Sequence:
        root = Path(root)
        toml_path = root / "sequence.toml"
        if not toml_path.is_file():
            raise FileNotFoundError(f"{root}: not a sequence folder (no sequence.toml)")
        with open(toml_path, "rb") as f:
            try:
                meta = tomllib.load(f)
            except tomllib.TOMLDecodeError as e:
                raise ValueError(f"{toml_path}: {e}") from None
        for required in ("events.parquet", "frames.csv"):
            if not (root / required).is_file():
                raise FileNotFoundError(f"{root}: sequence has no {required}")
        camera = Camera.from_dict(meta.pop("camera", {}), str(toml_path))
        return cls(root, str(meta.pop("name", root.name)), camera, meta)

    def events(self) -> EventArray:
        ev = read_parquet(self.root / "events.parquet")
        return EventArray(ev.t, ev.x, ev.y, ev.p, self.camera.width, self.camera.height)

    def frames_us(self) -> np.ndarray:
        """Frame (chunk-boundary) timestamps in µs, strictly increasing."""
        path = self.root / "frames.csv"
        t = pl.read_csv(path)["t_us"].to_numpy().astype(np.int64)
        if np.any(np.diff(t) <= 0):
            i = int(np.argmax(np.diff(t) <= 0))
            raise ValueError(f"{path}: frame {i + 1}: timestamps must be strictly increasing")
        return t

    def poses_gt(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(t_us, T_wc)`` of the ground truth, or None when the sequence has none."""
        path = self.root / "poses_gt.txt"
        if not path.is_file():
            return None
        t, T = read_tum(path)
        return np.round(t * 1e6).astype(np.int64), T

    def image(self, frame: int) -> np.ndarray | None:
        """GT intensity image of ``frame`` as float32 (H, W) in [0, 1], or None."""
        path = self.root / "images" / f"{frame:06d}.png"
        if not path.is_file():
            return None
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{path}: unreadable image")
        return img.astype(np.float32) / 65535.0

    def range_samples(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(t_us, range_m)`` of the range finder, or None."""
        path = self.root / "range.csv"
        if not path.is_file():
            return None
        df = pl.read_csv(path)
        return df["t_us"].to_numpy().astype(np.int64), df["range_m"].to_numpy().astype(np.float64)


def write_sequence(
    root: str | Path,
    name: str,
    camera: Camera,
    events: EventArray,
    frames_us: np.ndarray,
    *,
    poses_gt: tuple[np.ndarray, np.ndarray] | None = None,
    images: Iterable[np.ndarray] | None = None,
    range_samples: tuple[np.ndarray, np.ndarray] | None = None,
    meta: dict | None = None,
    tables: Mapping[str, pl.DataFrame] | None = None,
) -> Sequence:
    """Write a complete sequence folder, all or nothing: everything goes to a hidden sibling folder that
    replaces ``root`` only once complete, so an interrupted or failed write leaves any previous sequence
    untouched and never a half one.

    ``poses_gt`` is ``(t_us, T_wc)``; ``images`` yields (H, W) floats in [0, 1] aligned with ``frames_us``
    (an array or a generator, so importers can stream them); ``tables`` are extra CSV files by name
    (e.g. ``velocities_gt.csv``).
    """
    root = Path(root)
    tmp = root.with_name(f".{root.name}.partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        doc = {"name": name, **(meta or {}), "camera": camera.to_dict()}
        (tmp / "sequence.toml").write_text(tomli_w.dumps(doc))
        write_parquet(tmp / "events.parquet", events)
        frames_us = np.asarray(frames_us, np.int64)
        pl.DataFrame({"frame": np.arange(len(frames_us)), "t_us": frames_us}).write_csv(tmp / "frames.csv")
        if poses_gt is not None:
            write_tum(tmp / "poses_gt.txt", poses_gt[0] / 1e6, poses_gt[1])
        if images is not None:
            (tmp / "images").mkdir()
            for i, img in enumerate(images):
                png = np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)
                cv2.imwrite(str(tmp / "images" / f"{i:06d}.png"), png)
        if range_samples is not None:
            pl.DataFrame({"t_us": range_samples[0], "range_m": range_samples[1]}).write_csv(tmp / "range.csv")
        for file_name, df in (tables or {}).items():
            df.write_csv(tmp / file_name)
        old = root.with_name(f".{root.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        if root.exists():
            root.rename(old)
        tmp.rename(root)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return Sequence.load(root)

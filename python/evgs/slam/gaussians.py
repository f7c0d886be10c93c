"""The scene: 3D Gaussians as torch Parameters, their random initialisation and 3DGS PLY files.

Stored (un-activated) parameters, the rasterizer's convention (``evgs.render``):
``means`` (N, 3) world, ``log_scales`` (N, 3), ``quats`` (N, 4) ``(w, x, y, z)``, ``opacity_logits`` (N,)
(``o = sigmoid``), ``colors`` (N, 1) linear gray, kept in ``[0, max_color]`` by a guard rather than by
a sigmoid, so dim colours (the usual state on a black background) still get full-size gradients.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from evgs.config import GaussiansConfig
from evgs.data.sequence import Camera
from evgs.io_util import atomic_path

SH_C0 = 0.28209479177387814  # degree-0 spherical harmonic: colour = 0.5 + SH_C0 · f_dc
PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "colors")
_PLY_PROPS = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)  # fmt: skip
_PLY_OPTIONAL = ("nx", "ny", "nz", "f_dc_1", "f_dc_2")  # normals unused; one f_dc channel is enough
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


class Gaussians:
    """A set of Gaussians; ``params`` holds one Parameter per name in :data:`PARAM_NAMES`."""

    def __init__(
        self, means: Tensor, log_scales: Tensor, quats: Tensor, opacity_logits: Tensor, colors: Tensor
    ):
        n = len(means)
        shapes = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
            "colors": (n, 1),
        }
        tensors = dict(zip(PARAM_NAMES, (means, log_scales, quats, opacity_logits, colors), strict=True))
        for name, t in tensors.items():
            if tuple(t.shape) != shapes[name]:
                raise ValueError(f"gaussians: {name} has shape {tuple(t.shape)}, expected {shapes[name]}")
        self.params = torch.nn.ParameterDict(
            {k: torch.nn.Parameter(t.detach().to(torch.float32).clone()) for k, t in tensors.items()}
        )

    def __len__(self) -> int:
        return len(self.params["means"])

    def __getitem__(self, name: str) -> torch.nn.Parameter:
        return self.params[name]

    def opacities(self) -> Tensor:
        return torch.sigmoid(self.params["opacity_logits"])

    def scales(self) -> Tensor:
        return torch.exp(self.params["log_scales"])

    def render_inputs(self) -> dict[str, Tensor]:
        """Keyword arguments for ``evgs.render.render`` (activated opacity, everything else raw)."""
        p = self.params
        return {
            "means": p["means"],
            "log_scales": p["log_scales"],
            "quats": p["quats"],
            "opacities": self.opacities(),
            "colors": p["colors"],
        }

    @classmethod
    def random(
        cls, num: int, bounding_size: float, opacity: float, color: float, generator: torch.Generator
    ) -> Gaussians:
        """``num`` Gaussians uniform in ``[-s, s]³``, isotropic scale = RMS distance to the 3 nearest
        neighbours, identity rotation, the given opacity and gray colour."""
        if num < 4:
            raise ValueError(f"gaussians: need at least 4 for the 3-nearest-neighbour scale, got {num}")
        means = (torch.rand(num, 3, generator=generator, dtype=torch.float64) * 2 - 1) * bounding_size
        return cls.at(means, opacity, color)

    @classmethod
    def on_rays(
        cls,
        num: int,
        weights: Tensor,
        camera: Camera,
        depth_range: tuple[float, float],
        opacity: float,
        color: float,
        generator: torch.Generator,
        tilt_deg: float = 0.0,
    ) -> Gaussians:
        """``num`` Gaussians on the rays of the first camera (at the identity) through pixels drawn with
        probability ∝ ``weights`` (H, W), at a uniform point in the pixel and a depth uniform in
        ``depth_range``; scaled and oriented as :meth:`random`. ``tilt_deg`` ≠ 0 turns the slab about the
        camera's x axis (> 0: nearer at the image's bottom): a depth ``d`` on the optical axis becomes the
        plane through ``(0, 0, d)`` turned by that angle, so the mid-depth points lie on one tilted plane.

        Against a black background every event comes from the target, so its pixels say where in the
        image the target is; only depth is unknown. Seeding there puts the whole budget on the target
        instead of the ~1–5 % of a box around the camera that it fills.
        """
        if num < 4:
            raise ValueError(f"gaussians: need at least 4 for the 3-nearest-neighbour scale, got {num}")
        lo, hi = depth_range
        if not 0 < lo < hi:
            raise ValueError(f"gaussians: the seeding depth range ({lo:g}, {hi:g}) must be positive")
        flat = weights.reshape(-1).double()
        if not bool((flat > 0).any()):
            raise ValueError("gaussians: no pixel with events to seed the initial Gaussians from")
        pix = torch.multinomial(flat, num, replacement=True, generator=generator)
        jitter = torch.rand(num, 2, generator=generator, dtype=torch.float64)
        u = (pix % camera.width).double() + jitter[:, 0] - 0.5  # anywhere in the pixel (OpenCV centres)
        v = (pix // camera.width).double() + jitter[:, 1] - 0.5
        depth = lo + (hi - lo) * torch.rand(num, generator=generator, dtype=torch.float64)
        rays = camera_rays(u, v, camera)
        if tilt_deg:
            depth = depth * tilted_plane_depth(rays, tilt_deg, camera)
        means = rays * depth[:, None]
        g = cls.at(means, opacity, color)
        with torch.no_grad():  # isolated seeds (noise events) would get huge, slow, view-filling scales
            cap = torch.quantile(g["log_scales"][:, 0], 0.9)
            g["log_scales"].clamp_(max=float(cap))
        return g

    @classmethod
    def at(cls, means: Tensor, opacity: float, color: float) -> Gaussians:
        """Isotropic Gaussians at ``means`` (N, 3) with the 3-nearest-neighbour RMS distance as scale."""
        num = len(means)
        log_scale = torch.from_numpy(knn_log_scale(means.double().numpy()))
        quats = torch.zeros(num, 4)
        quats[:, 0] = 1
        return cls(
            means.float(),
            log_scale[:, None].expand(num, 3).float(),
            quats,
            torch.full((num,), opacity_logit(opacity)),
            torch.full((num, 1), float(color)),
        )

    def state(self) -> dict[str, Tensor]:
        return {k: v.detach().clone() for k, v in self.params.items()}

    @classmethod
    def from_state(cls, state: dict[str, Tensor]) -> Gaussians:
        return cls(*(state[k] for k in PARAM_NAMES))


def make_optimizer(
    gaussians: Gaussians, cfg: GaussiansConfig, scene_scale: float | None = None
) -> torch.optim.Adam:
    """Adam with one named group per parameter (the names the strategy uses to edit its state).

    The means' rate scales with the scene (gsplat convention); ``scene_scale`` defaults to
    ``bounding_size``.
    """
    scale = cfg.bounding_size if scene_scale is None else scene_scale
    lrs = {
        "means": cfg.means_lr * scale,
        "log_scales": cfg.scales_lr,
        "quats": cfg.quats_lr,
        "opacity_logits": cfg.opacities_lr,
        "colors": cfg.colors_lr,
    }
    groups = [{"params": [gaussians.params[k]], "lr": lrs[k], "name": k} for k in PARAM_NAMES]
    return torch.optim.Adam(groups, eps=cfg.adam_eps)


def quat_to_rotmat(q: Tensor) -> Tensor:
    """(..., 4) quaternions ``(w, x, y, z)``, normalised here → (..., 3, 3) rotation matrices."""
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    r = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    )  # fmt: skip
    return r.reshape(*q.shape[:-1], 3, 3)


def camera_rays(u: Tensor, v: Tensor, camera: Camera) -> Tensor:
    """(N, 3) camera-frame rays through image points ``(u, v)`` (pixels), scaled to unit depth (z = 1)."""
    return torch.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, torch.ones_like(u)], -1)


def tilted_plane_depth(rays: Tensor, tilt_deg: float, camera: Camera) -> Tensor:
    """(N,) depth along unit-depth ``rays`` of the plane through ``(0, 0, 1)`` turned ``tilt_deg`` about
    the camera's x axis: ``n·X = cos t`` with ``n = (0, sin t, cos t)``."""
    t = math.radians(tilt_deg)
    # The farthest row's |y| at unit depth; the margin keeps every row's depth within 20× the axis's.
    edge = max(camera.cy + 0.5, camera.height - 0.5 - camera.cy) / camera.fy
    if math.cos(t) - abs(math.sin(t)) * edge <= 0.05:
        raise ValueError(
            f"gaussians.init_tilt_deg = {tilt_deg:g}: the tilted plane would lie behind or along some of the "
            f"camera's rows (|tilt| must stay under 90° minus the half field of view, here "
            f"{90 - math.degrees(math.atan(edge)):.0f}°)"
        )
    return math.cos(t) / (math.cos(t) + math.sin(t) * rays[:, 1])


def knn_log_scale(points: np.ndarray) -> np.ndarray:
    """log of the RMS distance of each point to its 3 nearest neighbours (floored at 1e-7)."""
    dist, _ = cKDTree(points).query(points, k=4)
    rms = np.sqrt(np.mean(dist[:, 1:] ** 2, axis=1))
    return np.log(np.maximum(rms, 1e-7))


def opacity_logit(p: float) -> float:
    if not 0.0 < p < 1.0:
        raise ValueError(f"gaussians: opacity must be in (0, 1), got {p}")
    return float(np.log(p / (1 - p)))


def save_ply(path: str | Path, gaussians: Gaussians) -> None:
    """Write the standard 3DGS binary PLY (SH degree 0; gray copied to the three ``f_dc``), atomically."""
    with torch.no_grad():
        p = {k: v.detach().cpu().numpy() for k, v in gaussians.params.items()}
    n = len(gaussians)
    rec = np.zeros(n, dtype=[(name, "<f4") for name in _PLY_PROPS])
    for i, axis in enumerate("xyz"):
        rec[axis] = p["means"][:, i]
        rec[f"scale_{i}"] = p["log_scales"][:, i]
    f_dc = (p["colors"][:, 0] - 0.5) / SH_C0
    for i in range(3):
        rec[f"f_dc_{i}"] = f_dc
    rec["opacity"] = p["opacity_logits"]
    for i in range(4):
        rec[f"rot_{i}"] = p["quats"][:, i]
    header = "ply\nformat binary_little_endian 1.0\n"
    header += f"element vertex {n}\n" + "".join(f"property float {name}\n" for name in _PLY_PROPS)
    header += "end_header\n"
    with atomic_path(path) as tmp:
        tmp.write_bytes(header.encode("ascii") + rec.tobytes())


def load_ply(path: str | Path) -> Gaussians:
    """Read a 3DGS binary PLY (any property order and scalar types; extra properties such as
    ``f_rest_*`` or normals are ignored; a coloured splat becomes gray as the mean of its channels)."""
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: byte 0: not a PLY file (no 'ply' magic or no 'end_header')")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    count, fields, in_vertex, seen_format = -1, [], False, False
    for lineno, line in enumerate(lines, start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format":
            if words[1:] != ["binary_little_endian", "1.0"]:
                raise ValueError(f"{path}: line {lineno}: unsupported format {' '.join(words[1:])!r}")
            seen_format = True
        elif words[0] == "element":
            in_vertex = words[1] == "vertex"
            if in_vertex:
                count = int(words[2])
            elif count < 0:
                raise ValueError(
                    f"{path}: line {lineno}: element {words[1]!r} before 'vertex' is unsupported"
                )
        elif words[0] == "property" and in_vertex:
            if words[1] == "list" or words[1] not in _PLY_TYPES or len(words) != 3:
                raise ValueError(f"{path}: line {lineno}: unsupported vertex property {line!r}")
            fields.append((words[2], "<" + _PLY_TYPES[words[1]]))
    if not seen_format or count < 0:
        raise ValueError(f"{path}: header has no 'format' line or no 'element vertex'")
    names = [f[0] for f in fields]
    missing = [k for k in _PLY_PROPS if k not in names and k not in _PLY_OPTIONAL]
    if missing:
        raise ValueError(f"{path}: vertex element lacks {', '.join(missing)}")
    dtype = np.dtype(fields)
    start = end + len(b"end_header\n")
    if len(data) - start < count * dtype.itemsize:
        raise ValueError(
            f"{path}: byte {len(data)}: truncated: {count} vertices of {dtype.itemsize} bytes need "
            f"{count * dtype.itemsize} bytes after the header at byte {start}"
        )
    rec = np.frombuffer(data, dtype=dtype, count=count, offset=start)

    def cols(*keys: str) -> Tensor:
        return torch.from_numpy(np.stack([rec[k].astype(np.float32) for k in keys], axis=1))

    dc = [k for k in ("f_dc_0", "f_dc_1", "f_dc_2") if k in names]
    gray = 0.5 + SH_C0 * cols(*dc).mean(dim=1, keepdim=True)
    return Gaussians(
        cols("x", "y", "z"),
        cols("scale_0", "scale_1", "scale_2"),
        cols("rot_0", "rot_1", "rot_2", "rot_3"),
        cols("opacity")[:, 0],
        gray,
    )

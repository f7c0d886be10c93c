"""Simulated targets as triangle soups with per-corner normals and material ids.

World = target frame, metres, +z up. Built-in procedural targets: a Hubble-like telescope, a generic
satellite bus and a lunar-like terrain patch (for descents); any mesh trimesh can read (OBJ/GLB/PLY/STL,
…) can be used instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.ndimage import gaussian_filter
from trimesh.transformations import rotation_matrix, translation_matrix

from evgs.sim.materials import MATERIAL_IDS

# Creases sharper than this keep hard normals; smoother surfaces (cylinders) are smooth-shaded.
CREASE_ANGLE = np.radians(35.0)


@dataclass(frozen=True)
class Scene:
    """Triangles as ``(T, 3, 3)`` corner positions with matching corner normals and one material id per
    triangle."""

    triangles: np.ndarray
    normals: np.ndarray
    material: np.ndarray

    @property
    def vertices(self) -> np.ndarray:
        """Unique corner positions (N, 3)."""
        return np.unique(self.triangles.reshape(-1, 3), axis=0)

    @property
    def bounds(self) -> tuple[np.ndarray, float]:
        """Centre and radius of a sphere containing the scene."""
        v = self.triangles.reshape(-1, 3)
        centre = 0.5 * (v.min(0) + v.max(0))
        return centre, float(np.linalg.norm(v - centre, axis=1).max())

    def ray_distance(self, origin: np.ndarray, direction: np.ndarray) -> float:
        """Distance along the unit ``direction`` to the first triangle hit (Möller–Trumbore), or inf."""
        a, b, c = (self.triangles[:, i] for i in range(3))
        e1, e2 = b - a, c - a
        pv = np.cross(direction, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = origin - a
        u = np.einsum("ij,ij->i", tv, pv) * inv
        qv = np.cross(tv, e1)
        v = (qv @ direction) * inv
        t = np.einsum("ij,ij->i", e2, qv) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        return float(t[hit].min()) if hit.any() else float("inf")


def _part(mesh: trimesh.Trimesh, material: str) -> tuple[trimesh.Trimesh, int]:
    return mesh, MATERIAL_IDS[material]


def build_scene(parts: list[tuple[trimesh.Trimesh, int]]) -> Scene:
    """Concatenate parts; normals are smoothed across edges flatter than ``CREASE_ANGLE``."""
    tris, norms, mats = [], [], []
    for mesh, mat in parts:
        smooth = trimesh.graph.smooth_shade(mesh, angle=CREASE_ANGLE)
        tris.append(smooth.vertices[smooth.faces])
        norms.append(smooth.vertex_normals[smooth.faces])
        mats.append(np.full(len(smooth.faces), mat, np.int32))
    return Scene(np.concatenate(tris), np.concatenate(norms), np.concatenate(mats))


def _cylinder_x(radius: float, length: float, x0: float, sections: int = 48) -> trimesh.Trimesh:
    """Cylinder along +x from ``x0`` to ``x0 + length``."""
    m = trimesh.creation.cylinder(radius=radius, height=length, sections=sections)
    m.apply_transform(rotation_matrix(np.pi / 2, [0, 1, 0]))
    m.apply_translation([x0 + length / 2, 0, 0])
    return m


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=translation_matrix(centre))


def _rod(a: tuple[float, float, float], b: tuple[float, float, float], radius: float) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=radius, segment=np.array([a, b], float), sections=12)


def _dish(radius: float, depth: float, centre: np.ndarray, axis: np.ndarray) -> trimesh.Trimesh:
    """Shallow cone opening towards ``axis``."""
    m = trimesh.creation.cone(radius=radius, height=depth, sections=32)
    m.apply_transform(rotation_matrix(np.pi, [1, 0, 0]))  # apex down, rim up (+z)
    m.apply_translation([0, 0, depth])
    z = np.array([0.0, 0.0, 1.0])
    axis = axis / np.linalg.norm(axis)
    rot_axis = np.cross(z, axis)
    if np.linalg.norm(rot_axis) > 1e-9:
        m.apply_transform(rotation_matrix(np.arccos(np.clip(z @ axis, -1, 1)), rot_axis))
    elif z @ axis < 0:
        m.apply_transform(rotation_matrix(np.pi, [1, 0, 0]))
    m.apply_translation(centre)
    return m


def hubble() -> Scene:
    """Hubble-like telescope, about 3.8 m long: foil-wrapped tube, aft shroud, open aperture door, two
    solar arrays on masts, two high-gain antennas."""
    r = 0.6
    parts = [
        _part(_cylinder_x(r, 2.6, -1.3), "foil"),
        _part(_cylinder_x(r * 1.08, 0.7, -2.0), "metal"),
        _part(_cylinder_x(r * 0.5, 0.05, -2.05), "dark"),
    ]
    # Aperture door hinged at the top of the front rim, opened by ~70°.
    door = trimesh.creation.cylinder(radius=r, height=0.03, sections=48)
    door.apply_transform(rotation_matrix(np.pi / 2, [0, 1, 0]))
    door.apply_translation([0, 0, -r])
    door.apply_transform(rotation_matrix(np.radians(-70), [0, 1, 0]))
    door.apply_translation([1.32, 0, r])
    parts.append(_part(door, "paint"))
    for s in (-1.0, 1.0):
        parts.append(_part(_rod((-0.9, s * r, 0.0), (-0.9, s * 0.95, 0.0), 0.03), "metal"))
        parts.append(_part(_box((0.75, 2.2, 0.02), (-0.9, s * 2.05, 0.0)), "solar"))
        base = np.array([0.2, 0.0, s * r])
        tip = base + np.array([0.0, 0.0, s * 0.55])
        parts.append(_part(_rod(tuple(base), tuple(tip), 0.025), "metal"))
        parts.append(_part(_dish(0.28, 0.1, tip, np.array([0.3, 0.0, s * 1.0])), "dark"))
    return build_scene(parts)


def satellite() -> Scene:
    """Generic satellite bus: foil box, two solar panels on yokes, a magnetometer boom, a dish."""
    parts = [
        _part(_box((1.2, 1.0, 1.0), (0.0, 0.0, 0.0)), "foil"),
        _part(_box((1.22, 1.02, 0.04), (0.0, 0.0, 0.52)), "paint"),
    ]
    for s in (-1.0, 1.0):
        parts.append(_part(_rod((0.0, s * 0.5, 0.0), (0.0, s * 0.85, 0.0), 0.03), "metal"))
        parts.append(_part(_box((0.9, 1.8, 0.02), (0.0, s * 1.75, 0.0)), "solar"))
    parts.append(_part(_rod((-0.6, 0.3, 0.3), (-1.9, 0.3, 0.3), 0.015), "metal"))
    parts.append(_part(_box((0.1, 0.1, 0.1), (-1.95, 0.3, 0.3)), "dark"))
    parts.append(_part(_rod((0.6, 0.0, -0.1), (0.8, 0.0, -0.1), 0.04), "metal"))
    parts.append(_part(_dish(0.45, 0.15, np.array([0.8, 0.0, -0.1]), np.array([1.0, 0.0, 0.0])), "paint"))
    return build_scene(parts)


# The terrain patch: half its side (m), grid step (m), and the crater population. At the descent preset's
# 10 m start altitude the camera sees about ±8 m of ground; the patch leaves a margin for the ground track.
SURFACE_HALF_SIZE = 12.0
SURFACE_STEP = 0.08
SURFACE_SEED = 0
CRATERS = 1500
CRATER_RADII = (0.15, 3.0)
CRATER_SLOPE = 2.0
"""Cumulative size distribution N(> r) ∝ r^-CRATER_SLOPE (about the lunar one at these sizes)."""
BOULDERS = 60


def _crater_profile(r: np.ndarray) -> np.ndarray:
    """Height of a crater of unit radius at normalised distance ``r``: a bowl of depth 0.35 below a rim
    0.08 high, the ejecta blanket falling off as r^-3 outside, reaching 0 at r = 3."""
    rim, depth = 0.08, 0.35
    inside = rim + depth * (r**2 - 1.0)
    outside = rim * (np.maximum(r, 1.0) ** -3.0 - 1.0 / 27.0) / (1.0 - 1.0 / 27.0)
    return np.where(r < 1.0, inside, np.where(r < 3.0, outside, 0.0))


def surface_heights(seed: int = SURFACE_SEED) -> tuple[np.ndarray, np.ndarray]:
    """Grid coordinates (n,) and heights (n, n) (indexed ``[iy, ix]``) of the terrain: rolling noise
    of a few octaves plus craters of random freshness with a power-law size distribution."""
    rng = np.random.default_rng(seed)
    n = round(2 * SURFACE_HALF_SIZE / SURFACE_STEP) + 1
    xs = np.linspace(-SURFACE_HALF_SIZE, SURFACE_HALF_SIZE, n)
    h = np.zeros((n, n))
    # Rolling terrain and small-scale roughness: (correlation length m, standard deviation m).
    for length, amplitude in ((4.0, 0.25), (1.2, 0.06), (0.3, 0.02), (0.12, 0.008)):
        octave = gaussian_filter(rng.standard_normal((n, n)), length / SURFACE_STEP, mode="wrap")
        h += amplitude * octave / octave.std()
    r_min, r_max = CRATER_RADII
    # Inverse-CDF sampling of the truncated power law.
    u = rng.random(CRATERS)
    a, b = r_min**-CRATER_SLOPE, r_max**-CRATER_SLOPE
    radii = (a - u * (a - b)) ** (-1.0 / CRATER_SLOPE)
    centres = rng.uniform(-SURFACE_HALF_SIZE, SURFACE_HALF_SIZE, (CRATERS, 2))
    freshness = rng.uniform(0.3, 1.0, CRATERS)  # older craters are shallower (degraded)
    for (cx, cy), radius, fresh in zip(centres, radii, freshness, strict=True):
        reach = 3.0 * radius
        i0, i1 = np.searchsorted(xs, [cy - reach, cy + reach])
        j0, j1 = np.searchsorted(xs, [cx - reach, cx + reach])
        if i1 <= i0 or j1 <= j0:
            continue
        dist = np.hypot(xs[j0:j1][None, :] - cx, xs[i0:i1][:, None] - cy) / radius
        h[i0:i1, j0:j1] += fresh * radius * _crater_profile(dist)
    return xs, h


def _heightfield(xs: np.ndarray, h: np.ndarray) -> trimesh.Trimesh:
    n = len(xs)
    gx, gy = np.meshgrid(xs, xs)
    vertices = np.stack([gx.ravel(), gy.ravel(), h.ravel()], -1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])  # counter-clockwise: +z
    return trimesh.Trimesh(vertices, faces, process=False)


def _height_at(xs: np.ndarray, h: np.ndarray, x: float, y: float) -> float:
    j = int(np.clip(np.searchsorted(xs, x), 0, len(xs) - 1))
    i = int(np.clip(np.searchsorted(xs, y), 0, len(xs) - 1))
    return float(h[i, j])


def surface(seed: int = SURFACE_SEED) -> Scene:
    """Lunar-like terrain patch (24 m square, z = height, ~180 k triangles): a cratered heightfield and
    a scatter of half-buried, irregular boulders, all regolith. Deterministic for a given ``seed``."""
    xs, h = surface_heights(seed)
    rng = np.random.default_rng([seed, 1])
    parts = [_part(_heightfield(xs, h), "regolith")]
    limit = 0.9 * SURFACE_HALF_SIZE
    for _ in range(BOULDERS):
        radius = 0.08 * (1.0 - rng.random()) ** -0.6  # mostly small, a few up to ~0.5 m
        x, y = rng.uniform(-limit, limit, 2)
        rock = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
        rock.vertices *= rng.uniform(0.8, 1.2, (len(rock.vertices), 1))  # irregular facets
        rock.vertices *= radius * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.5, 0.8)])
        rock.apply_transform(rotation_matrix(rng.uniform(0, 2 * np.pi), [0, 0, 1]))
        rock.apply_translation([x, y, _height_at(xs, h, x, y)])  # the lower part is buried
        parts.append(_part(rock, "regolith"))
    return build_scene(parts)


TARGETS = {"hubble": hubble, "satellite": satellite, "surface": surface}


def load_mesh(path: str | Path, material: str = "paint", scale: float = 1.0) -> Scene:
    """Any mesh trimesh reads, centred on its bounding box, scaled, with one material."""
    path = Path(path)
    if material not in MATERIAL_IDS:
        raise ValueError(f"unknown material {material!r} (choose from {', '.join(MATERIAL_IDS)})")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path}: cannot load mesh: {e}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: no triangles")
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    mesh.apply_scale(scale)
    return build_scene([(mesh, MATERIAL_IDS[material])])


def make_scene(target: str, material: str = "paint", scale: float = 1.0, seed: int = SURFACE_SEED) -> Scene:
    """A built-in target by name (the terrain drawn from ``seed``) scaled about its origin, or a mesh
    file centred and scaled."""
    if target in TARGETS:
        scene = surface(seed) if target == "surface" else TARGETS[target]()
        return Scene(scene.triangles * scale, scene.normals, scene.material) if scale != 1.0 else scene
    if not Path(target).is_file():
        raise ValueError(f"target {target!r} is neither a built-in ({', '.join(TARGETS)}) nor a mesh file")
    return load_mesh(target, material, scale)

"""Surface materials of the simulated targets (monochrome: an event camera sees one channel).

The shader (``render.py``) reads one row per material: Lambertian albedo, a normalised Blinn–Phong
specular lobe, a crinkle bump (faceted normal perturbation per 3-D cell, which makes foil glints flicker
as the view changes) and an optional solar-cell grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Material:
    albedo: float
    specular: float = 0.0
    shininess: float = 1.0
    bump: float = 0.0
    """Amplitude of the crinkle normal perturbation (0 = smooth)."""
    bump_freq: float = 0.0
    """Crinkle cells per metre."""
    cell_pitch: float = 0.0
    """Solar-cell grid pitch in metres (0 = no grid)."""


MATERIALS: dict[str, Material] = {
    # White thermal paint: diffuse.
    "paint": Material(albedo=0.7, specular=0.03, shininess=8.0),
    # Crinkled multi-layer-insulation foil: dim diffuse, strong glossy specular, bumpy.
    "foil": Material(albedo=0.25, specular=0.5, shininess=60.0, bump=0.35, bump_freq=9.0),
    # Solar cells: dark glass with a bright grid between cells.
    "solar": Material(albedo=0.08, specular=0.25, shininess=120.0, cell_pitch=0.12),
    # Black anodised parts, antennas.
    "dark": Material(albedo=0.05, specular=0.1, shininess=20.0),
    # Bare aluminium.
    "metal": Material(albedo=0.45, specular=0.35, shininess=30.0),
    # Lunar regolith: dark grey, diffuse; its texture comes from relief under a low sun.
    "regolith": Material(albedo=0.15),
}

MATERIAL_IDS: dict[str, int] = {name: i for i, name in enumerate(MATERIALS)}


def material_table() -> np.ndarray:
    """(M, 8) float32 rows ``albedo, specular, shininess, bump, bump_freq, cell_pitch, 0, 0`` by id."""
    rows = [
        [m.albedo, m.specular, m.shininess, m.bump, m.bump_freq, m.cell_pitch, 0.0, 0.0]
        for m in MATERIALS.values()
    ]
    return np.asarray(rows, np.float32)

"""Lighting of the simulated scenes: a directional sun with shadows plus unshadowed fill lights.

Directions point from the scene towards the light, in the target (world) frame; intensities are in
sensor units (a white Lambertian surface facing a light of intensity 1 renders at its albedo).
The presets mirror the paper's scenarios: SEENIC's ambient and strongly directional set-ups and the
Blender scenes' bright (10 kW) and dim (100 W) four-light rigs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Lighting:
    sun_dir: tuple[float, float, float]
    sun: float
    fills: tuple[tuple[tuple[float, float, float], float], ...] = ()
    """(direction, intensity) of each fill light (no shadows)."""
    ambient: float = 0.0

    def scaled(self, k: float) -> Lighting:
        return Lighting(
            self.sun_dir, self.sun * k, tuple((d, i * k) for d, i in self.fills), self.ambient * k
        )


def unit(v: tuple[float, float, float]) -> np.ndarray:
    a = np.asarray(v, np.float64)
    return a / np.linalg.norm(a)


# The Blender rig: three lights in a triangle above the target and one below.
_RIG = (
    ((1.0, 0.0, 1.2), 0.45),
    ((-0.5, 0.87, 1.2), 0.45),
    ((-0.5, -0.87, 1.2), 0.45),
    ((0.2, 0.3, -1.0), 0.25),
)


def from_horizon(elevation_deg: float, azimuth_deg: float) -> tuple[float, float, float]:
    """Unit direction ``elevation_deg`` above the horizontal plane, ``azimuth_deg`` from +x towards +y."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    return (float(np.cos(el) * np.cos(az)), float(np.cos(el) * np.sin(az)), float(np.sin(el)))


GOOD = Lighting(sun_dir=(0.6, 0.5, 0.6), sun=1.0, fills=_RIG[:1] + _RIG[3:], ambient=0.01)

LIGHTING: dict[str, Lighting] = {
    # Bright sun plus two fills: the "good light" Blender scenes.
    "good": GOOD,
    # Same rig at 1 % of the power (100 W vs 10 kW in the paper).
    "low": GOOD.scaled(0.01),
    # Evenly lit from every side: SEENIC "ambient".
    "ambient": Lighting(sun_dir=(0.3, 0.4, 1.0), sun=0.35, fills=_RIG, ambient=0.05),
    # One hard sun from the side, nothing else: strong contrast and shadows.
    "directional": Lighting(sun_dir=(0.2, 1.0, 0.3), sun=1.2),
    # Lunar descent: a grazing sun 15° above the horizon, from behind on the left of a lander heading +x,
    # so that craters and boulders cast long shadows (bright enough that flat regolith renders at ~0.1),
    # and a faint ambient standing in for earthshine and light scattered off the surroundings.
    "low_sun": Lighting(sun_dir=from_horizon(15.0, 120.0), sun=3.0, ambient=0.03),
}

"""Simulation settings (one flat, TOML-friendly dataclass) and the named presets.

The presets mirror the paper's scenarios: SEENIC's Hubble mock-up in ambient / strongly directional light
(``orbit_ambient`` is the built-in default sequence) and the Blender scenes of Table 3 (docking, swirl,
orbit; good and low light) on a generic satellite bus. ``descent`` is an ELOPE-like lunar lander's final
approach over cratered terrain under a low sun. ``tiny`` is a fast 160×120 preset for tests.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from evgs.data.sequence import Camera
from evgs.sim.lights import LIGHTING
from evgs.sim.trajectory import ReplayTrajectory, Trajectory


@dataclass(frozen=True)
class SimConfig:
    name: str
    # Scene.
    target: str = "hubble"
    """``hubble``, ``satellite``, ``surface`` (lunar-like terrain) or a mesh file."""
    material: str = "paint"
    """Material of a mesh file (built-in targets carry their own)."""
    mesh_scale: float = 1.0
    """Size factor of the target (a mesh file is centred first; built-ins scale about their origin)."""
    lighting: str = "good"
    # Camera (DVXplorer-like 640×480, ~60° horizontal field of view).
    width: int = 640
    height: int = 480
    fx: float = 560.0
    fy: float = 560.0
    cx: float = 319.5
    cy: float = 239.5
    distortion: tuple[float, ...] = ()
    """OpenCV ``k1, k2, p1, p2, k3`` (``--set distortion=-0.1,0.02,0,0,0``); empty: pinhole."""
    # Trajectory.
    trajectory: str = "orbit"
    poses: str = ""
    """A TUM file to replay instead of the generated trajectory (empty: none)."""
    distance: float = 8.0
    speed: float = 2.0
    duration: float = 4.0
    elevation_deg: float = 20.0
    azimuth_deg: float = 0.0
    # Output rates.
    frame_rate: float = 25.0
    """Frame (chunk-boundary) and ground-truth image rate, Hz."""
    range_rate: float = 10.0
    # Event sensor (see src/sim/esim.rs).
    c_on: float = 0.25
    c_off: float = 0.25
    sigma_c: float = 0.03
    refractory_us: float = 100.0
    log_eps: float = 1e-3
    shot_rate_hz: float = 0.1
    shot_dark_level: float = 0.01
    leak_rate_hz: float = 0.05
    hot_pixel_fraction: float = 5e-5
    hot_pixel_rate_hz: float = 10.0
    # Adaptive render rate: steps such that the `change_quantile` of |Δ log I| over the lit pixels that
    # change stays below `change_fraction`·C (smooth shading, sweeping highlights) and no vertex moves
    # more than `max_px_per_frame` pixels (edges, which are steps at any rate).
    change_fraction: float = 0.5
    change_quantile: float = 0.5
    max_px_per_frame: float = 1.0
    dt_min_us: int = 200
    dt_max_us: int = 10_000
    msaa: int = 4
    shadow_size: int = 2048
    """Side of the sun's shadow map in texels (it covers the whole scene: large scenes need more)."""
    seed: int = 0
    """Sensor noise, and the terrain of the ``surface`` target."""

    @property
    def camera(self) -> Camera:
        return Camera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.distortion)

    def validate(self) -> None:
        """Raise ValueError naming the first setting that cannot work (the Rust core checks the sensor
        model, the trajectory its own parameters)."""
        checks = [
            ("lighting", self.lighting in LIGHTING, f"one of {', '.join(LIGHTING)}"),
            ("width", self.width > 0 and self.height > 0, "a positive sensor size"),
            ("frame_rate", self.frame_rate > 0, "> 0"),
            ("range_rate", self.range_rate > 0, "> 0"),
            ("change_fraction", self.change_fraction > 0, "> 0"),
            ("change_quantile", 0.0 <= self.change_quantile <= 1.0, "in [0, 1]"),
            ("max_px_per_frame", self.max_px_per_frame > 0, "> 0"),
            ("dt_min_us", 1 <= self.dt_min_us <= self.dt_max_us, "≥ 1 and ≤ dt_max_us"),
            ("msaa", self.msaa >= 0, "≥ 0"),
            ("shadow_size", 64 <= self.shadow_size <= 8192, "in [64, 8192]"),
            ("mesh_scale", self.mesh_scale > 0, "> 0"),
        ]
        for name, ok, need in checks:
            if not ok:
                raise ValueError(f"setting {name} = {getattr(self, name)!r}: must be {need}")

    def make_trajectory(self) -> Trajectory | ReplayTrajectory:
        if self.poses:
            return ReplayTrajectory(self.poses)
        return Trajectory(
            self.trajectory, self.distance, self.speed, self.duration, self.elevation_deg, self.azimuth_deg
        )

    def with_resolution(self, width: int, height: int) -> SimConfig:
        """Same field of view at another sensor size."""
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(
            self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
        )  # fmt: skip

    def override(self, key: str, value: str) -> SimConfig:
        """Set one field from its text form (``--set key=value``), converted to the field's type."""
        fields = {f.name: f for f in dataclasses.fields(self)}
        if key not in fields:
            raise ValueError(f"unknown setting {key!r} (known: {', '.join(fields)})")
        kind = type(getattr(self, key))
        try:
            if kind is tuple:
                return dataclasses.replace(
                    self, **{key: tuple(float(v) for v in value.split(",") if v.strip())}
                )
            return dataclasses.replace(self, **{key: kind(value)})
        except ValueError:
            raise ValueError(f"setting {key}: cannot read {value!r} as {kind.__name__}") from None


_DOCKING = SimConfig(
    "docking", target="satellite", trajectory="approach", distance=9.0, speed=1.0, duration=3.0,
    elevation_deg=10.0, azimuth_deg=30.0,
)  # fmt: skip
_SWIRL = dataclasses.replace(_DOCKING, name="swirl", trajectory="swirl")

PRESETS: dict[str, SimConfig] = {
    "orbit_ambient": SimConfig("orbit_ambient", lighting="ambient"),
    "orbit_directional": SimConfig("orbit_directional", lighting="directional"),
    "docking_good": dataclasses.replace(_DOCKING, name="docking_good", lighting="good"),
    "docking_low": dataclasses.replace(_DOCKING, name="docking_low", lighting="low"),
    "swirl_good": dataclasses.replace(_SWIRL, name="swirl_good", lighting="good"),
    "swirl_low": dataclasses.replace(_SWIRL, name="swirl_low", lighting="low"),
    "orbit": SimConfig("orbit", target="satellite", distance=6.0, speed=1.5, duration=4.0),
    # 10 m → 4.5 m altitude in 4 s on a 60° glide path (1.4 m/s down, 0.8 m/s forward).
    "descent": SimConfig(
        "descent",
        target="surface",
        lighting="low_sun",
        trajectory="descent",
        distance=10.0,
        speed=1.6,
        duration=4.0,
        elevation_deg=60.0,
        shadow_size=4096,
    ),  # fmt: skip
    "tiny": SimConfig("tiny", duration=0.4).with_resolution(160, 120),
}


def preset(name: str) -> SimConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return PRESETS[name]

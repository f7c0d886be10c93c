"""The ELOPE-like descent: a deterministic cratered terrain that fills the view for the whole descent,
camera-to-world poses that look down with the direction of travel "up" in the image, a range meter on
the optical axis, and the preset end to end at a small resolution."""

import dataclasses

import numpy as np
import pytest
import trimesh
from evgs.data.sequence import Sequence
from evgs.sim.driver import simulate
from evgs.sim.lights import Lighting
from evgs.sim.materials import MATERIAL_IDS
from evgs.sim.presets import preset
from evgs.sim.render import Renderer
from evgs.sim.scene import (
    SURFACE_HALF_SIZE,
    _crater_profile,
    build_scene,
    make_scene,
    surface,
    surface_heights,
)
from evgs.sim.trajectory import DESCENT_TILT_DEG, Trajectory

FLAT = Lighting(sun_dir=(0.0, 0.0, 1.0), sun=0.0, ambient=1.0)


@pytest.fixture(scope="module")
def terrain():
    return surface()


def corner_rays(camera, T_wc: np.ndarray) -> np.ndarray:
    """World directions (4, 3) of the rays through the image corners."""
    uv = np.array(
        [[0, 0], [camera.width - 1, 0], [0, camera.height - 1], [camera.width - 1, camera.height - 1]]
    )
    d = np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(4)], -1)
    d = d @ T_wc[:3, :3].T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_terrain_is_deterministic_and_cratered(terrain):
    xs, h = surface_heights()
    xs2, h2 = surface_heights()
    np.testing.assert_array_equal(h, h2)
    assert not np.array_equal(h, surface_heights(seed=1)[1])
    again = surface()
    np.testing.assert_array_equal(terrain.triangles, again.triangles)
    # The simulation's seed draws the terrain; the default seed is the one the preset was tuned on.
    np.testing.assert_array_equal(make_scene("surface", seed=0).triangles, terrain.triangles)
    assert not np.array_equal(make_scene("surface", seed=1).triangles, terrain.triangles)
    np.testing.assert_array_equal(terrain.normals, again.normals)
    assert np.all(terrain.material == MATERIAL_IDS["regolith"])
    assert 50_000 < len(terrain.triangles) < 300_000  # moderate: the renderer and the ray cast stay fast
    # Relief of a lunar patch: metres across, a metre or so deep; rough at every scale (craters).
    assert xs[0] == -SURFACE_HALF_SIZE and xs[-1] == SURFACE_HALF_SIZE
    assert 0.1 < h.std() < 1.0 and np.ptp(h) < 4.0
    slope = np.hypot(*np.gradient(h, xs[1] - xs[0]))
    assert np.percentile(slope, 90) > 0.15
    # The crater profile: a bowl below a raised rim, continuous, flat beyond three radii.
    r = np.array([0.0, 1.0 - 1e-9, 1.0 + 1e-9, 2.0, 3.0, 4.0])
    p = _crater_profile(r)
    assert p[0] < 0 < p[1] and p[1] == pytest.approx(p[2]) and p[2] > p[3] > 0
    assert p[4] == pytest.approx(0.0, abs=1e-12) and p[5] == 0.0


def test_descent_trajectory_is_a_straight_glide_looking_down():
    traj = Trajectory("descent", distance=10.0, speed=1.6, duration=4.0, elevation_deg=60.0, azimuth_deg=30.0)
    t = np.linspace(0.0, 4.0, 9)
    T = traj(t)
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    heading = np.array([np.cos(np.radians(30.0)), np.sin(np.radians(30.0)), 0.0])
    p = T[:, :3, 3]
    # 1.6 m/s on a 60° glide path: 1.386 m/s down, 0.8 m/s along the heading, ground track centred.
    np.testing.assert_allclose(p[:, 2], 10.0 - 1.6 * np.sin(np.radians(60.0)) * t, atol=1e-12)
    np.testing.assert_allclose(p[:, :2], np.outer(0.8 * (t - 2.0), heading[:2]), atol=1e-12)
    # The optical axis is DESCENT_TILT_DEG from nadir, tilted forwards; image up is forwards too.
    tilt = np.radians(DESCENT_TILT_DEG)
    axis = np.cos(tilt) * np.array([0.0, 0.0, -1.0]) + np.sin(tilt) * heading
    np.testing.assert_allclose(T[:, :3, 2], np.broadcast_to(axis, (9, 3)), atol=1e-12)
    assert np.all(-T[:, :3, 1] @ heading > 0.9)
    # Straight down is a valid descent (look_at would have no image "up" there).
    vertical = Trajectory("descent", distance=5.0, speed=1.0, duration=2.0, elevation_deg=90.0)(1.0)
    np.testing.assert_allclose(vertical[:3, 3], [0.0, 0.0, 4.0], atol=1e-12)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(distance=5.0, speed=3.0, duration=2.0, elevation_deg=60.0), "reach the surface"),
        (dict(distance=5.0, speed=1.0, duration=2.0, elevation_deg=0.0), "glide angle"),
        (dict(distance=5.0, speed=1.0, duration=2.0, elevation_deg=120.0), "glide angle"),
    ],
)
def test_descent_that_cannot_fly_is_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Trajectory("descent", **kwargs)


def test_ground_points_render_where_the_pose_says():
    """A marker on the ground straight below the camera appears DESCENT_TILT_DEG below the image centre;
    one ahead appears higher up, one to the left (of the direction of travel) left of the centre."""
    cfg = preset("descent").with_resolution(320, 240)
    cam = cfg.camera
    T = cfg.make_trajectory()(1.0)
    x0, altitude = T[0, 3], T[2, 3]
    ahead, left = 0.3 * altitude, 0.2 * altitude
    markers = {
        "below": ([x0, 0.0, 0.0], (cam.cx, cam.cy + cam.fy * np.tan(np.radians(DESCENT_TILT_DEG)))),
        "ahead": ([x0 + ahead, 0.0, 0.0], None),
        "left": ([x0, left, 0.0], None),
    }
    centroids = {}
    for name, (pos, _) in markers.items():
        ball = trimesh.creation.icosphere(subdivisions=2, radius=0.015 * altitude)
        ball.apply_translation(pos)
        with Renderer(build_scene([(ball, MATERIAL_IDS["paint"])]), cam, FLAT) as r:
            img = r.render(T)
        yy, xx = np.nonzero(img > 0)
        w = img[yy, xx].astype(np.float64)
        centroids[name] = np.array([(xx * w).sum(), (yy * w).sum()]) / w.sum()
    np.testing.assert_allclose(centroids["below"], markers["below"][1], atol=0.3)
    # Ahead: the ray's angle from nadir is atan(ahead / altitude), i.e. that minus the tilt from the axis.
    v_ahead = cam.cy - cam.fy * np.tan(np.arctan(ahead / altitude) - np.radians(DESCENT_TILT_DEG))
    np.testing.assert_allclose(centroids["ahead"], [cam.cx, v_ahead], atol=0.3)
    assert centroids["left"][0] < cam.cx - 30 and abs(centroids["left"][1] - centroids["below"][1]) < 2


def test_terrain_fills_the_view_for_the_whole_descent(terrain):
    cfg = preset("descent")
    traj = cfg.make_trajectory()
    for t in np.linspace(0.0, traj.t_end, 5):
        T = traj(t)
        assert np.isfinite(terrain.ray_distance(T[:3, 3], T[:3, 2])), f"t={t}: principal ray misses"
        for d in corner_rays(cfg.camera, T):
            assert np.isfinite(terrain.ray_distance(T[:3, 3], d)), f"t={t}: sky in a corner"


def test_descent_preset_simulates_events_and_range(tmp_path):
    cfg = dataclasses.replace(preset("descent").with_resolution(160, 120), duration=0.3)
    seq = simulate(cfg, tmp_path / "descent", progress=False)
    seq = Sequence.load(seq.root)
    ev = seq.events()
    ev.validate("descent")
    frames = seq.frames_us()
    np.testing.assert_array_equal(frames, np.arange(0, 300_001, 40_000))
    # Texture everywhere: many events per frame (the full preset makes ~0.4 per pixel), both
    # polarities, and most pixels fire.
    assert len(ev) > 0.2 * 160 * 120 * (len(frames) - 1)
    assert 0.3 < np.mean(ev.p == 1) < 0.7
    assert len(np.unique(ev.y.astype(np.int64) * 160 + ev.x)) > 0.5 * 160 * 120
    # The GT images are terrain to the border: no black sky, shadows and sunlit slopes.
    for k in (0, len(frames) - 1):
        img = seq.image(k)
        assert np.mean(img == 0.0) < 0.01 and img.std() > 0.03
    # Range along the optical axis: every sample hits, about altitude / cos(tilt), decreasing.
    rt, rd = seq.range_samples()
    np.testing.assert_array_equal(rt, np.arange(0, 300_001, 100_000))
    assert seq.meta["simulator"]["stats"]["range_misses"] == 0
    t_us, T_wc = seq.poses_gt()
    altitude = np.interp(rt, t_us, T_wc[:, 2, 3])
    slant = altitude / np.cos(np.radians(DESCENT_TILT_DEG))
    assert np.all(np.abs(rd - slant) < 1.5)
    assert np.all(np.diff(rd) < 0)

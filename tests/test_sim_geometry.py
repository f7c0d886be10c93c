"""Geometry of the simulator: trajectories give camera-to-world poses looking at the target, and a known
mesh vertex appears in the rendered image exactly where the pinhole model projects it."""

import dataclasses

import cv2
import numpy as np
import pytest
import trimesh
from evgs.data.tum import write_tum
from evgs.sim.driver import project
from evgs.sim.lights import Lighting
from evgs.sim.materials import MATERIAL_IDS
from evgs.sim.presets import SimConfig
from evgs.sim.render import Renderer
from evgs.sim.scene import build_scene, hubble, load_mesh, make_scene, satellite
from evgs.sim.trajectory import ReplayTrajectory, Trajectory, look_at

MARKER = np.array([0.4, -0.3, 0.25])
# Flat light from everywhere: a paint surface renders uniformly, so a blob's centroid is its centre.
FLAT = Lighting(sun_dir=(0.0, 0.0, 1.0), sun=0.0, ambient=1.0)


def marker_scene(position=MARKER):
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    ball.apply_translation(position)
    return build_scene([(ball, MATERIAL_IDS["paint"])])


@pytest.mark.parametrize("kind", ["approach", "swirl", "orbit"])
def test_trajectory_poses_look_at_the_target(kind):
    traj = Trajectory(kind, distance=8.0, speed=1.5, duration=3.0, elevation_deg=20.0, azimuth_deg=30.0)
    t = np.linspace(0.0, 3.0, 7)
    T = traj(t)
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    # Camera z axis points at the origin; camera y (image down) has a negative world-z component.
    to_target = -T[:, :3, 3] / np.linalg.norm(T[:, :3, 3], axis=1, keepdims=True)
    np.testing.assert_allclose(T[:, :3, 2], to_target, atol=1e-12)
    assert np.all(T[:, 2, 1] < 0)
    speed = np.linalg.norm(np.diff(traj.positions(np.linspace(0, 3, 3001)), axis=0), axis=1).sum() / 3.0
    if kind == "swirl":
        assert speed > 1.5  # the sideways excursion adds path length
        mid = traj.positions(1.5)
        assert np.linalg.norm(np.cross(mid, traj.positions(0.0))) > 1.0  # it leaves the straight line
    else:
        assert speed == pytest.approx(1.5, rel=1e-4)


def test_approach_that_reaches_the_target_is_rejected():
    with pytest.raises(ValueError, match="would reach the target"):
        Trajectory("approach", distance=3.0, speed=2.0, duration=2.0)


def test_replay_interpolates_a_tum_file(tmp_path):
    traj = Trajectory("orbit", distance=6.0, speed=2.0, duration=2.0)
    t = np.linspace(0.0, 2.0, 41)
    write_tum(tmp_path / "p.txt", 100.0 + t, traj(t))
    replay = ReplayTrajectory(tmp_path / "p.txt")
    assert replay.t0 == pytest.approx(100.0) and replay.t_end == pytest.approx(2.0)
    np.testing.assert_allclose(replay(t), traj(t), atol=1e-7)
    # Between samples: close to the true circle (chord error of a 0.05 s step).
    np.testing.assert_allclose(replay(np.array([1.025]))[0], traj(1.025), atol=2e-3)


def _kinds():
    return [
        ("approach", Trajectory("approach", 6.0, 1.0, 2.0, 15.0, 20.0)),
        ("swirl", Trajectory("swirl", 6.0, 1.0, 2.0, 15.0, 20.0)),
        ("orbit", Trajectory("orbit", 6.0, 1.0, 2.0, 15.0, 20.0)),
    ]


@pytest.fixture(scope="module")
def renderer():
    cam = SimConfig("t").with_resolution(320, 240).camera
    with Renderer(marker_scene(), cam, FLAT) as r:
        yield r


@pytest.mark.parametrize("kind,traj", _kinds(), ids=[k for k, _ in _kinds()])
def test_marker_vertex_renders_where_it_projects(renderer, kind, traj):
    cam = renderer.camera
    for t in (0.3, 1.0, 1.7):
        T = traj(t)
        img = renderer.render(T)
        assert img.shape == (cam.height, cam.width) and img.dtype == np.float32
        yy, xx = np.nonzero(img > 0)
        assert len(xx) > 3, f"{kind} t={t}: marker not visible"
        w = img[yy, xx].astype(np.float64)
        centroid = np.array([(xx * w).sum(), (yy * w).sum()]) / w.sum()
        expected = project(cam, T, MARKER[None])[0]
        np.testing.assert_allclose(centroid, expected, atol=0.15, err_msg=f"{kind} t={t}")
        # Away from the marker the image is exactly black (space background).
        far = np.hypot(*(np.mgrid[0 : cam.height, 0 : cam.width][::-1] - expected[:, None, None])) > 10
        assert np.all(img[far] == 0.0)


@pytest.mark.parametrize("make", [hubble, satellite])
def test_procedural_targets_are_sane(make):
    s = make()
    assert s.triangles.shape[1:] == (3, 3) and s.normals.shape == s.triangles.shape
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=-1), 1.0, atol=1e-6)
    centre, radius = s.bounds
    assert 1.0 < radius < 4.0
    assert len(np.unique(s.material)) >= 3
    # A ray from outside along -x hits the body before the origin.
    d = s.ray_distance(np.array([10.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]))
    assert 8.0 < d < 10.0
    assert s.ray_distance(np.array([10.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])) == np.inf


def test_distorted_camera_renders_where_opencv_projects():
    cfg = SimConfig("t").with_resolution(320, 240)
    cam = dataclasses.replace(cfg, distortion=(-0.3, 0.1, 1e-3, -1e-3, 0.0)).camera
    T = Trajectory("orbit", 6.0, 1.0, 2.0, 15.0, 20.0)(0.2)
    # A marker off-centre (normalised image coordinates (0.33, 0.23)), where distortion moves it.
    marker = T[:3, :3] @ np.array([2.0, 1.4, 6.0]) + T[:3, 3]
    with Renderer(marker_scene(marker), cam, FLAT) as r:
        img = r.render(T)
    assert img.shape == (240, 320)
    yy, xx = np.nonzero(img > 0)
    w = img[yy, xx].astype(np.float64)
    centroid = np.array([(xx * w).sum(), (yy * w).sum()]) / w.sum()
    T_cw = np.linalg.inv(T)
    rvec, _ = cv2.Rodrigues(T_cw[:3, :3])
    uv, _ = cv2.projectPoints(marker[None], rvec, T_cw[:3, 3], cam.K, np.array(cam.distortion))
    assert np.linalg.norm(uv[0, 0] - project(cam, T, marker[None])[0]) > 2.0  # distortion matters here
    np.testing.assert_allclose(centroid, uv[0, 0], atol=0.25)


def test_any_mesh_file_can_be_the_target(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    box.apply_translation([5.0, 0.0, 0.0])
    box.export(tmp_path / "box.ply")
    s = load_mesh(tmp_path / "box.ply", material="foil", scale=2.0)
    np.testing.assert_allclose(s.triangles.reshape(-1, 3).min(0), [-1.0, -2.0, -0.5], atol=1e-6)
    assert np.all(s.material == MATERIAL_IDS["foil"])
    assert make_scene(str(tmp_path / "box.ply")).triangles.shape == s.triangles.shape
    (tmp_path / "bad.obj").write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match=r"bad.obj"):
        load_mesh(tmp_path / "bad.obj")
    with pytest.raises(ValueError, match="unknown material"):
        load_mesh(tmp_path / "box.ply", material="gold")


def test_built_in_targets_scale_about_their_origin():
    base, big = make_scene("satellite"), make_scene("satellite", scale=2.5)
    np.testing.assert_allclose(big.triangles, 2.5 * base.triangles)
    np.testing.assert_array_equal(big.normals, base.normals)
    np.testing.assert_array_equal(big.material, base.material)


def test_sun_casts_shadows():
    floor = trimesh.creation.box(extents=(4.0, 4.0, 0.02))
    floor.apply_translation([0.0, 0.0, -0.01])
    blocker = trimesh.creation.box(extents=(1.0, 1.0, 0.1))
    blocker.apply_translation([0.0, 0.0, 1.0])
    scene = build_scene([(floor, MATERIAL_IDS["paint"]), (blocker, MATERIAL_IDS["paint"])])
    cam = SimConfig("t").with_resolution(320, 240).camera
    T = look_at(np.array([4.0, 0.0, 3.0]))
    with Renderer(scene, cam, Lighting(sun_dir=(0.0, 0.0, 1.0), sun=1.0)) as r:
        img = r.render(T)
    shadowed, lit = np.round(project(cam, T, np.array([[-0.2, 0.1, 0.0], [1.5, -0.5, 0.0]]))).astype(int)
    assert img[lit[1], lit[0]] == pytest.approx(0.7, abs=0.05)  # paint albedo under a zenith sun
    assert img[shadowed[1], shadowed[0]] == 0.0  # no fill, no ambient: pure shadow


def test_depth_is_the_camera_z_of_the_nearest_surface():
    """The depth pass against ray–plane intersections (tilted view: z-depth, not ray length), the ball
    in front of the plane where it hides it, and inf where nothing is hit."""
    floor = trimesh.creation.box(extents=(4.0, 4.0, 0.002))
    floor.apply_translation([0.0, 0.0, -0.001])  # top face at z = 0
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    ball.apply_translation([0.0, 0.0, 0.3])
    scene = build_scene([(floor, MATERIAL_IDS["paint"]), (ball, MATERIAL_IDS["paint"])])
    cam = SimConfig("t").with_resolution(160, 120).camera
    T = look_at(np.array([3.0, 1.0, 2.5]))
    with Renderer(scene, cam, FLAT, msaa=0) as r:
        z = r.depth(T)
    rays = np.linalg.solve(cam.K, np.array([[50.0, 40.0, 1.0], [150.0, 100.0, 1.0], [30.0, 110.0, 1.0]]).T)
    world = T[:3, :3] @ rays  # direction per unit of camera z
    t = -T[2, 3] / world[2]  # camera z where the ray meets z = 0
    np.testing.assert_allclose(z[[40, 100, 110], [50, 150, 30]], t, rtol=1e-4)
    centre = np.round(project(cam, T, np.array([[0.0, 0.0, 0.3]]))[0]).astype(int)
    to_ball = np.linalg.norm(T[:3, 3] - [0.0, 0.0, 0.3])
    assert z[centre[1], centre[0]] == pytest.approx(to_ball - 0.3, rel=0.01)  # the ball's near side
    away = look_at(np.array([3.0, 0.0, 5.0]), np.array([8.0, 0.0, 9.0]))
    with Renderer(scene, cam, FLAT, msaa=0) as r:
        assert np.isinf(r.depth(away)).all()  # looking away from everything

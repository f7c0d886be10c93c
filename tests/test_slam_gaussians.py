"""Gaussian parameters: random init and the 3DGS PLY layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from evgs.config import load_config
from evgs.data.sequence import Camera
from evgs.slam.gaussians import (
    PARAM_NAMES,
    SH_C0,
    Gaussians,
    knn_log_scale,
    load_ply,
    make_optimizer,
    quat_to_rotmat,
    save_ply,
)
from scipy.spatial.transform import Rotation


def small(n: int = 50, seed: int = 0) -> Gaussians:
    g = Gaussians.random(n, 2.0, 0.1, 0.05, torch.Generator().manual_seed(seed))
    with torch.no_grad():  # make every attribute distinct so a swapped column would show
        gen = torch.Generator().manual_seed(seed + 1)
        for p in g.params.values():
            p.add_(torch.randn(p.shape, generator=gen) * 0.1)
    return g


def test_random_init_inside_box_seeded_and_dim():
    a = Gaussians.random(1000, 3.0, 0.1, 0.05, torch.Generator().manual_seed(4))
    b = Gaussians.random(1000, 3.0, 0.1, 0.05, torch.Generator().manual_seed(4))
    assert all(torch.equal(a[k], b[k]) for k in PARAM_NAMES)
    assert a["means"].abs().max() <= 3.0 and a["means"].abs().max() > 2.5
    assert torch.allclose(a.opacities(), torch.full((1000,), 0.1))
    assert torch.all(a["colors"] == 0.05)
    assert torch.equal(a["quats"], torch.tensor([[1.0, 0, 0, 0]]).expand(1000, 4))
    assert torch.equal(a["log_scales"][:, 0], a["log_scales"][:, 2])  # isotropic


def test_knn_scale_on_a_grid():
    g = np.stack(np.meshgrid(*[np.arange(5.0)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.5
    s = np.exp(knn_log_scale(g))
    centre = np.all((g > 0) & (g < 2.0), axis=1)  # interior points: 3 neighbours at spacing 0.5
    assert np.allclose(s[centre], 0.5)


def test_on_rays_seeds_only_weighted_pixels_at_depths_in_range():
    camera = Camera(width=40, height=30, fx=50.0, fy=45.0, cx=19.5, cy=14.5)
    weights = torch.zeros(30, 40)
    weights[10:14, 5:9] = 1.0  # a 4×4 patch and one heavy pixel
    weights[25, 33] = 20.0
    g = Gaussians.on_rays(2000, weights, camera, (2.0, 5.0), 0.2, 0.3, torch.Generator().manual_seed(1))
    p = g["means"].detach().double()
    z = p[:, 2]
    assert bool(((z >= 2.0) & (z <= 5.0)).all())
    # OpenCV pixel centres (the camera's): pixel i spans [i - 0.5, i + 0.5).
    u = (p[:, 0] / z * camera.fx + camera.cx + 0.5).floor().long()
    v = (p[:, 1] / z * camera.fy + camera.cy + 0.5).floor().long()
    assert bool((weights[v, u] > 0).all())  # every Gaussian lies on a ray of a pixel with events
    heavy = float(((u == 33) & (v == 25)).double().mean())
    assert heavy == pytest.approx(20 / 36, abs=0.05)  # drawn in proportion to the weights
    assert torch.allclose(g.opacities(), torch.tensor(0.2)) and bool((g["colors"] == 0.3).all())
    again = Gaussians.on_rays(2000, weights, camera, (2.0, 5.0), 0.2, 0.3, torch.Generator().manual_seed(1))
    assert torch.equal(again["means"], g["means"])


def test_on_rays_tilted_puts_the_mid_depth_on_the_turned_plane_and_keeps_the_rays():
    camera = Camera(width=40, height=30, fx=50.0, fy=45.0, cx=19.5, cy=14.5)
    weights = torch.ones(30, 40)
    thin = (2.0, 2.0 + 1e-9)
    flat = Gaussians.on_rays(500, weights, camera, thin, 0.2, 0.3, torch.Generator().manual_seed(3))
    for tilt in (12.0, -20.0):
        g = Gaussians.on_rays(500, weights, camera, thin, 0.2, 0.3, torch.Generator().manual_seed(3), tilt)
        p = g["means"].detach().double()
        t = np.radians(tilt)
        normal = torch.tensor([0.0, np.sin(t), np.cos(t)], dtype=torch.float64)
        assert torch.allclose(p @ normal, torch.full((500,), 2.0 * np.cos(t), dtype=torch.float64), atol=1e-6)
        q = flat["means"].detach().double()  # the same rays (pixels) as the untilted seeding
        assert torch.allclose(p[:, :2] / p[:, 2:], q[:, :2] / q[:, 2:], atol=1e-6)
        bottom = p[:, 1] / p[:, 2] > 0.1
        assert bool((p[bottom, 2] < 2.0).all() if tilt > 0 else (p[bottom, 2] > 2.0).all())


def test_on_rays_rejects_a_tilt_that_puts_the_plane_behind_some_rows():
    camera = Camera(width=40, height=30, fx=50.0, fy=45.0, cx=19.5, cy=14.5)  # rows reach ±18.4° up/down
    with pytest.raises(ValueError, match="init_tilt_deg = 75"):
        Gaussians.on_rays(10, torch.ones(30, 40), camera, (1.0, 2.0), 0.1, 0.1, torch.Generator(), 75.0)


def test_on_rays_rejects_an_empty_activity_map_and_bad_depths():
    camera = Camera(width=4, height=3, fx=5.0, fy=5.0, cx=1.5, cy=1.0)
    gen = torch.Generator().manual_seed(0)
    with pytest.raises(ValueError, match="no pixel with events"):
        Gaussians.on_rays(10, torch.zeros(3, 4), camera, (1.0, 2.0), 0.1, 0.1, gen)
    with pytest.raises(ValueError, match="must be positive"):
        Gaussians.on_rays(10, torch.ones(3, 4), camera, (-1.0, 2.0), 0.1, 0.1, gen)


def test_optimizer_groups_are_named_with_scaled_means_lr():
    cfg = load_config().gaussians
    g = small()
    opt = make_optimizer(g, cfg, scene_scale=2.0)
    lrs = {grp["name"]: grp["lr"] for grp in opt.param_groups}
    assert lrs["means"] == pytest.approx(cfg.means_lr * 2.0) and lrs["colors"] == cfg.colors_lr
    assert opt.defaults["eps"] == cfg.adam_eps


def test_quat_to_rotmat_matches_scipy():
    q = torch.randn(20, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()  # scipy: (x, y, z, w)
    assert np.allclose(quat_to_rotmat(q).numpy(), ref, atol=1e-12)


def test_ply_round_trip_and_layout(tmp_path: Path):
    g = small()
    path = tmp_path / "out" / "gaussians.ply"
    save_ply(path, g)
    back = load_ply(path)
    for k in PARAM_NAMES:
        assert torch.allclose(back[k], g[k], atol=1e-6), k
    data = path.read_bytes()
    header = data[: data.index(b"end_header\n")].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert props[:10] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    assert props[10:] == ["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert "binary_little_endian 1.0" in header and f"element vertex {len(g)}" in header
    rec = np.frombuffer(data[len(header) + len("end_header\n") :], dtype=[(p, "<f4") for p in props])
    assert np.allclose(0.5 + SH_C0 * rec["f_dc_1"], g["colors"].detach().numpy()[:, 0], atol=1e-6)
    assert np.allclose(rec["rot_0"], g["quats"].detach().numpy()[:, 0])  # w first
    assert not list(tmp_path.glob("out/.*"))  # no temporary left behind


def test_ply_reader_accepts_other_property_orders_and_types(tmp_path: Path):
    n = 3
    props = [("rot_0", "<f4"), ("rot_1", "<f4"), ("rot_2", "<f4"), ("rot_3", "<f4"), ("x", "<f8")]
    props += [("y", "<f8"), ("z", "<f8"), ("f_dc_0", "<f4"), ("f_dc_1", "<f4"), ("f_dc_2", "<f4")]
    props += [("f_rest_0", "<f4"), ("opacity", "<f4"), ("scale_0", "<f4"), ("scale_1", "<f4")]
    props += [("scale_2", "<f4"), ("red", "u1")]
    rec = np.zeros(n, dtype=props)
    rec["x"] = [1, 2, 3]
    rec["rot_0"] = 1
    rec["f_dc_0"], rec["f_dc_1"], rec["f_dc_2"] = 0.0, 1.0, 2.0
    names = {"<f4": "float", "<f8": "double", "u1": "uchar"}
    header = "ply\nformat binary_little_endian 1.0\ncomment made by a test\n"
    header += f"element vertex {n}\n" + "".join(f"property {names[t]} {p}\n" for p, t in props)
    header += "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    path = tmp_path / "other.ply"
    path.write_bytes(header.encode() + rec.tobytes())
    g = load_ply(path)
    assert torch.equal(g["means"][:, 0], torch.tensor([1.0, 2, 3]))
    assert torch.allclose(g["colors"], torch.full((3, 1), 0.5 + SH_C0))  # gray = mean of the channels


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        (b"hello", "not a PLY file"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n",
            "line 2: unsupported format",
        ),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n", "lacks"),
    ],
)
def test_ply_reader_errors_name_the_position(tmp_path: Path, body: bytes, needle: str):
    path = tmp_path / "bad.ply"
    path.write_bytes(body)
    with pytest.raises(ValueError, match=needle) as e:
        load_ply(path)
    assert str(path) in str(e.value)


def test_ply_truncated(tmp_path: Path):
    path = tmp_path / "t.ply"
    save_ply(path, small(10))
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(ValueError, match="truncated"):
        load_ply(path)


def test_shape_validation():
    with pytest.raises(ValueError, match="colors has shape"):
        Gaussians(torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(2, 4), torch.zeros(2), torch.zeros(2, 3))

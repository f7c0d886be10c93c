"""``evgs import``: frame selection across every output, replacing an existing import, bad arguments."""

import numpy as np
import polars as pl
import pytest
from evgs.data.importers import parse_frames
from evgs.data.sequence import Sequence
from import_helpers import run_import
from test_import_elope import descent_poses, write_elope


def test_frames_crop_every_output(tmp_path):
    T_wc = descent_poses(10)
    events, ts, arrays = write_elope(tmp_path / "0013.npz", np.random.default_rng(60), T_wc)
    assert run_import("elope", tmp_path / "0013.npz", "--out", tmp_path / "o", "--frames", "2:7") == 0
    seq = Sequence.load(tmp_path / "o")
    t_us = np.round(ts * 1e6).astype(np.int64)
    np.testing.assert_array_equal(seq.frames_us(), t_us[2:7])
    keep = (events["t"] >= t_us[2]) & (events["t"] <= t_us[6])
    np.testing.assert_array_equal(seq.events().t, events["t"][keep])
    t_pose, T = seq.poses_gt()
    np.testing.assert_array_equal(t_pose, t_us[2:7])
    np.testing.assert_allclose(T[:, :3, 3], T_wc[2:7, :3, 3], atol=1e-9)
    np.testing.assert_array_equal(seq.range_samples()[0], t_us[2:7])
    np.testing.assert_array_equal(
        pl.read_csv(tmp_path / "o" / "velocities_gt.csv")["t_us"].to_numpy(), t_us[2:7]
    )
    assert seq.meta["frame_offset"] == 2


def test_reimport_replaces_and_failure_keeps_previous(tmp_path):
    write_elope(tmp_path / "a.npz", np.random.default_rng(61), descent_poses(6))
    out = tmp_path / "data" / "elope" / "a"
    assert run_import("elope", tmp_path / "a.npz", "--out", out, "--frames", "0:4") == 0
    assert run_import("elope", tmp_path / "a.npz", "--out", out) == 0
    assert len(Sequence.load(out).frames_us()) == 6
    (tmp_path / "a.npz").write_bytes(b"not an npz")
    assert run_import("elope", tmp_path / "a.npz", "--out", out) == 2
    assert len(Sequence.load(out).frames_us()) == 6  # the previous import is untouched
    assert sorted(p.name for p in out.parent.iterdir()) == ["a"]


def test_default_output_folder(tmp_path, monkeypatch):
    write_elope(tmp_path / "0016.npz", np.random.default_rng(62), descent_poses(4))
    monkeypatch.chdir(tmp_path)
    assert run_import("elope", "0016.npz") == 0
    assert Sequence.load(tmp_path / "data" / "elope" / "0016").name == "0016"


@pytest.mark.parametrize(("spec", "expected"), [("3:8", (3, 8)), (":5", (None, 5)), ("10:", (10, None))])
def test_parse_frames(spec, expected):
    assert parse_frames(spec) == expected


@pytest.mark.parametrize("spec", ["3", "a:b", "1:2:3"])
def test_bad_frames(tmp_path, capsys, spec):
    write_elope(tmp_path / "a.npz", np.random.default_rng(63), descent_poses(4))
    assert run_import("elope", tmp_path / "a.npz", "--out", tmp_path / "o", "--frames", spec) == 2
    assert "expected A:B" in capsys.readouterr().err
    assert run_import("elope", tmp_path / "a.npz", "--out", tmp_path / "o", "--frames", "3:4") == 2
    assert "selects 1 of 4 frames" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()

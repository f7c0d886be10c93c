"""E-M-S adapter on fixtures written in E-M-S's own layout (per-frame CSVs, r1..r9 pose files)."""

import cv2
import numpy as np
import pytest
from evgs.data.ems import detect_time_unit
from evgs.data.sequence import Sequence
from evgs.geometry import invert_pose
from import_helpers import assert_projects_as_truth, orbit_poses, random_events, run_import

N_FRAMES = 8
INTRINSICS = "500,500,320,240"
FRAME_US = 33_333


def write_ems(split, rng, *, unit: str, polarity: str, empty_first: bool = False, direction: str = "w2c"):
    """An E-M-S split folder for one sequence; returns (events with p ±1, per-frame counts, frame µs, c2w)."""
    ev_dir, pose_dir, img_dir = (
        split / "Event" / "event_stream",
        split / "Event" / "pose",
        split / "RGB" / "img",
    )
    for d in (ev_dir, pose_dir, img_dir):
        d.mkdir(parents=True)
    T_wc = orbit_poses(N_FRAMES)
    stored = invert_pose(T_wc) if direction == "w2c" else T_wc
    all_ev, counts, ends = [], [], []
    for i in range(N_FRAMES):
        start, end = 500_000 + i * FRAME_US + 1, 500_000 + (i + 1) * FRAME_US
        n = 0 if (empty_first and i == 0) else int(rng.integers(50, 300))
        ev = random_events(rng, n, start, end, 640, 480)
        if n:
            ev["t"][-1] = end  # the frame's last event sits on the boundary
        counts.append(n)
        ends.append(end)
        all_ev.append(ev)
        t_txt = [f"{t / 1e6:.6f}" for t in ev["t"]] if unit == "s" else [str(t) for t in ev["t"]]
        pol = ev["p"] if polarity == "pm1" else (ev["p"] > 0).astype(int)
        body = [f"{t},{x},{y},{p}" for t, x, y, p in zip(t_txt, ev["x"], ev["y"], pol, strict=True)]
        (ev_dir / f"{i}.csv").write_text("\n".join(["timestamp,x,y,polarity", *body]) + "\n")
        R, t = stored[i, :3, :3], stored[i, :3, 3]
        (pose_dir / f"{i}.txt").write_text(" ".join(f"{v:.12g}" for v in [*R.ravel(), *t]) + "\n")
        cv2.imwrite(str(img_dir / f"{i}.jpg"), np.full((480, 640, 3), 20 * i, np.uint8))
    events = {c: np.concatenate([e[c] for e in all_ev]) for c in "txyp"}
    return events, np.array(counts), np.array(ends), T_wc


@pytest.mark.parametrize(("unit", "polarity"), [("s", "01"), ("us", "pm1")])
def test_ems_import(tmp_path, unit, polarity):
    ev, counts, ends, T_wc = write_ems(
        tmp_path / "testing", np.random.default_rng(20), unit=unit, polarity=polarity
    )
    out = tmp_path / "out"
    assert run_import("ems", tmp_path / "testing", "--intrinsics", INTRINSICS, "--out", out) == 0
    seq = Sequence.load(out)
    assert seq.meta["time_unit"] == unit
    assert (seq.camera.fx, seq.camera.cx, seq.camera.width) == (500.0, 320.0, 640)
    got = seq.events()
    assert len(got) == counts.sum()
    np.testing.assert_array_equal(got.t, ev["t"])
    np.testing.assert_array_equal(got.p, ev["p"])
    frames = seq.frames_us()
    np.testing.assert_array_equal(frames, ends)
    # The events of frame i are exactly those after frame i−1 up to frame i.
    per_frame = np.diff(np.searchsorted(got.t, frames, side="right"), prepend=0)
    np.testing.assert_array_equal(per_frame, counts)
    assert_projects_as_truth(seq, T_wc, ends)
    assert seq.image(3) is not None and abs(float(seq.image(3).mean()) - 60 / 255) < 0.01


def test_ems_empty_frame_interpolated_and_c2w(tmp_path, capsys):
    ev, counts, ends, T_wc = write_ems(
        tmp_path / "Event_split",
        np.random.default_rng(21),
        unit="s",
        polarity="01",
        empty_first=True,
        direction="c2w",
    )
    out = tmp_path / "out"
    argv = ["ems", tmp_path / "Event_split" / "Event", "--intrinsics", INTRINSICS, "--out", out]
    assert run_import(*argv, "--pose-direction", "c2w", "--no-images") == 0
    assert "1 event CSVs hold no events (0.csv)" in capsys.readouterr().err
    seq = Sequence.load(out)
    np.testing.assert_array_equal(seq.frames_us(), ends)  # frame 0 extrapolated from the regular spacing
    assert len(seq.events()) == counts.sum() and seq.image(0) is None
    assert_projects_as_truth(seq, T_wc, ends)


@pytest.mark.parametrize(
    ("firsts", "unit"),
    [(["0.0333", "0.0666"], "s"), (["33", "66", "100"], "ms"), (["33333", "66666"], "us"),
     (["33333333", "66666666"], "ns"), (["1e-3", "2e-3"], "s")],
)  # fmt: skip
def test_ems_time_unit_from_magnitudes(tmp_path, firsts, unit):
    files = []
    for i, t in enumerate(firsts):
        files.append(tmp_path / f"{i}.csv")
        files[-1].write_text(f"timestamp,x,y,polarity\n{t},1,2,0\n{t},3,4,1\n")
    assert detect_time_unit(files) == unit


def test_ems_errors(tmp_path, capsys):
    write_ems(tmp_path / "s", np.random.default_rng(22), unit="us", polarity="01")
    (tmp_path / "s" / "Event" / "pose" / "5.txt").write_text("1 0 0 0 1 0 0 0 1 0 0\n")
    assert run_import("ems", tmp_path / "s", "--intrinsics", INTRINSICS, "--out", tmp_path / "o") == 2
    assert "5.txt: expected 12 numbers (r1..r9 tx ty tz), found 11" in capsys.readouterr().err
    (tmp_path / "s" / "Event" / "pose" / "5.txt").unlink()
    assert run_import("ems", tmp_path / "s", "--intrinsics", INTRINSICS, "--out", tmp_path / "o") == 2
    assert "no pose file for frame 5" in capsys.readouterr().err
    assert run_import("ems", tmp_path / "nowhere", "--intrinsics", INTRINSICS) == 2
    assert "event_stream: folder not found" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_ems_sequence_selection(tmp_path):
    """Several sequences in one folder, files named <seq>_<frame>: --sequence picks one."""
    split = tmp_path / "training"
    ev, counts, ends, T_wc = write_ems(split, np.random.default_rng(23), unit="s", polarity="01")
    for sub, ext in (("Event/event_stream", "csv"), ("Event/pose", "txt"), ("RGB/img", "jpg")):
        for f in (split / sub).glob(f"*.{ext}"):
            f.rename(f.with_name(f"69_{f.name}"))
            (split / sub / f"70_{f.name}").write_bytes(b"other sequence, must not be read")
    out = tmp_path / "o"
    assert run_import("ems", split, "--sequence", "69", "--intrinsics", INTRINSICS, "--out", out) == 0
    seq = Sequence.load(out)
    assert seq.name == "69"
    np.testing.assert_array_equal(seq.events().t, ev["t"])
    np.testing.assert_array_equal(seq.frames_us(), ends)
    assert_projects_as_truth(seq, T_wc, ends)

"""Chunks, the §3.1 window sampler and event frames (evgs.events.frames) against plain numpy / OpenCV."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from evgs.data.sequence import Camera
from evgs.events.arrays import EventArray
from evgs.events.frames import UndistortMap, WindowSampler, accumulate, chunk_ranges
from hypothesis import given, settings
from hypothesis import strategies as st

CAMERA = Camera(96, 64, 80.0, 82.0, 47.3, 31.8, (-0.3, 0.12, 1.5e-3, -8e-4, -0.02))


def random_events(n: int, width: int, height: int, seed: int) -> EventArray:
    rng = np.random.default_rng(seed)
    return EventArray(
        t=np.sort(rng.integers(0, 10 * n, n)).astype(np.int64),
        x=rng.integers(0, width, n).astype(np.uint16),
        y=rng.integers(0, height, n).astype(np.uint16),
        p=rng.choice(np.array([-1, 1], np.int8), n, p=[0.4, 0.6]),
        width=width,
        height=height,
    )


def add_at_frames(ev: EventArray, starts, ends, c_on: float, c_off: float, f: int = 1) -> np.ndarray:
    """Reference: per-window integer counts with np.add.at, then float32 C_on·n_on − C_off·n_off."""
    h, w = -(-ev.height // f), -(-ev.width // f)
    out = np.zeros((len(starts), h, w), np.float32)
    for b, (s, e) in enumerate(zip(starts, ends, strict=True)):
        on, off = np.zeros(h * w, np.int64), np.zeros(h * w, np.int64)
        idx = (ev.y[s:e].astype(np.int64) // f) * w + ev.x[s:e] // f
        pos = ev.p[s:e] > 0
        np.add.at(on, idx[pos], 1)
        np.add.at(off, idx[~pos], 1)
        if c_on == c_off:  # one C: the frame is C·Σp rounded once
            frame = np.float32(c_on) * (on - off).astype(np.float32)
        else:
            frame = np.float32(c_on) * on.astype(np.float32) - np.float32(c_off) * off.astype(np.float32)
        out[b] = frame.reshape(h, w)
    return out


# --- chunk index -------------------------------------------------------------------------------------


def test_chunk_ranges_are_half_open_and_match_searchsorted():
    ev = random_events(5000, 8, 8, 0)
    frame_t = np.array([-3, 0, 777, int(ev.t[1234]), int(ev.t[1234]) + 1, 30_000, 60_000])
    ranges = chunk_ranges(ev.t, frame_t)
    assert ranges.shape == (len(frame_t) - 1, 2) and ranges.dtype == np.int64
    b = np.searchsorted(ev.t, frame_t, side="left")
    np.testing.assert_array_equal(ranges, np.stack([b[:-1], b[1:]], axis=1))
    for k, (s, e) in enumerate(ranges):
        assert np.all((frame_t[k] <= ev.t[s:e]) & (ev.t[s:e] < frame_t[k + 1]))
    # An event exactly on a frame timestamp opens the chunk that starts there.
    assert ranges[3, 0] <= 1234 and ev.t[ranges[3, 0]] == ev.t[1234]


def test_chunk_ranges_rejects_unsorted_input():
    with pytest.raises(ValueError, match="strictly increasing"):
        chunk_ranges(np.arange(5), [0, 2, 2])
    with pytest.raises(ValueError, match=r"event 2 \(0 µs\) < event 1"):
        chunk_ranges(np.array([0, 5, 0]), [0, 2])
    with pytest.raises(ValueError, match="at least 2"):
        chunk_ranges(np.arange(5), [0])


# --- window sampler ----------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(
    start=st.integers(0, 1000),
    n=st.integers(1, 5000),
    min_w=st.integers(1, 3000),
    extra=st.integers(0, 3000),
    seed=st.integers(0, 2**64 - 1),
)
def test_paper_windows_always_valid(start, n, min_w, extra, seed):
    max_w = min_w + extra
    if min_w > n:
        with pytest.raises(
            ValueError, match=f"min_n_winsize = {min_w} events cannot be met: only {n} events"
        ):
            WindowSampler((start, start + n), min_w, max_w, seed)
        return
    sampler = WindowSampler((start, start + n), min_w, max_w, seed)
    eff_max = min(max_w, n)
    assert sampler.sizes == (min_w, eff_max)
    s, e = sampler.sample(64)
    assert s.dtype == e.dtype == np.int64 and s.shape == (64,)
    assert np.all((s >= start) & (e <= start + n) & (e >= start + eff_max))
    assert np.all((e - s >= min_w) & (e - s <= eff_max))


def test_paper_edge_cases():
    # max > N clamps: every window ends at the last event.
    s, e = WindowSampler(50, 5, 10_000, seed=1).sample(100)
    assert np.all(e == 50) and np.all(e - s >= 5)
    # min == max: fixed length; N tiny: the one window there is.
    s, e = WindowSampler(1000, 64, 64, seed=1).sample(100)
    assert np.all(e - s == 64)
    s, e = WindowSampler((7, 8), 1, 1, seed=1).sample(3)
    assert s.tolist() == [7, 7, 7] and e.tolist() == [8, 8, 8]
    # Empty range / min > N: a clear error, not a hang.
    with pytest.raises(ValueError, match=r"only 0 events in events \[5, 5\)"):
        WindowSampler((5, 5), 1, 10, seed=1)
    with pytest.raises(ValueError, match=r"min_n_winsize = 31 events cannot be met: only 30 events"):
        WindowSampler((10, 40), 31, 100, seed=1)
    with pytest.raises(ValueError, match="larger than max_n_winsize"):
        WindowSampler(100, 20, 10, seed=1)
    with pytest.raises(ValueError, match="reversed"):
        WindowSampler((9, 3), 1, 2, seed=1)
    with pytest.raises(ValueError, match="mode must be"):
        WindowSampler(100, 1, 2, seed=1, mode="time")  # type: ignore[arg-type]


def test_paper_windows_are_uniform():
    s, e = WindowSampler(1000, 10, 109, seed=3).sample(100_000)
    # end ~ U{109..1000}, w ~ U{10..109}: both means within 6 standard errors.
    assert abs((e.mean() - (109 + 1000) / 2) / (np.sqrt((892**2 - 1) / 12) / np.sqrt(1e5))) < 6
    w = e - s
    assert abs((w.mean() - 59.5) / (np.sqrt((100**2 - 1) / 12) / np.sqrt(1e5))) < 6
    assert w.min() == 10 and w.max() == 109


def test_seeded_reproducibility():
    a = WindowSampler(10_000, 5, 500, seed=42)
    b = WindowSampler(10_000, 5, 500, seed=42)
    for _ in range(3):
        sa, sb = a.sample(32), b.sample(32)
        np.testing.assert_array_equal(sa[0], sb[0])
        np.testing.assert_array_equal(sa[1], sb[1])
    assert not np.array_equal(WindowSampler(10_000, 5, 500, seed=43).sample(32)[0], sa[0])


def test_reference_mode_follows_linspace():
    n, lo, min_w, max_w, seg = 5000, 200, 20, 400, 37
    sampler = WindowSampler((lo, lo + n), min_w, max_w, seed=7, mode="reference", seg_num=seg)
    cand = np.linspace(10, n - 10, seg).astype(np.int64)
    cand = cand[cand > max_w]
    for _ in range(20):
        s, e = sampler.sample(len(cand))
        np.testing.assert_array_equal(np.sort(e - lo), np.sort(cand))  # distinct candidates, all of them
        assert np.all((e - s >= min_w) & (e - s < max_w))
    with pytest.raises(ValueError, match=f"only {len(cand)} distinct candidate ends"):
        sampler.sample(len(cand) + 1)
    with pytest.raises(ValueError, match="no candidate end"):
        WindowSampler(100, 5, 95, seed=0, mode="reference", seg_num=4)


# --- event frames ------------------------------------------------------------------------------------


@pytest.mark.parametrize("f", [1, 2, 4])
def test_accumulate_matches_np_add_at(f):
    ev = random_events(60_000, 45, 31, 1)
    starts, ends = WindowSampler(len(ev), 1, 20_000, seed=5).sample(6)
    # whole stream, a small window, an empty one
    starts, ends = np.append(starts, [0, 500, 17]), np.append(ends, [len(ev), 600, 17])
    frames = accumulate(ev, starts, ends, c_on=0.3, c_off=0.1, downsample=f)
    assert frames.dtype == np.float32 and frames.shape == (9, -(-31 // f), -(-45 // f))
    np.testing.assert_array_equal(frames, add_at_frames(ev, starts, ends, 0.3, 0.1, f))
    assert np.all(frames[-1] == 0)
    # c_off defaults to c_on: the paper's single symmetric C.
    sym = accumulate(ev, starts[:2], ends[:2], c_on=0.2, downsample=f)
    np.testing.assert_array_equal(sym, add_at_frames(ev, starts[:2], ends[:2], 0.2, 0.2, f))


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(0, 3000),
    width=st.integers(1, 40),
    height=st.integers(1, 40),
    f=st.sampled_from([1, 2, 4]),
    c=st.sampled_from([(0.1, 0.1), (1.0, 1.0), (0.3, 0.05), (0.0, 2.5)]),
    seed=st.integers(0, 2**32 - 1),
)
def test_accumulate_property(n, width, height, f, c, seed):
    ev = random_events(n, width, height, seed)
    rng = np.random.default_rng(seed)
    bounds = np.sort(rng.integers(0, n + 1, (5, 2)), axis=1)
    starts, ends = bounds[:, 0], bounds[:, 1]
    got = accumulate(ev, starts, ends, c_on=c[0], c_off=c[1], downsample=f)
    np.testing.assert_array_equal(got, add_at_frames(ev, starts, ends, c[0], c[1], f))


def test_sampling_a_sliding_window_of_chunks():
    ev = random_events(20_000, 8, 8, 6)
    ranges = chunk_ranges(ev.t, np.linspace(0, ev.t[-1], 11).astype(np.int64))
    lo, hi = ranges[3, 0], ranges[6, 1]  # chunks 3..6
    s, e = WindowSampler((lo, hi), 100, 1500, seed=2).sample(500)
    assert np.all((s >= lo) & (e <= hi) & (e - s >= 100) & (e - s <= 1500))
    assert np.all(ev.t[s] >= np.linspace(0, ev.t[-1], 11).astype(np.int64)[3])


def test_accumulate_rejects_bad_input():
    ev = random_events(100, 8, 8, 2)
    with pytest.raises(ValueError, match=r"window 1 = \[50, 101\) is not inside \[0, 100\)"):
        accumulate(ev, [0, 50], [10, 101])
    with pytest.raises(ValueError, match="is negative"):
        accumulate(ev, [-1], [10])
    with pytest.raises(ValueError, match="1 window starts but 2 ends"):
        accumulate(ev, [0], [10, 20])
    with pytest.raises(ValueError, match="power of two"):
        accumulate(ev, [0], [10], downsample=3)
    bad = EventArray(ev.t, ev.x.copy(), ev.y, ev.p, 8, 8)
    bad.x[42] = 8
    with pytest.raises(ValueError, match=r"event 42 at \(8, \d+\) is outside the 8x8 sensor"):
        accumulate(bad, [40], [50])
    with pytest.raises(ValueError, match="sensor size is unknown"):
        accumulate(EventArray(ev.t, ev.x, ev.y, ev.p), [0], [10])
    with pytest.raises(ValueError, match="undistortion map is 96x64"):
        accumulate(ev, [0], [10], undistort=UndistortMap.from_camera(CAMERA))


# --- undistortion ------------------------------------------------------------------------------------


def test_undistort_map_matches_cv2_undistort_points():
    umap = UndistortMap.from_camera(CAMERA)
    assert umap.uv.shape == (64, 96, 2) and umap.uv.dtype == np.float32 and umap.n_invalid == 0
    ys, xs = np.mgrid[0:64, 0:96]
    pts = np.stack([xs, ys], axis=-1).reshape(-1, 1, 2).astype(np.float64)
    K, dist = CAMERA.K, np.array(CAMERA.distortion)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    ref = cv2.undistortPoints(pts, K, dist, P=K, criteria=criteria).reshape(64, 96, 2)
    np.testing.assert_allclose(umap.uv, ref, atol=2e-3)
    # And the map inverts cv2's forward model: projecting the undistorted rays lands on the pixel centres.
    rays = np.concatenate(
        [(umap.uv - [CAMERA.cx, CAMERA.cy]) / [CAMERA.fx, CAMERA.fy], np.ones((64, 96, 1))], -1
    )
    proj, _ = cv2.projectPoints(rays.reshape(-1, 3), np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(proj.reshape(64, 96, 2), pts.reshape(64, 96, 2), atol=1e-3)


def test_undistort_map_without_distortion_is_identity():
    cam = Camera(20, 10, 30.0, 30.0, 9.5, 4.5)
    ys, xs = np.mgrid[0:10, 0:20]
    np.testing.assert_allclose(UndistortMap.from_camera(cam).uv, np.stack([xs, ys], -1), atol=1e-4)


def bilinear_reference(ev: EventArray, s: int, e: int, uv: np.ndarray, c_on: float, c_off: float):
    """Per-event float64 bilinear splat with np.add.at; returns (frame, dropped)."""
    h, w = ev.height, ev.width
    pos = uv[ev.y[s:e], ev.x[s:e]].astype(np.float64)
    val = np.where(ev.p[s:e] > 0, c_on, -c_off)
    inside = (pos[:, 0] >= -0.5) & (pos[:, 0] < w - 0.5) & (pos[:, 1] >= -0.5) & (pos[:, 1] < h - 0.5)
    u, v = np.clip(pos[inside, 0], 0, w - 1), np.clip(pos[inside, 1], 0, h - 1)
    x0, y0 = np.floor(u).astype(int), np.floor(v).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ax, ay, val = u - x0, v - y0, val[inside]
    out = np.zeros((h, w))
    for yy, xx, wt in (
        (y0, x0, (1 - ax) * (1 - ay)),
        (y0, x1, ax * (1 - ay)),
        (y1, x0, (1 - ax) * ay),
        (y1, x1, ax * ay),
    ):
        np.add.at(out, (yy, xx), val * wt)
    return out, int((~inside).sum())


def test_undistorted_frames_match_a_bilinear_splat_and_count_dropped_events():
    ev = random_events(40_000, CAMERA.width, CAMERA.height, 3)
    umap = UndistortMap.from_camera(CAMERA)
    starts, ends = np.array([0, 1000]), np.array([40_000, 9000])
    frames, dropped = accumulate(ev, starts, ends, c_on=0.25, c_off=0.15, undistort=umap, return_dropped=True)
    for b in range(2):
        ref, n_out = bilinear_reference(ev, starts[b], ends[b], umap.uv, 0.25, 0.15)
        np.testing.assert_allclose(frames[b], ref, atol=1e-4)
        assert dropped[b] == n_out
    # Barrel distortion (k1 < 0) pulls corner pixels outwards: some events leave the image, none silently.
    assert dropped[0] > 0
    # Downsampled undistorted frames keep the same total mass.
    coarse = accumulate(ev, starts, ends, c_on=0.25, c_off=0.15, undistort=umap, downsample=2)
    assert coarse.shape == (2, 32, 48)
    np.testing.assert_allclose(coarse.sum(axis=(1, 2)), frames.sum(axis=(1, 2)), rtol=1e-4)


# --- determinism across thread counts ----------------------------------------------------------------

_DETERMINISM_SCRIPT = """
import hashlib, sys
import numpy as np
from evgs.data.sequence import Camera
from evgs.events.arrays import EventArray
from evgs.events.frames import UndistortMap, WindowSampler, accumulate

rng = np.random.default_rng(0)
n = 2_500_000
ev = EventArray(np.arange(n, dtype=np.int64), rng.integers(0, 64, n).astype(np.uint16),
                rng.integers(0, 48, n).astype(np.uint16), rng.choice(np.array([-1, 1], np.int8), n), 64, 48)
# 3 windows of > 1 M events: one thread counts each whole, two threads split them into parts.
s, e = WindowSampler(n, 1_100_000, 2_400_000, seed=11).sample(3)
cam = Camera(64, 48, 60.0, 60.0, 31.5, 23.5, (-0.25, 0.05, 0.0, 0.0, 0.0))
h = hashlib.sha256()
for arr in (s, e, accumulate(ev, s, e, c_on=0.3, c_off=0.2),
            accumulate(ev, s, e, c_on=0.3, undistort=UndistortMap.from_camera(cam), downsample=2)):
    h.update(np.ascontiguousarray(arr).tobytes())
print(h.hexdigest())
"""


def test_results_identical_for_one_and_two_threads():
    python_dir = str(Path(__file__).resolve().parents[1] / "python")
    digests = []
    for threads in ("1", "2"):
        env = {**os.environ, "RAYON_NUM_THREADS": threads}
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [python_dir, env.get("PYTHONPATH")]))
        out = subprocess.run(
            [sys.executable, "-c", _DETERMINISM_SCRIPT], env=env, capture_output=True, text=True, check=True
        )
        digests.append(out.stdout.strip())
    assert len(digests[0]) == 64 and digests[0] == digests[1]
    assert hashlib.sha256(b"").hexdigest() not in digests


def test_out_buffer_is_overwritten_and_returned():
    ev = random_events(30_000, 40, 30, 4)
    starts, ends = np.array([0, 100, 29_000]), np.array([30_000, 130, 29_010])
    out = np.full((3, 15, 20), np.nan, np.float32)
    got = accumulate(ev, starts, ends, c_on=0.5, downsample=2, out=out)
    assert got is out
    np.testing.assert_array_equal(out, add_at_frames(ev, starts, ends, 0.5, 0.5, 2))
    with pytest.raises(ValueError, match=r"shape \(3, 15, 20\)"):
        accumulate(ev, starts, ends, out=np.zeros((3, 30, 40), np.float32), downsample=2)

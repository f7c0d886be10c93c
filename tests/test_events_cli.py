"""``evgs events info|convert|slice|demo`` on small files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from evgs.cli import main
from evgs.events.io import read_events, write_events
from evgs.events.synthetic import synthetic_events


def run(capsys, *argv: str) -> str:
    assert main(list(argv)) == 0
    return capsys.readouterr().out


def test_info_reports_every_field(tmp_path: Path, capsys) -> None:
    ev = synthetic_events(3000, width=64, height=48, seed=5)
    write_events(tmp_path / "e.raw", ev, "evt2")
    out = run(capsys, "events", "info", str(tmp_path / "e.raw"), "--batch", "1000")
    on = int(np.count_nonzero(ev.p > 0))
    assert "format:    evt2" in out and "events:    3000" in out and "sensor:    64x48" in out
    assert f"time:      {ev.t[0]} .. {ev.t[-1]} us" in out
    assert f"polarity:  on {on} ({100 * on / 3000:.1f}%), off {3000 - on}" in out
    assert "sorted:    yes" in out and "rate:" in out
    (tmp_path / "s.csv").write_text("t,x,y,p\n0.5,1,2,0\n")
    out = run(capsys, "events", "info", str(tmp_path / "s.csv"))
    assert "text (delimiter ',', header yes, columns txyp, time unit s)" in out
    assert "sensor:    unknown (max x 1, max y 2)" in out


def test_convert_time_range_and_roi_counts(tmp_path: Path, capsys) -> None:
    ev = synthetic_events(10_000, width=100, height=80, seed=6)
    write_events(tmp_path / "e.npy", ev)
    t0, t1 = ev.t[2000] / 1e6, ev.t[7000] / 1e6
    out = run(
        capsys, "events", "convert", str(tmp_path / "e.npy"), str(tmp_path / "o.h5"),
        "--t0", str(t0), "--t1", str(t1), "--roi", "10", "20", "60", "70", "--width", "100", "--height", "80",
        "--batch", "999",
    )  # fmt: skip
    in_t = (ev.t >= round(t0 * 1e6)) & (ev.t < round(t1 * 1e6))
    in_roi = (ev.x >= 10) & (ev.x < 60) & (ev.y >= 20) & (ev.y < 70)
    got = read_events(tmp_path / "o.h5")
    assert len(got) == int(np.count_nonzero(in_t & in_roi))
    np.testing.assert_array_equal(got.x, ev.x[in_t & in_roi] - 10)
    assert (got.width, got.height) == (50, 50)
    assert f"{np.count_nonzero(~in_t)} outside the time range" in out
    assert f"{np.count_nonzero(in_t & ~in_roi)} outside the roi" in out


def test_slice_by_index_and_format_choice(tmp_path: Path, capsys) -> None:
    ev = synthetic_events(5000, seed=7)
    write_events(tmp_path / "e.parquet", ev)
    out = run(
        capsys, "events", "slice", str(tmp_path / "e.parquet"), str(tmp_path / "o.raw"), "--start", "100",
        "--stop", "4100", "--to", "evt2", "--batch", "777",
    )  # fmt: skip
    assert "wrote 4000 events (evt2)" in out and "1000 outside the index range" in out
    got = read_events(tmp_path / "o.raw")
    np.testing.assert_array_equal(got.t, ev.t[100:4100])


def test_demo_round_trips_every_format(tmp_path: Path, capsys) -> None:
    out = run(capsys, "events", "demo", "--out", str(tmp_path), "--events", "20000")
    assert "MISMATCH" not in out and out.count(" ok ") == 16
    for name in ("events.parquet", "events.csv", "events.txt", "events.npy", "events.h5", "events.aedat4"):
        assert (tmp_path / name).exists() and f"file:      {tmp_path / name}" in out

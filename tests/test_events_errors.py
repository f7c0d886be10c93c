"""Bad input: each error names the file and the line / byte offset / event index, the CLI exits 2
and leaves no output file behind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from evgs.cli import main
from evgs.events.arrays import EventArray
from evgs.events.io import EventWriter, read_events, write_events
from evgs.events.synthetic import synthetic_events


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


TEXT_CASES = [
    ("columns.csv", "t,x,y,p\n1,1,1,1\n2,1,1\n", [], r"line 3: expected 4 columns, found 3"),
    ("nan.csv", "1,1,1,1\nnan,1,1,1\n", [], r"line 2: time \"nan\": not a finite number"),
    ("inf.txt", "0.5 1 1 1\ninf 1 1 1\n", [], r"line 2: time \"inf\": not a finite number"),
    ("number.csv", "1,1,1,1\n2,1,1x,1\n", [], r"line 2: coordinate \"1x\": not a number"),
    ("order.csv", "t,x,y,p\n5,1,1,1\n4,1,1,1\n", [], r"line 3: time goes backwards"),
    (
        "sensor.csv",
        "1,1,1,1\n2,1,9,1\n",
        ["--width", "4", "--height", "4"],
        r"line 2: .*outside the 4x4 sensor",
    ),
]


@pytest.mark.parametrize(("name", "text", "extra", "pattern"), TEXT_CASES)
def test_text_errors_name_line_and_cli_leaves_nothing(
    tmp_path: Path, capsys, name, text, extra, pattern
) -> None:
    src = tmp_path / name
    src.write_text(text)
    out = tmp_path / "out.parquet"
    code, _, err = run_cli(capsys, "events", "convert", str(src), str(out), *extra)
    assert code == 2
    assert err.startswith(f"evgs: error: {src}: line ")
    assert __import__("re").search(pattern, err), err
    assert not out.exists() and list(tmp_path.iterdir()) == [src]


def test_unsorted_allowed_when_asked_and_info_reports_it(tmp_path: Path, capsys) -> None:
    src = tmp_path / "order.csv"
    src.write_text("5,1,1,1\n4,1,1,1\n6,1,1,1\n")
    code, out, _ = run_cli(capsys, "events", "info", str(src))
    assert code == 0 and "sorted:    no (first decrease at event 1)" in out
    code, _, _ = run_cli(capsys, "events", "convert", str(src), str(tmp_path / "o.npy"), "--allow-unsorted")
    assert code == 0 and read_events(tmp_path / "o.npy").t.tolist() == [5, 4, 6]


def binary_file(tmp_path: Path, fmt: str, name: str) -> bytes:
    write_events(tmp_path / name, synthetic_events(5000, seed=1), fmt)
    return (tmp_path / name).read_bytes()


@pytest.mark.parametrize(
    ("fmt", "name", "cut", "pattern"),
    [
        ("npy", "e.npy", 5, r"byte offset \d+: truncated"),
        ("aedat4", "e.aedat4", 1000, r"byte offset \d+: truncated packet"),
        ("evt3", "e.raw", None, r"byte offset \d+"),
    ],
)
def test_truncated_or_corrupt_binary(tmp_path: Path, capsys, fmt, name, cut, pattern) -> None:
    data = bytearray(binary_file(tmp_path, fmt, name))
    bad = tmp_path / f"bad_{name}"
    if cut:
        bad.write_bytes(bytes(data[:-cut]))
    else:  # a RAW header naming an unknown encoding
        bad.write_bytes(b"% format EVT9;width=640;height=480\n% end\n" + bytes(64))
        pattern = "header: unsupported format"
    with pytest.raises(ValueError, match=pattern) as e:
        read_events(bad)
    assert str(e.value).startswith(str(bad))
    out = tmp_path / "out.csv"
    code, _, err = run_cli(capsys, "events", "convert", str(bad), str(out))
    assert code == 2 and str(bad) in err and not out.exists()


def test_npy_nan_names_row_and_offset(tmp_path: Path) -> None:
    arr = np.array([[1, 2, 0.5, 1], [3, 4, np.nan, 1]], np.float64)
    np.save(tmp_path / "n.npy", arr)
    with pytest.raises(ValueError, match=r"n.npy: row 1 \(byte offset 160\): time NaN is not finite"):
        read_events(tmp_path / "n.npy")


def test_out_of_sensor_binary_names_event_and_drop_outside_counts(tmp_path: Path, capsys) -> None:
    ev = synthetic_events(1000, seed=2)
    write_events(tmp_path / "e.h5", ev)
    out = tmp_path / "o.parquet"
    code, _, err = run_cli(capsys, "events", "convert", str(tmp_path / "e.h5"), str(out), "--width", "320")
    assert code == 2 and "e.h5: event " in err and "outside the 320x480 sensor" in err and not out.exists()
    code, stdout, _ = run_cli(
        capsys, "events", "convert", str(tmp_path / "e.h5"), str(out), "--width", "320", "--drop-outside"
    )
    dropped = int(np.count_nonzero(ev.x >= 320))
    assert code == 0 and f"{dropped} dropped outside" in stdout
    assert len(read_events(out)) == len(ev) - dropped


def test_unknown_binary_and_empty(tmp_path: Path, capsys) -> None:
    (tmp_path / "junk.raw").write_bytes(b"\x00\x01\x02garbage")
    (tmp_path / "empty.csv").write_bytes(b"")
    code, _, err = run_cli(capsys, "events", "info", str(tmp_path / "junk.raw"))
    assert code == 2 and "junk.raw: byte offset 0: unrecognised binary content" in err
    code, _, err = run_cli(capsys, "events", "info", str(tmp_path / "empty.csv"))
    assert code == 2 and "empty.csv: byte offset 0: empty file" in err


def test_corrupt_parquet_is_a_clean_error(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"PAR1" + bytes(100))
    code, _, err = run_cli(capsys, "events", "info", str(bad))
    assert code == 2 and str(bad) in err


def test_writers_leave_nothing_behind_on_error(tmp_path: Path) -> None:
    ev = synthetic_events(100, seed=3)
    for fmt, name in (
        ("parquet", "o.parquet"),
        ("npy", "o.npy"),
        ("hdf5", "o.h5"),
        ("csv", "o.csv"),
        ("evt3", "o.raw"),
    ):
        with pytest.raises(RuntimeError, match="boom"), EventWriter(tmp_path / name, fmt) as w:
            w.write(ev)
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("fmt", "bits"), [("evt2", 34), ("evt3", 24)])
def test_evt_writers_refuse_times_their_counter_cannot_hold(tmp_path: Path, fmt: str, bits: int) -> None:
    """A stream starting past the first counter period would read back wrapped: refused, nothing written;
    the same events shifted into range round-trip exactly."""
    ev = synthetic_events(1000, 64, 48, seed=3)
    late = type(ev)(ev.t + (1 << bits), ev.x, ev.y, ev.p, ev.width, ev.height)
    out = tmp_path / f"late.{fmt}"
    with pytest.raises(ValueError, match=rf"late.{fmt}: {fmt} stores {bits} bits"):
        write_events(out, late, fmt=fmt)
    assert not list(tmp_path.iterdir())
    write_events(out, ev, fmt=fmt)
    np.testing.assert_array_equal(read_events(out).t, ev.t)


@pytest.mark.parametrize(
    ("fmt", "name"),
    [("evt2", "o2.raw"), ("evt3", "o3.raw"), ("aedat4", "o.aedat4"), ("aedat4-zstd", "z.aedat4")],
)
def test_camera_writers_stream_and_refuse_unsorted_input(tmp_path: Path, fmt: str, name: str) -> None:
    """Each batch is encoded and written when it arrives (the temporary file grows); a batch that goes
    back in time is a ValueError naming the event's index in the stream, and no output appears."""
    ev = synthetic_events(20_000, 64, 48, seed=3)
    first, second = (
        EventArray(ev.t[s], ev.x[s], ev.y[s], ev.p[s], 64, 48) for s in (slice(10_000), slice(10_000, None))
    )
    out = tmp_path / name
    with EventWriter(out, fmt, 64, 48) as w:
        w.write(first)
        (tmp,) = tmp_path.iterdir()
        assert tmp.stat().st_size > 10_000
        w.write(second)
    same = read_events(out)
    for k in "txyp":
        np.testing.assert_array_equal(getattr(same, k), getattr(ev, k))
    out.unlink()
    t = second.t.copy()
    t[5] = t[4] - 1
    back = EventArray(t, second.x, second.y, second.p, 64, 48)
    with (
        pytest.raises(ValueError, match=rf"{name}: event 10005: time .* before the previous"),
        EventWriter(out, fmt) as w,
    ):
        w.write(first)
        w.write(back)
    assert list(tmp_path.iterdir()) == []

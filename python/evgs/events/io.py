"""One entry point for event files: ``read_events``, ``iter_events``, ``write_events``.

The format is detected from the file's content (``evgs._core.detect_format``); the extension is only a
hint for output files. Text, NPY, EVT 2.0/3.0 and AEDAT 4 decode in Rust (``_core.EventReader``,
streaming, GIL released); NPZ, HDF5 and Parquet go through numpy, h5py and polars. Every source runs
the same per-batch checks (``_core.BatchCheck``): coordinates inside the sensor (or dropped and
counted with ``drop_outside``) and, with ``require_sorted``, non-decreasing time.

Reader options (all formats where they make sense): ``width``/``height`` (sensor size, overriding the
file's), ``drop_outside``, ``require_sorted``, ``time_unit`` (``s``/``ms``/``us``/``ns``); text only:
``delimiter``, ``has_header``, ``columns`` (one letter per column from ``txyp_``); NPY 2-D arrays:
``columns`` (default ``xytp``); EVT: ``time_shift``.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from evgs import _core
from evgs.events.arrays import EventArray
from evgs.events.parquet import SCHEMA, read_parquet, write_parquet
from evgs.io_util import atomic_path

RUST_FORMATS = ("text", "npy", "evt2", "evt3", "aedat4")
READ_FORMATS = (*RUST_FORMATS, "npz", "hdf5", "parquet")
# Time bits of the EVT counters (see EventWriter._check_time_range).
EVT_TIME_BITS = {"evt2": 34, "evt3": 24}
WRITE_FORMATS = ("parquet", "csv", "txt", "npy", "hdf5", "evt2", "evt3", "aedat4")
DEFAULT_BATCH = 1 << 20
SCHEMA_NP = (np.int64, np.uint16, np.uint16, np.int8)

_EXTENSIONS = {
    ".parquet": "parquet",
    ".pq": "parquet",
    ".csv": "csv",
    ".txt": "txt",
    ".npy": "npy",
    ".npz": "npz",
    ".h5": "hdf5",
    ".hdf5": "hdf5",
    ".raw": "evt3",
    ".aedat4": "aedat4",
}
_TIME_SCALE_US = {"s": 1e6, "ms": 1e3, "us": 1.0, "ns": 1e-3}
_NAMES = {
    "t": ("t", "ts", "time", "timestamp", "timestamps"),
    "x": ("x", "xs"),
    "y": ("y", "ys"),
    "p": ("p", "ps", "pol", "polarity", "polarities"),
}


def format_from_extension(path: str | Path) -> str | None:
    """The format an output file's extension suggests (``.raw`` → EVT 3.0), or None."""
    return _EXTENSIONS.get(Path(path).suffix.lower())


def detect_format(path: str | Path) -> str:
    """The format of an existing file, from its content."""
    return _core.detect_format(str(path))


def _normalize_read_format(fmt: str | None) -> str | None:
    if fmt is None:
        return None
    fmt = fmt.lower()
    fmt = "text" if fmt in ("csv", "txt") else fmt
    if fmt not in READ_FORMATS:
        raise ValueError(f"unknown event format {fmt!r} (known: {', '.join(READ_FORMATS)}, csv, txt)")
    return fmt


class EventSource:
    """An open event file yielding :class:`EventArray` batches in bounded memory.

    After (or during) iteration, ``skipped`` counts everything not returned as an event.
    """

    def __init__(self, path: str | Path, fmt: str | None = None, **options: Any) -> None:
        self.path = str(path)
        fmt = _normalize_read_format(fmt) or detect_format(path)
        self.format = fmt
        self._rust: _core.EventReader | None = None
        self._py: _PySource | None = None
        if fmt in RUST_FORMATS:
            self._rust = _core.EventReader(self.path, fmt, **options)
            self.width, self.height = self._rust.width, self._rust.height
        else:
            with _library_errors(self.path):
                self._py = _PY_SOURCES[fmt](self.path, **options)
            self.width, self.height = self._py.width, self._py.height

    @property
    def file_size(self) -> int:
        return self._rust.file_size if self._rust else Path(self.path).stat().st_size

    @property
    def progress(self) -> float:
        """Fraction of the file decoded so far, in [0, 1]."""
        if self._rust:
            return self._rust.bytes_done / max(1, self._rust.file_size)
        return self._py.progress()

    @property
    def skipped(self) -> dict[str, int]:
        return dict(self._rust.skipped()) if self._rust else {"dropped_outside": self._py.check.dropped}

    @property
    def text_layout(self) -> dict | None:
        return self._rust.text_layout() if self._rust else None

    def batches(self, batch_events: int = DEFAULT_BATCH) -> Iterator[EventArray]:
        if batch_events < 1:
            raise ValueError(f"batch_events must be ≥ 1, got {batch_events}")
        if self._rust:
            while (cols := self._rust.next_batch(batch_events)) is not None:
                yield EventArray.from_columns(cols)
        else:
            with _library_errors(self.path):
                yield from self._py.batches(batch_events)

    def read_all(self) -> EventArray:
        if self._rust:
            return EventArray.from_columns(self._rust.read_all())
        with _library_errors(self.path):
            parts = list(self._py.batches(DEFAULT_BATCH * 16))
        return _concat(parts, self.width, self.height)


@contextlib.contextmanager
def _library_errors(path: str) -> Iterator[None]:
    """Report a reading library's own exception (polars, h5py, zipfile) as a ValueError naming the file."""
    try:
        yield
    except (ValueError, OSError, TypeError):
        raise
    except Exception as e:
        raise ValueError(f"{path}: {type(e).__name__}: {e}") from e


def _concat(parts: list[EventArray], width: int, height: int) -> EventArray:
    if not parts:
        return EventArray(*(np.empty(0, d) for d in SCHEMA_NP), width, height)
    if len(parts) == 1:
        return EventArray(parts[0].t, parts[0].x, parts[0].y, parts[0].p, width, height)
    cols = {k: np.concatenate([getattr(b, k) for b in parts]) for k in "txyp"}
    return EventArray.from_columns({**cols, "width": width, "height": height})


def open_events(path: str | Path, fmt: str | None = None, **options: Any) -> EventSource:
    """Open an event file for streaming (see the module docstring for options)."""
    return EventSource(path, fmt, **options)


def read_events(path: str | Path, fmt: str | None = None, **options: Any) -> EventArray:
    """Read a whole event file."""
    return EventSource(path, fmt, **options).read_all()


def iter_events(
    path: str | Path, fmt: str | None = None, batch_events: int = DEFAULT_BATCH, **options: Any
) -> Iterator[EventArray]:
    """Stream an event file as batches of at most ``batch_events`` events."""
    yield from EventSource(path, fmt, **options).batches(batch_events)


# --- Python-decoded formats -------------------------------------------------------------------------


def _column(names: list[str], key: str, path: str) -> str:
    for n in names:
        if n.lower() in _NAMES[key]:
            return n
    raise ValueError(f"{path}: no {key!r} column among {names} (accepted names: {', '.join(_NAMES[key])})")


def _to_events(
    cols: dict[str, np.ndarray], time_unit: str | None, t_offset: int, first: int, path: str
) -> dict[str, np.ndarray]:
    """Convert raw columns to canonical dtypes, with errors naming the event index."""
    t = np.asarray(cols["t"])
    if t.dtype.kind == "f":
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise ValueError(f"{path}: event {first + bad[0]}: time {t[bad[0]]} is not finite")
        t = np.rint(t * _TIME_SCALE_US[time_unit or "s"]).astype(np.int64)
    else:
        scale = _TIME_SCALE_US[time_unit or "us"]
        t = t.astype(np.int64) * int(scale) if scale >= 1 else np.rint(t * scale).astype(np.int64)
    out = {"t": t + t_offset}
    for k in "xy":
        v = np.asarray(cols[k])
        bad = np.flatnonzero((v < 0) | (v > 65535) | (v != np.floor(v)))
        if bad.size:
            raise ValueError(f"{path}: event {first + bad[0]}: {k} = {v[bad[0]]} is not a pixel coordinate")
        out[k] = v.astype(np.uint16)
    p = np.asarray(cols["p"])
    if p.dtype != np.bool_:
        bad = np.flatnonzero((p != 0) & (p != 1) & (p != -1))
        if bad.size:
            raise ValueError(f"{path}: event {first + bad[0]}: polarity {p[bad[0]]} is not 0/1, -1/+1")
    out["p"] = np.where(p > 0, 1, -1).astype(np.int8)
    return out


class _PySource:
    """A Python-decoded source: raw column chunks from the subclass, then the shared batch checks."""

    width = 0
    height = 0
    n = 0

    def __init__(self, path: str, **options: Any) -> None:
        known = {"width", "height", "drop_outside", "require_sorted", "time_unit"}
        unknown = set(options) - known
        if unknown:
            raise TypeError(f"options {sorted(unknown)} do not apply to {type(self).__name__} files")
        self.path = path
        self.time_unit = options.get("time_unit")
        self._open()
        self.width = options.get("width") or self.width
        self.height = options.get("height") or self.height
        self.check = _core.BatchCheck(
            path,
            self.width,
            self.height,
            drop_outside=options.get("drop_outside", False),
            require_sorted=options.get("require_sorted", False),
        )
        self.done = 0

    def _open(self) -> None:
        raise NotImplementedError

    def _chunks(self, batch_events: int) -> Iterator[dict[str, np.ndarray]]:
        """Canonical columns in consecutive chunks of at most ``batch_events``."""
        raise NotImplementedError

    def progress(self) -> float:
        return self.done / max(1, self.n)

    def batches(self, batch_events: int) -> Iterator[EventArray]:
        for cols in self._chunks(batch_events):
            ev = EventArray.from_columns({**cols, "width": self.width, "height": self.height})
            self.done += len(ev)
            keep = self.check.check(ev.t, ev.x, ev.y, ev.p)
            if keep is not None:
                ev = EventArray(ev.t[keep], ev.x[keep], ev.y[keep], ev.p[keep], self.width, self.height)
            yield ev


class _SlicedSource(_PySource):
    """A source whose raw columns can be sliced (``self._raw``), converted chunk by chunk."""

    _raw: dict[str, Any]
    _t_offset = 0

    def _chunks(self, batch_events: int) -> Iterator[dict[str, np.ndarray]]:
        for start in range(0, self.n, batch_events):
            raw = {k: v[start : start + batch_events] for k, v in self._raw.items()}
            yield _to_events(raw, self.time_unit, self._t_offset, start, self.path)


class _NpzSource(_SlicedSource):
    """ELOPE-style ``.npz``: a structured ``events`` array, or separate t/x/y/p arrays (read whole:
    zip members cannot be memory-mapped)."""

    def _open(self) -> None:
        with np.load(self.path, allow_pickle=False) as z:
            if "events" in z.files and z["events"].dtype.names:
                arr = z["events"]
                names = list(arr.dtype.names)
                self._raw = {k: arr[_column(names, k, self.path)] for k in "txyp"}
            else:
                self._raw = {k: z[_column(z.files, k, self.path)] for k in "txyp"}
        self.n = len(self._raw["t"])


class _Hdf5Source(_SlicedSource):
    """HDF5 ``events/{t,x,y,p}`` (DSEC/TUM-VIE, with ``t_offset``) or ``events/{ts,xs,ys,ps}``
    (event_utils); read by slices."""

    def _open(self) -> None:
        import h5py

        f = h5py.File(self.path, "r")
        grp = f["events"] if "events" in f else f
        names = [k for k in grp if isinstance(grp[k], h5py.Dataset)]
        self._raw = {k: grp[_column(names, k, self.path)] for k in "txyp"}
        for where in (f, grp):
            if "t_offset" in where:
                self._t_offset = int(where["t_offset"][()])
        self.width = int(grp.attrs.get("width", f.attrs.get("width", 0)))
        self.height = int(grp.attrs.get("height", f.attrs.get("height", 0)))
        self.n = len(self._raw["t"])


class _ParquetSource(_PySource):
    """Canonical Parquet, streamed by polars in batches."""

    def _open(self) -> None:
        schema = pl.read_parquet_schema(self.path)
        for name, dtype in SCHEMA.items():
            if schema.get(name) != dtype:
                raise ValueError(
                    f"{self.path}: column {name!r} has type {schema.get(name)}, expected {dtype}"
                )
        size = json.loads(pl.read_parquet_metadata(self.path).get("evgs", "{}"))
        self.width, self.height = int(size.get("width", 0)), int(size.get("height", 0))
        self.n = pl.scan_parquet(self.path).select(pl.len()).collect().item()

    def _chunks(self, batch_events: int) -> Iterator[dict[str, np.ndarray]]:
        if batch_events >= self.n:
            ev = read_parquet(self.path)
            yield {k: getattr(ev, k) for k in "txyp"}
            return
        lf = pl.scan_parquet(self.path).select(list(SCHEMA))
        for df in lf.collect_batches(chunk_size=batch_events):
            for start in range(0, len(df), batch_events):
                part = df[start : start + batch_events]
                yield {k: part[k].to_numpy() for k in "txyp"}


_PY_SOURCES: dict[str, type[_PySource]] = {"npz": _NpzSource, "hdf5": _Hdf5Source, "parquet": _ParquetSource}


# --- writers ----------------------------------------------------------------------------------------


class EventWriter:
    """Write event batches to ``path`` atomically: the output appears only when ``close`` succeeds.

    Use as a context manager; an exception inside the block leaves no file behind. Every format is
    written batch by batch in bounded memory; camera formats (EVT 2.0/3.0, AEDAT 4) take their header's
    sensor size from the first batch and need time-sorted events (an error names the first that is not).
    """

    def __init__(self, path: str | Path, fmt: str | None = None, width: int = 0, height: int = 0) -> None:
        fmt = (fmt or format_from_extension(path) or "").lower()
        if fmt == "text":
            fmt = "csv"
        if fmt not in WRITE_FORMATS and not fmt.startswith("aedat4"):
            raise ValueError(
                f"{path}: cannot tell the output format (pass one of {', '.join(WRITE_FORMATS)})"
            )
        self.path, self.format, self.width, self.height = Path(path), fmt, width, height
        self.count = 0
        self._atomic = atomic_path(self.path)
        self._tmp = self._atomic.__enter__()
        self._nparts = 0
        self._camera: _core.CameraWriter | None = None
        self._file = None
        self._h5 = None
        self._tmpdir: str | None = None
        if fmt in ("csv", "txt", "npy"):
            self._file = open(self._tmp, "wb")  # noqa: SIM115 (closed in close/abort)
            if fmt == "npy":
                self._file.write(_core.encode_npy_header(0))
        elif fmt == "hdf5":
            import h5py

            self._h5 = h5py.File(self._tmp, "w")
            g = self._h5.create_group("events")
            for k, dt in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.uint8)):
                g.create_dataset(k, shape=(0,), maxshape=(None,), dtype=dt, chunks=(1 << 16,))
            self._h5.create_dataset("t_offset", data=np.int64(0))
        elif fmt == "parquet":
            self._tmpdir = tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent)

    def write(self, ev: EventArray) -> None:
        self.width, self.height = max(self.width, ev.width), max(self.height, ev.height)
        n = len(ev)
        if self._file is not None and self.format == "npy":
            self._file.write(_core.encode_npy_data(ev.t, ev.x, ev.y, ev.p))
        elif self._file is not None:
            csv = self.format == "csv"
            self._file.write(
                _core.encode_text_bytes(
                    ev.t,
                    ev.x,
                    ev.y,
                    ev.p,
                    delimiter="," if csv else " ",
                    time_unit="us" if csv else "s",
                    header=csv and self.count == 0,
                    zero_one=True,
                )
            )
        elif self._h5 is not None:
            g = self._h5["events"]
            for k, v in (("t", ev.t), ("x", ev.x), ("y", ev.y), ("p", (ev.p > 0).astype(np.uint8))):
                g[k].resize((self.count + n,))
                g[k][self.count :] = v
        elif self._tmpdir is not None:
            write_parquet(Path(self._tmpdir) / f"{self._nparts:06d}.parquet", ev)
            self._nparts += 1
        elif n:
            self._camera_writer(ev).write(ev.t, ev.x, ev.y, ev.p)
        self.count += n

    def close(self) -> None:
        """Finish the file and move it into place."""
        try:
            self._finish()
        except BaseException:
            self.abort()
            raise
        self._cleanup()
        self._atomic.__exit__(None, None, None)

    def abort(self) -> None:
        """Discard everything written so far."""
        self._cleanup()
        err = RuntimeError("aborted")
        self._atomic.__exit__(RuntimeError, err, None)

    def _finish(self) -> None:
        if self._file is not None:
            if self.format == "npy":
                self._file.seek(0)
                self._file.write(_core.encode_npy_header(self.count))
            self._file.close()
        elif self._h5 is not None:
            self._h5["events"].attrs["width"] = self.width
            self._h5["events"].attrs["height"] = self.height
            self._h5.close()
        elif self._tmpdir is not None:
            meta = {"evgs": json.dumps({"width": self.width, "height": self.height})}
            if self._nparts:
                pl.scan_parquet(str(Path(self._tmpdir) / "*.parquet")).sink_parquet(
                    self._tmp, compression="zstd", metadata=meta
                )
            else:
                write_parquet(self._tmp, _concat([], self.width, self.height))
        else:
            self._camera_writer(None).close()

    def _camera_writer(self, first: EventArray | None) -> _core.CameraWriter:
        """The camera-format writer, created (header written) at the first batch or at close."""
        if self._camera is None:
            if first is not None:
                self._check_time_range(first)
            self._camera = _core.CameraWriter(
                str(self._tmp), self.format, self.width, self.height, name=str(self.path)
            )
        return self._camera

    def _check_time_range(self, ev: EventArray) -> None:
        """EVT counters carry 34 (2.0) or 24 (3.0) bits of µs and a decoder rebuilds absolute time from
        the first period on, so a stream starting later would come back wrapped: refuse, don't corrupt."""
        bits = EVT_TIME_BITS.get(self.format)
        if bits is None or len(ev) == 0:
            return
        t0 = int(ev.t[0])
        if not 0 <= t0 < 1 << bits:
            raise ValueError(
                f"{self.path}: {self.format} stores {bits} bits of µs time, so the first event at {t0} µs "
                f"cannot be written (it would read back as {t0 % (1 << bits)} µs); subtract a time offset "
                "first, or write parquet/npy/hdf5/aedat4, which keep 64-bit times"
            )

    def _cleanup(self) -> None:
        self._camera = None  # closes the file (the temporary is removed by atomic_path)
        if self._file is not None and not self._file.closed:
            self._file.close()
        if self._h5 is not None and self._h5.id.valid:
            self._h5.close()
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)

    def __enter__(self) -> EventWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_events(path: str | Path, ev: EventArray, fmt: str | None = None) -> None:
    """Write events atomically; the format comes from ``fmt`` or the extension (``.raw`` → EVT 3.0).

    ``fmt`` is one of parquet (canonical), csv (µs, header), txt (ESIM: seconds, space-separated),
    npy (structured t/x/y/p), hdf5 (``events/{t,x,y,p}``), evt2, evt3, aedat4 (LZ4), aedat4-zstd.
    """
    if (fmt or format_from_extension(path)) == "parquet":
        write_parquet(path, ev)
        return
    with EventWriter(path, fmt, ev.width, ev.height) as w:
        w.write(ev)

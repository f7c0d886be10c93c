//! Bindings for `crate::events`: validation, the streaming reader, format detection, encoders and
//! the camera-format writer.

use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1};
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};

use crate::error::Error;
use crate::events::detect::{detect_file, Format};
use crate::events::npy::{encode_npy_rows, npy_header, NpyStyle};
use crate::events::reader::{BatchCheck, EventReader, ReadOptions};
use crate::events::text::{encode_text, Delimiter, Role, TextOptions, TextStyle, TimeUnit};
use crate::events::writer::CameraWriter;
use crate::events::{Events, EventsView};

/// Convert a core error into the matching Python exception.
pub(crate) fn to_py_err(e: Error) -> PyErr {
    match e {
        Error::Io { .. } => PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// Hand an event stream to Python as a dict of numpy columns (the Vecs move, nothing is copied).
pub(crate) fn events_to_py(py: Python<'_>, ev: Events) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("t", ev.t.into_pyarray(py))?;
    d.set_item("x", ev.x.into_pyarray(py))?;
    d.set_item("y", ev.y.into_pyarray(py))?;
    d.set_item("p", ev.p.into_pyarray(py))?;
    d.set_item("width", ev.width)?;
    d.set_item("height", ev.height)?;
    Ok(d)
}

/// Borrow four numpy columns as an [`EventsView`].
fn view<'a>(
    t: &'a PyReadonlyArray1<'_, i64>,
    x: &'a PyReadonlyArray1<'_, u16>,
    y: &'a PyReadonlyArray1<'_, u16>,
    p: &'a PyReadonlyArray1<'_, i8>,
    width: u32,
    height: u32,
) -> PyResult<EventsView<'a>> {
    let v =
        EventsView { t: t.as_slice()?, x: x.as_slice()?, y: y.as_slice()?, p: p.as_slice()?, width, height };
    if v.x.len() != v.len() || v.y.len() != v.len() || v.p.len() != v.len() {
        return Err(PyValueError::new_err("event columns have different lengths"));
    }
    Ok(v)
}

#[allow(clippy::too_many_arguments)]
/// Check an event stream's invariants; raises ValueError naming `source` and the event index.
#[pyfunction]
fn validate_events(
    py: Python<'_>,
    t: PyReadonlyArray1<'_, i64>,
    x: PyReadonlyArray1<'_, u16>,
    y: PyReadonlyArray1<'_, u16>,
    p: PyReadonlyArray1<'_, i8>,
    width: u32,
    height: u32,
    source: &str,
) -> PyResult<()> {
    let view =
        EventsView { t: t.as_slice()?, x: x.as_slice()?, y: y.as_slice()?, p: p.as_slice()?, width, height };
    py.detach(|| view.validate(source)).map_err(to_py_err)
}

/// The format of a file, detected from its content.
#[pyfunction]
fn detect_format(py: Python<'_>, path: &str) -> PyResult<&'static str> {
    py.detach(|| detect_file(path)).map(Format::name).map_err(to_py_err)
}

fn delimiter_byte(d: &str) -> PyResult<u8> {
    match d.as_bytes() {
        [b] => Ok(*b),
        _ if d == "whitespace" => Ok(b' '),
        _ => Err(PyValueError::new_err(format!("delimiter {d:?} must be one character or 'whitespace'"))),
    }
}

/// An open event file decoded in Rust (text, npy, evt2, evt3, aedat4), batch by batch, GIL released.
#[pyclass(name = "EventReader", module = "evgs._core")]
pub struct PyEventReader {
    inner: EventReader,
}

#[pymethods]
impl PyEventReader {
    #[new]
    #[pyo3(signature = (path, format=None, *, delimiter=None, has_header=None, columns=None, time_unit=None,
                        width=0, height=0, require_sorted=false, drop_outside=false, time_shift=false))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        path: &str,
        format: Option<&str>,
        delimiter: Option<&str>,
        has_header: Option<bool>,
        columns: Option<String>,
        time_unit: Option<&str>,
        width: u32,
        height: u32,
        require_sorted: bool,
        drop_outside: bool,
        time_shift: bool,
    ) -> PyResult<Self> {
        let format = format.map(Format::parse).transpose().map_err(to_py_err)?;
        let text = TextOptions {
            delimiter: delimiter.map(delimiter_byte).transpose()?,
            has_header,
            columns,
            time_unit: time_unit.map(TimeUnit::parse).transpose().map_err(to_py_err)?,
            width,
            height,
            require_sorted,
        };
        let opts = ReadOptions { text, drop_outside, time_shift };
        let inner = py.detach(|| EventReader::open(path, format, &opts)).map_err(to_py_err)?;
        Ok(PyEventReader { inner })
    }

    /// The next batch (dict of numpy columns t, x, y, p plus width/height) of at most `max_events`,
    /// or None at the end of the file.
    fn next_batch<'py>(
        &mut self,
        py: Python<'py>,
        max_events: usize,
    ) -> PyResult<Option<Bound<'py, PyDict>>> {
        let inner = &mut self.inner;
        match py.detach(|| inner.next_batch(max_events)).map_err(to_py_err)? {
            Some(ev) => Ok(Some(events_to_py(py, ev)?)),
            None => Ok(None),
        }
    }

    /// Every remaining event as one dict of numpy columns.
    fn read_all<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let inner = &mut self.inner;
        let ev = py.detach(|| inner.read_all()).map_err(to_py_err)?;
        events_to_py(py, ev)
    }

    #[getter]
    fn format(&self) -> &'static str {
        self.inner.format().name()
    }

    #[getter]
    fn width(&self) -> u32 {
        self.inner.width()
    }

    #[getter]
    fn height(&self) -> u32 {
        self.inner.height()
    }

    #[getter]
    fn file_size(&self) -> u64 {
        self.inner.file_size()
    }

    #[getter]
    fn bytes_done(&self) -> u64 {
        self.inner.bytes_done()
    }

    /// Counts of everything not returned as an event: `dropped_outside` and, for camera formats,
    /// the decoder's skipped words/packets by reason.
    fn skipped<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        d.set_item("dropped_outside", self.inner.dropped_outside())?;
        if let Some(s) = self.inner.decode_stats() {
            d.set_item("triggers", s.triggers)?;
            d.set_item("words_before_time_high", s.words_before_time_high)?;
            d.set_item("skipped_words", s.skipped_words)?;
            d.set_item("dropped_events", s.dropped_events)?;
            d.set_item("dropped_partial_bytes", s.dropped_partial_bytes)?;
            d.set_item("skipped_packets", s.skipped_packets)?;
        }
        Ok(d)
    }

    /// For text files, the sniffed layout: delimiter, header, columns, time unit.
    fn text_layout<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(l) = self.inner.text_layout() else { return Ok(None) };
        let d = PyDict::new(py);
        let delim = match l.delimiter {
            Delimiter::Byte(b) => (b as char).to_string(),
            Delimiter::Whitespace => "whitespace".into(),
        };
        let cols: String = l
            .roles
            .iter()
            .map(|r| match r {
                Role::T => 't',
                Role::X => 'x',
                Role::Y => 'y',
                Role::P => 'p',
                Role::Skip => '_',
            })
            .collect();
        d.set_item("delimiter", delim)?;
        d.set_item("has_header", l.has_header)?;
        d.set_item("columns", cols)?;
        d.set_item("time_unit", l.time_unit.name())?;
        Ok(Some(d))
    }
}

/// The reader's per-batch checks (sensor bounds with optional dropping, sortedness) for event
/// batches decoded outside Rust, so every format reports problems the same way.
#[pyclass(name = "BatchCheck", module = "evgs._core")]
pub struct PyBatchCheck {
    inner: BatchCheck,
}

#[pymethods]
impl PyBatchCheck {
    #[new]
    #[pyo3(signature = (path, width=0, height=0, *, drop_outside=false, require_sorted=false))]
    fn new(path: &str, width: u32, height: u32, drop_outside: bool, require_sorted: bool) -> Self {
        PyBatchCheck { inner: BatchCheck::new(path, width, height, drop_outside, require_sorted) }
    }

    /// Check the next batch; returns the indices to keep when events were dropped, else None.
    fn check<'py>(
        &mut self,
        py: Python<'py>,
        t: PyReadonlyArray1<'py, i64>,
        x: PyReadonlyArray1<'py, u16>,
        y: PyReadonlyArray1<'py, u16>,
        p: PyReadonlyArray1<'py, i8>,
    ) -> PyResult<Option<Bound<'py, PyArray1<usize>>>> {
        let v = view(&t, &x, &y, &p, 0, 0)?;
        let inner = &mut self.inner;
        Ok(py.detach(|| inner.check(v)).map_err(to_py_err)?.map(|k| k.into_pyarray(py)))
    }

    #[getter]
    fn dropped(&self) -> u64 {
        self.inner.dropped
    }
}

/// Events as text lines (bytes as a uint8 array, no copy).
#[pyfunction]
#[pyo3(signature = (t, x, y, p, *, delimiter=",", time_unit="us", header=true, zero_one=true))]
#[allow(clippy::too_many_arguments)]
fn encode_text_bytes<'py>(
    py: Python<'py>,
    t: PyReadonlyArray1<'py, i64>,
    x: PyReadonlyArray1<'py, u16>,
    y: PyReadonlyArray1<'py, u16>,
    p: PyReadonlyArray1<'py, i8>,
    delimiter: &str,
    time_unit: &str,
    header: bool,
    zero_one: bool,
) -> PyResult<Bound<'py, PyArray1<u8>>> {
    let style = TextStyle {
        delimiter: delimiter_byte(delimiter)?,
        time_unit: TimeUnit::parse(time_unit).map_err(to_py_err)?,
        header,
        zero_one,
    };
    let v = view(&t, &x, &y, &p, 0, 0)?;
    Ok(py.detach(|| encode_text(v, style)).into_pyarray(py))
}

fn npy_style(style: &str) -> PyResult<NpyStyle> {
    match style {
        "structured" => Ok(NpyStyle::Structured),
        "xytp" => Ok(NpyStyle::Xytp),
        _ => Err(PyValueError::new_err(format!("npy style {style:?}: expected 'structured' or 'xytp'"))),
    }
}

/// A fixed-length NPY header for `rows` events (rewritable in place once the count is known).
#[pyfunction]
#[pyo3(signature = (rows, style="structured"))]
fn encode_npy_header<'py>(py: Python<'py>, rows: u64, style: &str) -> PyResult<Bound<'py, PyBytes>> {
    Ok(PyBytes::new(py, &npy_header(rows, npy_style(style)?)))
}

/// NPY rows (no header) for the events.
#[pyfunction]
#[pyo3(signature = (t, x, y, p, style="structured"))]
fn encode_npy_data<'py>(
    py: Python<'py>,
    t: PyReadonlyArray1<'py, i64>,
    x: PyReadonlyArray1<'py, u16>,
    y: PyReadonlyArray1<'py, u16>,
    p: PyReadonlyArray1<'py, i8>,
    style: &str,
) -> PyResult<Bound<'py, PyArray1<u8>>> {
    let style = npy_style(style)?;
    let v = view(&t, &x, &y, &p, 0, 0)?;
    Ok(py.detach(|| encode_npy_rows(v, style)).into_pyarray(py))
}

/// A camera-format file (`evt2`, `evt3`, `aedat4`/`aedat4-lz4`, `aedat4-zstd`, `aedat4-none`) written
/// batch by batch in bounded memory. Write to a temporary path and rename it after `close`; `name`
/// (default `path`) is what errors call the output.
#[pyclass(name = "CameraWriter", module = "evgs._core")]
pub struct PyCameraWriter {
    inner: Option<CameraWriter>,
}

#[pymethods]
impl PyCameraWriter {
    #[new]
    #[pyo3(signature = (path, format, width=0, height=0, *, name=None))]
    fn new(
        py: Python<'_>,
        path: &str,
        format: &str,
        width: u32,
        height: u32,
        name: Option<&str>,
    ) -> PyResult<Self> {
        let name = name.unwrap_or(path);
        let inner =
            py.detach(|| CameraWriter::create(path, name, format, width, height)).map_err(to_py_err)?;
        Ok(PyCameraWriter { inner: Some(inner) })
    }

    /// Encode and write the stream's next events; ValueError (naming the event's index in the
    /// stream) for unsorted times or coordinates that do not fit.
    fn write(
        &mut self,
        py: Python<'_>,
        t: PyReadonlyArray1<'_, i64>,
        x: PyReadonlyArray1<'_, u16>,
        y: PyReadonlyArray1<'_, u16>,
        p: PyReadonlyArray1<'_, i8>,
    ) -> PyResult<()> {
        let v = view(&t, &x, &y, &p, 0, 0)?;
        let inner = self.inner.as_mut().ok_or_else(|| PyValueError::new_err("CameraWriter is closed"))?;
        py.detach(|| inner.write(v)).map_err(to_py_err)
    }

    /// Write what is pending and flush the file to disk.
    fn close(&mut self, py: Python<'_>) -> PyResult<()> {
        let inner = self.inner.take().ok_or_else(|| PyValueError::new_err("CameraWriter is closed"))?;
        py.detach(|| inner.finish()).map_err(to_py_err)
    }
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(validate_events, m)?)?;
    m.add_function(wrap_pyfunction!(detect_format, m)?)?;
    m.add_function(wrap_pyfunction!(encode_text_bytes, m)?)?;
    m.add_function(wrap_pyfunction!(encode_npy_header, m)?)?;
    m.add_function(wrap_pyfunction!(encode_npy_data, m)?)?;
    m.add_class::<PyEventReader>()?;
    m.add_class::<PyBatchCheck>()?;
    m.add_class::<PyCameraWriter>()?;
    Ok(())
}

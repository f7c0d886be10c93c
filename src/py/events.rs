//! Bindings for `crate::events`.

use numpy::{IntoPyArray, PyReadonlyArray1};
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;

use crate::error::Error;
use crate::events::{Events, EventsView};

/// Convert a core error into the matching Python exception.
pub(crate) fn to_py_err(e: Error) -> PyErr {
    match e {
        Error::Io { .. } => PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// Hand an event stream to Python as a dict of numpy columns (the Vecs move, nothing is copied).
pub(crate) fn events_to_py(py: Python<'_>, ev: Events) -> PyResult<Bound<'_, pyo3::types::PyDict>> {
    let d = pyo3::types::PyDict::new(py);
    d.set_item("t", ev.t.into_pyarray(py))?;
    d.set_item("x", ev.x.into_pyarray(py))?;
    d.set_item("y", ev.y.into_pyarray(py))?;
    d.set_item("p", ev.p.into_pyarray(py))?;
    d.set_item("width", ev.width)?;
    d.set_item("height", ev.height)?;
    Ok(d)
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

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(validate_events, m)?)?;
    Ok(())
}

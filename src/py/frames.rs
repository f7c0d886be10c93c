//! Bindings for `crate::events::{index, window, accumulate}` (chunks, windows, event frames).

use pyo3::prelude::*;

pub(crate) fn register(_m: &Bound<'_, PyModule>) -> PyResult<()> {
    Ok(())
}

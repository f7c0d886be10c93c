//! Bindings for `crate::raster` (the Gaussian rasterizer).

use pyo3::prelude::*;

pub(crate) fn register(_m: &Bound<'_, PyModule>) -> PyResult<()> {
    Ok(())
}

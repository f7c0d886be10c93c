//! Bindings for `crate::loss` (the SSIM window's blur). Planes arrive as flat contiguous numpy views of
//! the caller's tensors (no copy) and leave as a flat numpy array that owns the Rust buffer (no copy);
//! `evgs.slam.loss` gives them their shapes.

use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1};
use pyo3::prelude::*;

use super::events::to_py_err;
use crate::loss::blur::{self, Sample};

fn correlate<'py, T: Sample + numpy::Element>(
    py: Python<'py>,
    x: PyReadonlyArray1<'py, T>,
    planes: usize,
    height: usize,
    width: usize,
    taps: PyReadonlyArray1<'py, T>,
) -> PyResult<Bound<'py, PyArray1<T>>> {
    let (x, taps) = (x.as_slice()?, taps.as_slice()?);
    let out = py.detach(|| blur::correlate_valid(x, planes, height, width, taps)).map_err(to_py_err)?;
    Ok(out.into_pyarray(py))
}

/// `planes × (height − n + 1) × (width − n + 1)` float32: each `height × width` plane of `x`
/// correlated with the `n` taps along its rows, then its columns ("valid" positions only).
#[pyfunction]
fn correlate_valid_f32<'py>(
    py: Python<'py>,
    x: PyReadonlyArray1<'py, f32>,
    planes: usize,
    height: usize,
    width: usize,
    taps: PyReadonlyArray1<'py, f32>,
) -> PyResult<Bound<'py, PyArray1<f32>>> {
    correlate(py, x, planes, height, width, taps)
}

/// `correlate_valid_f32` in float64.
#[pyfunction]
fn correlate_valid_f64<'py>(
    py: Python<'py>,
    x: PyReadonlyArray1<'py, f64>,
    planes: usize,
    height: usize,
    width: usize,
    taps: PyReadonlyArray1<'py, f64>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    correlate(py, x, planes, height, width, taps)
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(correlate_valid_f32, m)?)?;
    m.add_function(wrap_pyfunction!(correlate_valid_f64, m)?)?;
    Ok(())
}

//! Bindings for `crate::loss` (the SSIM term and the relief prior, each with its gradient). Images
//! arrive as flat contiguous numpy views of the caller's tensors (no copy) and leave as flat numpy arrays
//! that own the Rust buffers (no copy); `evgs.slam.loss` gives them their shapes.

use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1};
use pyo3::prelude::*;

use super::events::to_py_err;
use crate::loss::relief::depth_variation;
use crate::loss::ssim::{ssim, SsimWindow};
use crate::loss::{Planes, Real};

type Grads<'py, T> = Option<(Bound<'py, PyArray1<T>>, Bound<'py, PyArray1<T>>)>;

fn grads<'py, T: numpy::Element>(py: Python<'py>, g: Option<(Vec<T>, Vec<T>)>) -> Grads<'py, T> {
    g.map(|(x, y)| (x.into_pyarray(py), y.into_pyarray(py)))
}

#[allow(clippy::too_many_arguments)]
fn ssim_any<'py, T: Real + numpy::Element>(
    py: Python<'py>,
    a: PyReadonlyArray1<'py, T>,
    b: PyReadonlyArray1<'py, T>,
    shape: (usize, usize, usize),
    taps: PyReadonlyArray1<'py, T>,
    c1: f64,
    c2: f64,
    with_grad: bool,
) -> PyResult<(Bound<'py, PyArray1<T>>, Grads<'py, T>)> {
    let (a, b, taps) = (a.as_slice()?, b.as_slice()?, taps.as_slice()?);
    let planes = Planes { planes: shape.0, height: shape.1, width: shape.2 };
    let window = SsimWindow { taps, c1: T::from_f64(c1), c2: T::from_f64(c2) };
    let out = py.detach(|| ssim(a, b, planes, &window, with_grad)).map_err(to_py_err)?;
    Ok((out.values.into_pyarray(py), grads(py, out.grad)))
}

fn relief_any<'py, T: Real + numpy::Element>(
    py: Python<'py>,
    depth: PyReadonlyArray1<'py, T>,
    alpha: PyReadonlyArray1<'py, T>,
    shape: (usize, usize, usize),
    min_alpha: f64,
    with_grad: bool,
) -> PyResult<(f64, Grads<'py, T>)> {
    let (depth, alpha) = (depth.as_slice()?, alpha.as_slice()?);
    let planes = Planes { planes: shape.0, height: shape.1, width: shape.2 };
    let out = py
        .detach(|| depth_variation(depth, alpha, planes, T::from_f64(min_alpha), with_grad))
        .map_err(to_py_err)?;
    Ok((out.value.to_f64(), grads(py, out.grad)))
}

/// One monomorphic `#[pyfunction]` pair per element type: pyo3 exports no generics, and the two types'
/// wrappers differ in nothing else.
macro_rules! typed_bindings {
    ($t:ty, $ssim:ident, $relief:ident, $ssim_doc:literal, $relief_doc:literal) => {
        #[doc = $ssim_doc]
        #[pyfunction]
        #[allow(clippy::too_many_arguments)]
        fn $ssim<'py>(
            py: Python<'py>,
            a: PyReadonlyArray1<'py, $t>,
            b: PyReadonlyArray1<'py, $t>,
            shape: (usize, usize, usize),
            taps: PyReadonlyArray1<'py, $t>,
            c1: f64,
            c2: f64,
            with_grad: bool,
        ) -> PyResult<(Bound<'py, PyArray1<$t>>, Grads<'py, $t>)> {
            ssim_any(py, a, b, shape, taps, c1, c2, with_grad)
        }

        #[doc = $relief_doc]
        #[pyfunction]
        fn $relief<'py>(
            py: Python<'py>,
            depth: PyReadonlyArray1<'py, $t>,
            alpha: PyReadonlyArray1<'py, $t>,
            shape: (usize, usize, usize),
            min_alpha: f64,
            with_grad: bool,
        ) -> PyResult<(f64, Grads<'py, $t>)> {
            relief_any(py, depth, alpha, shape, min_alpha, with_grad)
        }
    };
}

typed_bindings!(
    f32,
    ssim_f32,
    depth_variation_f32,
    "Mean SSIM of each of the `(B, H, W)` float32 image pairs `a`, `b` (Gaussian window `taps`, constants \
     `c1`, `c2`) and, with `with_grad`, `(∂/∂a, ∂/∂b)` of each image's value (else None).",
    "The relief prior of `(B, H, W)` float32 rendered depth and opacity (`crate::loss::relief`) and, with \
     `with_grad`, `(∂/∂depth, ∂/∂alpha)` (else None)."
);
typed_bindings!(
    f64,
    ssim_f64,
    depth_variation_f64,
    "`ssim_f32` in float64.",
    "`depth_variation_f32` in float64."
);

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(ssim_f32, m)?)?;
    m.add_function(wrap_pyfunction!(ssim_f64, m)?)?;
    m.add_function(wrap_pyfunction!(depth_variation_f32, m)?)?;
    m.add_function(wrap_pyfunction!(depth_variation_f64, m)?)?;
    Ok(())
}

//! Bindings for `crate::raster` (the Gaussian rasterizer). Arrays arrive as flat contiguous float32
//! numpy views of the caller's tensors (no copy); results leave as flat numpy arrays that own the Rust
//! buffers (no copy); the forward state stays in Rust inside an opaque `RasterState`.

use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1};
use pyo3::prelude::*;

use super::events::to_py_err;
use crate::raster::{self, Camera, Gaussians};

/// The saved forward pass (tile lists, final transmittance, last contributors); pass it to
/// `rasterize_backward`.
#[pyclass(frozen, module = "evgs._core")]
struct RasterState {
    inner: raster::RasterState,
}

#[pymethods]
impl RasterState {
    /// Pixel–Gaussian evaluations performed by the forward pass.
    #[getter]
    fn forward_evaluations(&self) -> u64 {
        self.inner.forward_evaluations
    }

    /// Forward evaluations in the standard (3DGS/gsplat) sense: every pixel × its tile's list entries
    /// until it saturated.
    #[getter]
    fn forward_evaluations_standard(&self) -> u64 {
        self.inner.forward_evaluations_standard
    }

    /// Backward evaluations in the standard sense: every pixel × its list entries up to its last
    /// contributor.
    #[getter]
    fn backward_evaluations_standard(&self) -> u64 {
        self.inner.backward_evaluations_standard
    }
}

type Array<'py> = PyReadonlyArray1<'py, f32>;
type Out<'py, T> = Bound<'py, PyArray1<T>>;

fn gaussians<'a>(
    means: &'a Array,
    log_scales: &'a Array,
    quats: &'a Array,
    opacities: &'a Array,
    colors: &'a Array,
    channels: usize,
) -> PyResult<Gaussians<'a>> {
    Ok(Gaussians {
        means: means.as_slice()?,
        log_scales: log_scales.as_slice()?,
        quats: quats.as_slice()?,
        opacities: opacities.as_slice()?,
        colors: colors.as_slice()?,
        channels,
    })
}

/// Render B views; returns flat `(color, depth, alpha, radii, state)`.
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
#[pyfunction]
#[pyo3(signature = (means, log_scales, quats, opacities, colors, channels, viewmats, width, height, fx, fy, cx, cy, near, far, background))]
fn rasterize_forward<'py>(
    py: Python<'py>,
    means: Array<'py>,
    log_scales: Array<'py>,
    quats: Array<'py>,
    opacities: Array<'py>,
    colors: Array<'py>,
    channels: usize,
    viewmats: Array<'py>,
    width: u32,
    height: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    near: f32,
    far: f32,
    background: Array<'py>,
) -> PyResult<(Out<'py, f32>, Out<'py, f32>, Out<'py, f32>, Out<'py, i32>, RasterState)> {
    let gs = gaussians(&means, &log_scales, &quats, &opacities, &colors, channels)?;
    let cam = Camera { width, height, fx, fy, cx, cy, near, far };
    let (views, bg) = (viewmats.as_slice()?, background.as_slice()?);
    let out = py.detach(|| raster::forward(&gs, views, &cam, bg)).map_err(to_py_err)?;
    Ok((
        out.color.into_pyarray(py),
        out.depth.into_pyarray(py),
        out.alpha.into_pyarray(py),
        out.radii.into_pyarray(py),
        RasterState { inner: out.state },
    ))
}

/// Gradients from upstream colour/depth/alpha gradients; returns flat
/// `(means, log_scales, quats, opacities, colors, viewmats, grad2d_norm, evaluations)`.
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
#[pyfunction]
fn rasterize_backward<'py>(
    py: Python<'py>,
    state: &RasterState,
    means: Array<'py>,
    log_scales: Array<'py>,
    quats: Array<'py>,
    opacities: Array<'py>,
    colors: Array<'py>,
    channels: usize,
    viewmats: Array<'py>,
    grad_color: Array<'py>,
    grad_depth: Array<'py>,
    grad_alpha: Array<'py>,
) -> PyResult<(
    Out<'py, f32>,
    Out<'py, f32>,
    Out<'py, f32>,
    Out<'py, f32>,
    Out<'py, f32>,
    Out<'py, f32>,
    Out<'py, f32>,
    u64,
)> {
    let gs = gaussians(&means, &log_scales, &quats, &opacities, &colors, channels)?;
    let (views, gc, gd, ga) =
        (viewmats.as_slice()?, grad_color.as_slice()?, grad_depth.as_slice()?, grad_alpha.as_slice()?);
    let g = py.detach(|| raster::backward(&gs, views, &state.inner, gc, gd, ga)).map_err(to_py_err)?;
    Ok((
        g.means.into_pyarray(py),
        g.log_scales.into_pyarray(py),
        g.quats.into_pyarray(py),
        g.opacities.into_pyarray(py),
        g.colors.into_pyarray(py),
        g.viewmats.into_pyarray(py),
        g.grad2d_norm.into_pyarray(py),
        g.evaluations,
    ))
}

/// Render B views and the colour's derivative along six tangents of each view (forward mode);
/// returns flat `(color, alpha, d_color)`, `d_color` laid out (B, H, W, 6, C).
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
#[pyfunction]
#[pyo3(signature = (means, log_scales, quats, opacities, colors, channels, viewmats, tangents, width, height, fx, fy, cx, cy, near, far, background))]
fn rasterize_pose_jvp<'py>(
    py: Python<'py>,
    means: Array<'py>,
    log_scales: Array<'py>,
    quats: Array<'py>,
    opacities: Array<'py>,
    colors: Array<'py>,
    channels: usize,
    viewmats: Array<'py>,
    tangents: Array<'py>,
    width: u32,
    height: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    near: f32,
    far: f32,
    background: Array<'py>,
) -> PyResult<(Out<'py, f32>, Out<'py, f32>, Out<'py, f32>)> {
    let gs = gaussians(&means, &log_scales, &quats, &opacities, &colors, channels)?;
    let cam = Camera { width, height, fx, fy, cx, cy, near, far };
    let (views, dviews, bg) = (viewmats.as_slice()?, tangents.as_slice()?, background.as_slice()?);
    let out = py.detach(|| raster::forward_jvp(&gs, views, dviews, &cam, bg)).map_err(to_py_err)?;
    Ok((out.forward.color.into_pyarray(py), out.forward.alpha.into_pyarray(py), out.d_color.into_pyarray(py)))
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<RasterState>()?;
    m.add_function(wrap_pyfunction!(rasterize_forward, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_backward, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_pose_jvp, m)?)?;
    Ok(())
}

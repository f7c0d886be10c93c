//! Bindings for `crate::events::{index, window, accumulate, undistort}` (chunks, windows, event frames).
//! Arrays cross as flat 1-D buffers; `evgs.events.frames` gives them their shapes (views, no copies).

use numpy::{IntoPyArray, PyArray1, PyArrayMethods, PyReadonlyArray1};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use super::events::to_py_err;
use crate::error::Error;
use crate::events::accumulate::{accumulate, accumulate_into, frame_size, FrameParams};
use crate::events::index::ChunkIndex;
use crate::events::undistort::Intrinsics;
use crate::events::window::{self, WindowMode};
use crate::events::EventsView;

/// A 1-D numpy array owned by Python.
type Array<'py, T> = Bound<'py, PyArray1<T>>;

/// `bounds[k]` = first event with `t ≥ frame_t[k]`; chunk `k` is `bounds[k]:bounds[k+1]`.
#[pyfunction]
fn chunk_bounds<'py>(
    py: Python<'py>,
    t: PyReadonlyArray1<'_, i64>,
    frame_t: PyReadonlyArray1<'_, i64>,
) -> PyResult<Array<'py, i64>> {
    let (t, frame_t) = (t.as_slice()?, frame_t.as_slice()?);
    let idx = py.detach(|| ChunkIndex::new(t, frame_t)).map_err(to_py_err)?;
    Ok(idx.bounds.into_iter().map(|b| b as i64).collect::<Vec<_>>().into_pyarray(py))
}

/// Seeded batches of event windows `[start, end)` inside `[start, end)` of the stream (paper §3.1).
#[pyclass(name = "WindowSampler", module = "evgs._core")]
struct PyWindowSampler {
    inner: window::WindowSampler,
}

#[pymethods]
impl PyWindowSampler {
    #[new]
    #[pyo3(signature = (start, end, min_n_winsize, max_n_winsize, seed, mode = "paper", seg_num = 100))]
    fn new(
        start: usize,
        end: usize,
        min_n_winsize: usize,
        max_n_winsize: usize,
        seed: u64,
        mode: &str,
        seg_num: usize,
    ) -> PyResult<Self> {
        if start > end {
            return Err(PyValueError::new_err(format!(
                "window sampler: event range [{start}, {end}) is reversed"
            )));
        }
        let mode = match mode {
            "paper" => WindowMode::Paper,
            "reference" => WindowMode::Reference { seg_num },
            other => {
                return Err(PyValueError::new_err(format!(
                    "window sampler: mode must be 'paper' or 'reference', got {other:?}"
                )))
            }
        };
        let inner = window::WindowSampler::new(start..end, min_n_winsize, max_n_winsize, mode, seed)
            .map_err(to_py_err)?;
        Ok(PyWindowSampler { inner })
    }

    /// `(starts, ends)` of `batch` windows, int64.
    fn sample<'py>(&mut self, py: Python<'py>, batch: usize) -> PyResult<(Array<'py, i64>, Array<'py, i64>)> {
        let inner = &mut self.inner;
        let ws = py.detach(|| inner.sample(batch)).map_err(to_py_err)?;
        let (s, e): (Vec<i64>, Vec<i64>) = ws.into_iter().map(|(s, e)| (s as i64, e as i64)).unzip();
        Ok((s.into_pyarray(py), e.into_pyarray(py)))
    }

    /// `(min, max)` window size in events, max after clamping.
    #[getter]
    fn sizes(&self) -> (usize, usize) {
        self.inner.sizes()
    }
}

/// Event frames of the windows `[starts[b], ends[b])`: `(flat (B·H·W) float32, width, height, dropped)`.
/// With `out` (a flat float32 buffer of the right size, e.g. a view of the previous call's frames) the
/// frames are written there and `out` is returned.
#[allow(clippy::too_many_arguments)]
#[pyfunction]
#[pyo3(signature = (
    t, x, y, p, width, height, starts, ends, c_on, c_off, downsample_log2 = 0, undistort_map = None, out = None
))]
fn accumulate_frames<'py>(
    py: Python<'py>,
    t: PyReadonlyArray1<'_, i64>,
    x: PyReadonlyArray1<'_, u16>,
    y: PyReadonlyArray1<'_, u16>,
    p: PyReadonlyArray1<'_, i8>,
    width: u32,
    height: u32,
    starts: PyReadonlyArray1<'_, i64>,
    ends: PyReadonlyArray1<'_, i64>,
    c_on: f32,
    c_off: f32,
    downsample_log2: u32,
    undistort_map: Option<PyReadonlyArray1<'_, f32>>,
    out: Option<Bound<'py, PyArray1<f32>>>,
) -> PyResult<(Array<'py, f32>, usize, usize, Array<'py, u64>)> {
    let ev =
        EventsView { t: t.as_slice()?, x: x.as_slice()?, y: y.as_slice()?, p: p.as_slice()?, width, height };
    let windows = windows(starts.as_slice()?, ends.as_slice()?).map_err(to_py_err)?;
    let map = undistort_map.as_ref().map(|m| m.as_slice()).transpose()?;
    let params = FrameParams { c_on, c_off, downsample_log2 };
    let (w, h) = frame_size(width, height, params);
    match out {
        Some(out) => {
            let dropped = {
                let mut rw = out.try_readwrite()?;
                let buf = rw.as_slice_mut()?;
                py.detach(|| accumulate_into(ev, &windows, params, map, buf)).map_err(to_py_err)?
            };
            Ok((out, w, h, dropped.into_pyarray(py)))
        }
        None => {
            let frames = py.detach(|| accumulate(ev, &windows, params, map)).map_err(to_py_err)?;
            Ok((frames.data.into_pyarray(py), w, h, frames.dropped.into_pyarray(py)))
        }
    }
}

/// Pair up window starts and ends, rejecting negative indices (the core checks the upper bound).
fn windows(starts: &[i64], ends: &[i64]) -> Result<Vec<(usize, usize)>, Error> {
    if starts.len() != ends.len() {
        return Err(Error::Invalid(format!(
            "event frames: {} window starts but {} ends",
            starts.len(),
            ends.len()
        )));
    }
    starts
        .iter()
        .zip(ends)
        .enumerate()
        .map(|(b, (&s, &e))| match (usize::try_from(s), usize::try_from(e)) {
            (Ok(s), Ok(e)) => Ok((s, e)),
            _ => Err(Error::Invalid(format!("event frames: window {b} = [{s}, {e}) is negative"))),
        })
        .collect()
}

/// Undistorted pixel position of every sensor pixel centre, flat `(H·W·2)` float32, NaN where the
/// inversion fails.
#[allow(clippy::too_many_arguments)]
#[pyfunction]
fn undistort_map<'py>(
    py: Python<'py>,
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    distortion: Vec<f64>,
) -> PyResult<Array<'py, f32>> {
    let cam = Intrinsics::new(width, height, fx, fy, cx, cy, &distortion).map_err(to_py_err)?;
    Ok(py.detach(|| cam.undistort_map()).into_pyarray(py))
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(chunk_bounds, m)?)?;
    m.add_class::<PyWindowSampler>()?;
    m.add_function(wrap_pyfunction!(accumulate_frames, m)?)?;
    m.add_function(wrap_pyfunction!(undistort_map, m)?)?;
    Ok(())
}

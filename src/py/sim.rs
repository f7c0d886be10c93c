//! Bindings for `crate::sim` (event simulation).

use numpy::PyReadonlyArray1;
use pyo3::prelude::*;

use super::events::{events_to_py, to_py_err};
use crate::sim::{EsimConfig, EventSimulator, NoiseConfig};

/// ESIM event simulator fed linear-intensity frames (flattened float32, row-major) in time order.
#[pyclass(name = "EventSimulator", module = "evgs._core")]
pub(crate) struct PyEventSimulator {
    inner: EventSimulator,
}

#[pymethods]
impl PyEventSimulator {
    #[new]
    #[pyo3(signature = (width, height, *, c_on=0.2, c_off=0.2, sigma_c=0.0, refractory_us=0.0, log_eps=1e-3,
                        shot_rate_hz=0.0, shot_dark_level=0.01, leak_rate_hz=0.0, hot_pixel_fraction=0.0,
                        hot_pixel_rate_hz=0.0, seed=0))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        width: u32,
        height: u32,
        c_on: f64,
        c_off: f64,
        sigma_c: f64,
        refractory_us: f64,
        log_eps: f64,
        shot_rate_hz: f64,
        shot_dark_level: f64,
        leak_rate_hz: f64,
        hot_pixel_fraction: f64,
        hot_pixel_rate_hz: f64,
        seed: u64,
    ) -> PyResult<Self> {
        let noise = NoiseConfig {
            shot_rate_hz,
            shot_dark_level,
            leak_rate_hz,
            hot_pixel_fraction,
            hot_pixel_rate_hz,
        };
        let cfg = EsimConfig { c_on, c_off, sigma_c, refractory_us, log_eps, noise, seed };
        Ok(Self { inner: EventSimulator::new(width, height, cfg).map_err(to_py_err)? })
    }

    /// Push a linear-intensity frame at `t_us`; returns the number of events it added.
    fn push_frame(
        &mut self,
        py: Python<'_>,
        t_us: i64,
        intensity: PyReadonlyArray1<'_, f32>,
    ) -> PyResult<usize> {
        let frame = intensity.as_slice()?;
        let sim = &mut self.inner;
        py.detach(|| sim.push_frame(t_us, frame)).map_err(to_py_err)
    }

    /// Push a frame given as log intensity (analytic signals).
    fn push_log_frame(
        &mut self,
        py: Python<'_>,
        t_us: i64,
        log: PyReadonlyArray1<'_, f32>,
    ) -> PyResult<usize> {
        let frame = log.as_slice()?;
        let sim = &mut self.inner;
        py.detach(|| sim.push_log_frame(t_us, frame)).map_err(to_py_err)
    }

    /// Push `intensity` at `t_us` unless the `q`-quantile of |Δ log I| over lit changing pixels exceeds
    /// `max_change`; returns `(change, events added or None when refused)`.
    fn push_frame_if_smooth(
        &mut self,
        py: Python<'_>,
        t_us: i64,
        intensity: PyReadonlyArray1<'_, f32>,
        q: f64,
        min_level: f32,
        max_change: f64,
    ) -> PyResult<(f64, Option<usize>)> {
        let frame = intensity.as_slice()?;
        let sim = &mut self.inner;
        py.detach(|| sim.push_frame_if_smooth(t_us, frame, q, min_level, max_change)).map_err(to_py_err)
    }

    /// All events generated so far (dict of numpy columns, sorted by t then pixel index).
    fn take_events<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, pyo3::types::PyDict>> {
        let ev = self.inner.take_events();
        events_to_py(py, ev)
    }

    #[getter]
    fn num_events(&self) -> usize {
        self.inner.num_events()
    }

    #[getter]
    fn hot_pixel_count(&self) -> usize {
        self.inner.hot_pixel_count()
    }

    #[getter]
    fn last_time(&self) -> Option<i64> {
        self.inner.last_time()
    }
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyEventSimulator>()?;
    Ok(())
}

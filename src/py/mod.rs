//! The Python binding `evgs._core`: the only code that knows pyo3. Thin wrappers that convert numpy
//! arrays to slices, release the GIL around the heavy call, and hand results back without copying.

use pyo3::prelude::*;

mod events;
mod frames;
mod loss;
mod raster;
mod sim;

#[pymodule]
#[pyo3(name = "_core")]
fn core_module(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    events::register(m)?;
    frames::register(m)?;
    loss::register(m)?;
    raster::register(m)?;
    sim::register(m)?;
    Ok(())
}

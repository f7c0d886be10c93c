//! evgs core: the hot loops of event-only Gaussian-splatting SLAM.
//!
//! The module tree mirrors the pipeline: `events` (ingestion, indexing, windows, event frames),
//! `raster` (the CPU Gaussian rasterizer with analytic gradients), `loss` (the SSIM term and the relief prior, with their gradients) and
//! `sim` (event simulation).
//! Nothing here knows about Python; the optional `py` module is the only binding layer.

pub mod error;
pub mod events;
pub mod loss;
pub mod raster;
pub mod sim;

#[cfg(feature = "python")]
mod py;
#[cfg(test)]
mod test_util;

pub use error::{Error, Result};
pub use events::Events;

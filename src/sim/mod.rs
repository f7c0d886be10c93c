//! Event simulation (ESIM semantics) from a stream of rendered intensity frames.
//!
//! `esim` turns consecutive linear-intensity frames into events (per-pixel log intensity, linear
//! interpolation in time, threshold crossings with per-pixel mismatch, refractory period, leak);
//! `noise` adds the sensor's spurious events (shot noise, hot pixels); `rng` gives every (frame, row)
//! its own random stream so results do not depend on the number of threads.

pub mod esim;
pub mod noise;
pub mod rng;

pub use esim::{EsimConfig, EventSimulator};
pub use noise::NoiseConfig;

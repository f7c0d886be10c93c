//! Sensor noise beyond the ideal ESIM pixel: shot noise (more in the dark), hot pixels, and the leak
//! rate (which acts on the pixel's reference level and therefore lives in `esim`).

use super::rng::Rng;
use crate::error::{Error, Result};

/// Noise parameters. The default is a noiseless sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseConfig {
    /// Shot-noise rate per pixel in total darkness (events/s). Photon shot noise dominates when little
    /// light arrives, so the rate falls off as `shot_dark_level / (I + shot_dark_level)` with the pixel's
    /// linear intensity `I`.
    pub shot_rate_hz: f64,
    /// Intensity at which the shot-noise rate has halved.
    pub shot_dark_level: f64,
    /// Leak events per pixel and second in a static scene: the reference level drifts down by
    /// `leak_rate_hz · C_on` per second, so the pixel eventually fires ON events.
    pub leak_rate_hz: f64,
    /// Fraction of pixels that are hot (chosen once per seed).
    pub hot_pixel_fraction: f64,
    /// Event rate of a hot pixel (events/s, random polarity).
    pub hot_pixel_rate_hz: f64,
}

impl Default for NoiseConfig {
    fn default() -> Self {
        NoiseConfig {
            shot_rate_hz: 0.0,
            shot_dark_level: 0.01,
            leak_rate_hz: 0.0,
            hot_pixel_fraction: 0.0,
            hot_pixel_rate_hz: 0.0,
        }
    }
}

impl NoiseConfig {
    pub fn validate(&self) -> Result<()> {
        let rates = [self.shot_rate_hz, self.leak_rate_hz, self.hot_pixel_rate_hz];
        if rates.iter().any(|r| !r.is_finite() || *r < 0.0) {
            return Err(Error::Invalid("noise rates must be finite and ≥ 0".into()));
        }
        if !(self.shot_dark_level > 0.0 && self.shot_dark_level.is_finite()) {
            return Err(Error::Invalid("shot_dark_level must be > 0".into()));
        }
        if !(0.0..=1.0).contains(&self.hot_pixel_fraction) {
            return Err(Error::Invalid("hot_pixel_fraction must be in [0, 1]".into()));
        }
        Ok(())
    }

    /// Shot-noise rate (events/s) of a pixel whose mean linear intensity is `intensity`.
    #[inline]
    pub fn shot_rate_at(&self, intensity: f64) -> f64 {
        self.shot_rate_hz * self.shot_dark_level / (intensity.max(0.0) + self.shot_dark_level)
    }
}

/// A uniform time in `(t0, t1]` µs and a fair polarity.
#[inline]
fn random_event(rng: &mut Rng, t0: i64, t1: i64) -> (i64, i8) {
    let t = (t0 + 1 + (rng.uniform() * (t1 - t0) as f64) as i64).min(t1);
    (t, if rng.next_u64() >> 63 == 0 { 1 } else { -1 })
}

/// The Poisson events of one pixel firing at `rate_hz` over `(t0, t1]` µs, handed to `emit(t, p)`.
pub(crate) fn poisson_events(rng: &mut Rng, rate_hz: f64, t0: i64, t1: i64, mut emit: impl FnMut(i64, i8)) {
    for _ in 0..rng.poisson(rate_hz * (t1 - t0) as f64 * 1e-6) {
        let (t, p) = random_event(rng, t0, t1);
        emit(t, p);
    }
}

/// Shot noise of one pixel row over `(t0, t1]` µs by thinning: candidates arrive at the dark rate
/// (the maximum) on uniformly chosen pixels and are kept with probability `rate(I) / dark rate`. The
/// cost is proportional to the number of candidates, not to the number of pixels.
pub(crate) fn shot_noise_row(
    cfg: &NoiseConfig,
    rng: &mut Rng,
    width: usize,
    intensity: impl Fn(usize) -> f64,
    t0: i64,
    t1: i64,
    mut emit: impl FnMut(usize, i64, i8),
) {
    if cfg.shot_rate_hz <= 0.0 {
        return;
    }
    for _ in 0..rng.poisson(cfg.shot_rate_hz * width as f64 * (t1 - t0) as f64 * 1e-6) {
        let x = ((rng.uniform() * width as f64) as usize).min(width - 1);
        let keep = rng.uniform() * cfg.shot_rate_hz < cfg.shot_rate_at(intensity(x));
        let (t, p) = random_event(rng, t0, t1);
        if keep {
            emit(x, t, p);
        }
    }
}

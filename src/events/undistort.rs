//! Undistortion map for event coordinates: each sensor pixel → its undistorted (pinhole) position.
//!
//! OpenCV's distortion model with `(k1, k2, p1, p2, k3)` maps normalised pinhole coordinates `(x, y)` to
//! distorted ones `x_d = x·(1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)` (and symmetrically
//! for `y_d`). Events come at distorted pixels; the map inverts the model once per pixel centre by the
//! usual fixed-point iteration, so accumulating events with undistortion costs one table look-up.
//! The undistorted point is re-projected with the same intrinsics (`u = fx·x + cx`), which is the
//! pinhole camera the rasterizer renders. Pixels where the iteration does not converge (strong
//! distortion far outside the calibrated field) are NaN: their events are counted as dropped.

use rayon::prelude::*;

use crate::error::{Error, Result};

/// Pinhole intrinsics plus OpenCV `(k1, k2, p1, p2, k3)` distortion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub dist: [f64; 5],
}

/// Fixed-point iterations: converges to < 1e-12 within ~10 for lens-like distortion; the cap only
/// bounds the time spent on pixels where it never converges.
const MAX_ITERATIONS: usize = 100;
/// A pixel is kept only if re-distorting its undistorted point lands within this many pixels.
const MAX_RESIDUAL_PX: f64 = 1e-3;

impl Intrinsics {
    /// From OpenCV-ordered distortion coefficients: 0, 4 or 5 of them (missing ones are 0).
    pub fn new(width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64, dist: &[f64]) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(Error::Invalid(format!("undistortion map: image size {width}x{height} is empty")));
        }
        if !(fx.is_finite() && fy.is_finite() && fx != 0.0 && fy != 0.0 && cx.is_finite() && cy.is_finite()) {
            return Err(Error::Invalid(format!(
                "undistortion map: bad intrinsics fx={fx} fy={fy} cx={cx} cy={cy}"
            )));
        }
        if !matches!(dist.len(), 0 | 4 | 5) || dist.iter().any(|d| !d.is_finite()) {
            return Err(Error::Invalid(format!(
                "undistortion map: expected 0, 4 or 5 finite distortion coefficients \
                 (k1 k2 p1 p2 [k3]), got {dist:?}"
            )));
        }
        let mut d = [0.0; 5];
        d[..dist.len()].copy_from_slice(dist);
        Ok(Intrinsics { width, height, fx, fy, cx, cy, dist: d })
    }

    /// Normalised undistorted → normalised distorted coordinates (the forward model).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.dist;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Distorted pixel → undistorted pixel, or None where the inversion fails.
    pub fn undistort_pixel(&self, u: f64, v: f64) -> Option<(f64, f64)> {
        let [k1, k2, p1, p2, k3] = self.dist;
        let (xd, yd) = ((u - self.cx) / self.fx, (v - self.cy) / self.fy);
        let (mut x, mut y) = (xd, yd);
        for _ in 0..MAX_ITERATIONS {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            let (nx, ny) = ((xd - dx) / radial, (yd - dy) / radial);
            let step = (nx - x).abs().max((ny - y).abs());
            (x, y) = (nx, ny);
            if !step.is_finite() || step < 1e-15 {
                break;
            }
        }
        let (rx, ry) = self.distort(x, y);
        let residual = ((rx - xd) * self.fx).abs().max(((ry - yd) * self.fy).abs());
        (residual <= MAX_RESIDUAL_PX).then_some((self.fx * x + self.cx, self.fy * y + self.cy))
    }

    /// The map for every pixel centre (pixel `(x, y)` has its centre at `(x, y)`, as in OpenCV), row-major,
    /// interleaved `(u, v)`; NaN where the inversion fails.
    pub fn undistort_map(&self) -> Vec<f32> {
        let w = self.width as usize;
        let mut map = vec![0f32; 2 * w * self.height as usize];
        map.par_chunks_mut(2 * w).enumerate().for_each(|(y, row)| {
            for (x, uv) in row.chunks_exact_mut(2).enumerate() {
                let (u, v) = self.undistort_pixel(x as f64, y as f64).unwrap_or((f64::NAN, f64::NAN));
                uv[0] = u as f32;
                uv[1] = v as f32;
            }
        });
        map
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(dist: &[f64]) -> Intrinsics {
        Intrinsics::new(64, 48, 50.0, 52.0, 31.7, 24.2, dist).unwrap()
    }

    #[test]
    fn no_distortion_is_identity() {
        let map = cam(&[]).undistort_map();
        for (i, uv) in map.chunks_exact(2).enumerate() {
            assert!((uv[0] - (i % 64) as f32).abs() < 1e-4 && (uv[1] - (i / 64) as f32).abs() < 1e-4);
        }
    }

    #[test]
    fn undistorted_points_redistort_to_the_pixel() {
        let c = cam(&[-0.28, 0.07, 1e-3, -5e-4, 0.01]);
        let map = c.undistort_map();
        for (i, uv) in map.chunks_exact(2).enumerate() {
            let (x, y) = ((uv[0] as f64 - c.cx) / c.fx, (uv[1] as f64 - c.cy) / c.fy);
            let (xd, yd) = c.distort(x, y);
            let (u, v) = (c.fx * xd + c.cx, c.fy * yd + c.cy);
            assert!((u - (i % 64) as f64).abs() < 1e-3 && (v - (i / 64) as f64).abs() < 1e-3, "pixel {i}");
        }
    }

    #[test]
    fn failed_inversion_is_nan() {
        // Extreme barrel distortion folds over near the corners: no undistorted point maps there.
        let map = cam(&[-2.0, 0.0, 0.0, 0.0, 0.0]).undistort_map();
        assert!(map[0].is_nan() && map[1].is_nan());
        let centre = 2 * (24 * 64 + 32);
        assert!(map[centre].is_finite());
    }

    #[test]
    fn bad_parameters_are_named() {
        assert!(Intrinsics::new(0, 4, 1.0, 1.0, 0.0, 0.0, &[]).is_err());
        let e = Intrinsics::new(4, 4, 1.0, 1.0, 0.0, 0.0, &[0.1; 8]).unwrap_err().to_string();
        assert!(e.contains("0, 4 or 5"), "{e}");
        assert!(Intrinsics::new(4, 4, 0.0, 1.0, 0.0, 0.0, &[]).is_err());
    }
}

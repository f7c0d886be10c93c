//! Pinhole camera and view matrices as the rasterizer sees them.

use crate::error::{Error, Result};

/// Tile edge in pixels. 16 lanes of f32 = two AVX2 registers per tile row.
pub const TILE: usize = 16;

/// Pinhole intrinsics, image size and clipping planes (distortion is not modelled here).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub near: f32,
    pub far: f32,
}

impl Camera {
    pub fn validate(&self) -> Result<()> {
        let finite = [self.fx, self.fy, self.cx, self.cy, self.near].iter().all(|v| v.is_finite());
        if self.width == 0 || self.height == 0 || self.width > 1 << 15 || self.height > 1 << 15 {
            return Err(Error::Invalid(format!(
                "raster: image size {}x{} must be in 1..=32768",
                self.width, self.height
            )));
        }
        if !finite || self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(Error::Invalid(format!(
                "raster: focal lengths must be finite and positive (fx={}, fy={})",
                self.fx, self.fy
            )));
        }
        if !(self.near > 0.0 && self.far > self.near) {
            return Err(Error::Invalid(format!(
                "raster: need 0 < near < far (near={}, far={})",
                self.near, self.far
            )));
        }
        Ok(())
    }

    pub fn tiles_x(&self) -> usize {
        (self.width as usize).div_ceil(TILE)
    }

    pub fn tiles_y(&self) -> usize {
        (self.height as usize).div_ceil(TILE)
    }

    pub fn num_tiles(&self) -> usize {
        self.tiles_x() * self.tiles_y()
    }

    pub fn num_pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// The 3DGS field-of-view clamp limits `(lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos)` on `x/z`, `y/z`.
    pub(crate) fn fov_limits(&self) -> [f32; 4] {
        let (w, h) = (self.width as f32, self.height as f32);
        let margin_x = 0.3 * 0.5 * w / self.fx;
        let margin_y = 0.3 * 0.5 * h / self.fy;
        [
            self.cx / self.fx + margin_x,
            (w - self.cx) / self.fx + margin_x,
            self.cy / self.fy + margin_y,
            (h - self.cy) / self.fy + margin_y,
        ]
    }
}

/// The rotation and translation of a world-to-camera 4×4 matrix (row-major; the last row is ignored).
#[derive(Clone, Copy, Debug)]
pub(crate) struct View {
    pub r: nalgebra::Matrix3<f32>,
    pub t: nalgebra::Vector3<f32>,
}

impl View {
    pub fn from_row_major(m: &[f32]) -> Self {
        View {
            r: nalgebra::Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]),
            t: nalgebra::Vector3::new(m[3], m[7], m[11]),
        }
    }
}

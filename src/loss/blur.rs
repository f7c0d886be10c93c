//! Separable "valid" correlation of image planes with one 1-D kernel, along rows then columns: the
//! Gaussian window of SSIM (forward) and, on a zero-padded gradient with the flipped kernel, its
//! adjoint (backward).
//!
//! Each output is `x[0]·k[0]` followed by one fused multiply-add per further tap, in tap order: the
//! arithmetic of torch's `mul` + `add_(alpha=k[i])` loop this replaces (whose vectorised CPU kernel is an
//! FMA), so results are the same to the last bit. Torch spent most of an SSIM call in the 44 small
//! ops' dispatch and OpenMP barriers; here both passes are one rayon loop each over rows.

use std::ops::Mul;

use rayon::prelude::*;

use crate::error::{Error, Result};

/// The float types the filter runs on (the SLAM's float32, the tests' float64).
pub trait Sample: Copy + Send + Sync + Mul<Output = Self> + Default {
    /// `self · a + b` with one rounding.
    fn fma(self, a: Self, b: Self) -> Self;
}

impl Sample for f32 {
    #[inline(always)]
    fn fma(self, a: f32, b: f32) -> f32 {
        self.mul_add(a, b)
    }
}

impl Sample for f64 {
    #[inline(always)]
    fn fma(self, a: f64, b: f64) -> f64 {
        self.mul_add(a, b)
    }
}

/// Correlate the `planes` row-major `height × width` images in `x` with `taps` along each row, then
/// along each column, keeping only the positions where the kernel lies wholly inside: the result is
/// `planes × (height − n + 1) × (width − n + 1)` for `n` taps.
pub fn correlate_valid<T: Sample>(
    x: &[T],
    planes: usize,
    height: usize,
    width: usize,
    taps: &[T],
) -> Result<Vec<T>> {
    let n = taps.len();
    if n == 0 || n > height || n > width {
        return Err(Error::Invalid(format!(
            "blur: a {n}-tap kernel needs images of at least {n}×{n} pixels, got {height}×{width}"
        )));
    }
    if x.len() != planes * height * width {
        return Err(Error::Invalid(format!(
            "blur: {} values are not {planes} planes of {height}×{width}",
            x.len()
        )));
    }
    let (h, w) = (height - n + 1, width - n + 1);
    // Rows of every plane are independent in the first pass, output rows in the second.
    let mut rows = vec![T::default(); planes * height * w];
    rows.par_chunks_mut(w).zip(x.par_chunks(width)).for_each(|(out, src)| correlate_line(src, 1, taps, out));
    let mut out = vec![T::default(); planes * h * w];
    out.par_chunks_mut(h * w).zip(rows.par_chunks(height * w)).for_each(|(out, plane)| {
        out.par_chunks_mut(w).enumerate().for_each(|(r, line)| correlate_line(&plane[r * w..], w, taps, line))
    });
    Ok(out)
}

/// `out[j] = Σ_i taps[i] · src[j + i·stride]`, accumulated in tap order (see the module doc). The inner
/// loop runs along `j`, contiguous in both passes, so it vectorises.
#[inline]
fn correlate_line<T: Sample>(src: &[T], stride: usize, taps: &[T], out: &mut [T]) {
    let len = out.len();
    for (o, &s) in out.iter_mut().zip(&src[..len]) {
        *o = s * taps[0];
    }
    for (i, &t) in taps.iter().enumerate().skip(1) {
        let line = &src[i * stride..i * stride + len];
        for (o, &s) in out.iter_mut().zip(line) {
            *o = s.fma(t, *o);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition, one output at a time, in the same order of operations.
    fn naive(x: &[f64], planes: usize, height: usize, width: usize, taps: &[f64]) -> Vec<f64> {
        let n = taps.len();
        let (h, w) = (height - n + 1, width - n + 1);
        let at = |p: usize, r: usize, c: usize| x[(p * height + r) * width + c];
        let row = |p: usize, r: usize, c: usize| {
            taps.iter()
                .enumerate()
                .skip(1)
                .fold(at(p, r, c) * taps[0], |acc, (i, &t)| at(p, r, c + i).fma(t, acc))
        };
        let mut out = Vec::with_capacity(planes * h * w);
        for p in 0..planes {
            for r in 0..h {
                for c in 0..w {
                    let v = taps
                        .iter()
                        .enumerate()
                        .skip(1)
                        .fold(row(p, r, c) * taps[0], |acc, (i, &t)| row(p, r + i, c).fma(t, acc));
                    out.push(v);
                }
            }
        }
        out
    }

    fn pseudo_random(len: usize) -> Vec<f64> {
        let mut s = 0x9e37_79b9_7f4a_7c15_u64;
        (0..len)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect()
    }

    #[test]
    fn matches_the_definition_to_the_last_bit() {
        let (planes, height, width) = (3, 17, 29);
        let x = pseudo_random(planes * height * width);
        let taps = [0.1, 0.2, 0.4, 0.2, 0.1];
        let got = correlate_valid(&x, planes, height, width, &taps).unwrap();
        assert_eq!(got, naive(&x, planes, height, width, &taps));
        assert_eq!(got.len(), planes * 13 * 25);
    }

    #[test]
    fn an_impulse_returns_the_kernel_and_a_constant_its_sum() {
        // A unit impulse at (2, 2) of a 5×5 image, 3-tap kernel: output (r, c) = k[2−r]·k[2−c].
        let taps = [0.25f32, 0.5, 0.25];
        let mut x = vec![0f32; 25];
        x[12] = 1.0;
        let got = correlate_valid(&x, 1, 5, 5, &taps).unwrap();
        let expect: Vec<f32> = (0..3).flat_map(|r| (0..3).map(move |c| taps[2 - r] * taps[2 - c])).collect();
        assert_eq!(got, expect);
        let ones = correlate_valid(&[1f32; 4 * 6], 1, 4, 6, &taps).unwrap();
        assert!(ones.iter().all(|&v| v == 1.0));
    }

    #[test]
    fn a_kernel_wider_than_the_image_or_a_wrong_length_is_refused() {
        let err = correlate_valid(&[0f32; 20], 1, 4, 5, &[1.0; 5]).unwrap_err().to_string();
        assert!(err.contains("at least 5×5"), "{err}");
        let err = correlate_valid(&[0f32; 19], 1, 4, 5, &[1.0; 3]).unwrap_err().to_string();
        assert!(err.contains("19 values"), "{err}");
    }
}

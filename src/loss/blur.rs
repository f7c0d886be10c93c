//! The separable "valid" correlation with a 1-D kernel along one line, and its adjoint: the pieces of
//! SSIM's Gaussian window ([`super::ssim`]) forward and backward.
//!
//! Each output of [`correlate_line`] is `x[0]·k[0]` followed by one fused multiply-add per further tap,
//! in tap order (the arithmetic of torch's `mul` + `add_(alpha=k[i])` loop this once replaced). The inner
//! loops run along the line, contiguous in memory in both passes of a 2-D filter, so they vectorise, and
//! a block of outputs stays in registers across the taps.

use super::Real;

/// The longest kernel the lines take (SSIM's window is 11).
pub const MAX_TAPS: usize = 32;

/// Outputs computed together in registers: each is loaded and stored once, not once per tap.
const BLOCK: usize = 32;

/// `out[j] = Σ_i weights[i] · lines[i][j]`, the first term a product and one fused multiply-add per
/// further one, in order (`lines.len() = weights.len()` ≥ 1, each line at least `out.len()` long).
#[inline]
pub fn combine_lines<T: Real>(lines: &[&[T]], weights: &[T], out: &mut [T]) {
    let len = out.len();
    if len < BLOCK {
        for (j, o) in out.iter_mut().enumerate() {
            *o = lines[1..]
                .iter()
                .zip(&weights[1..])
                .fold(lines[0][j] * weights[0], |acc, (l, &t)| l[j].fma(t, acc));
        }
        return;
    }
    // Blocks from the start, the last one flush with the end (it may overlap the one before: each
    // output is a function of the inputs alone, so computing it twice gives it the same value).
    let mut j = 0;
    loop {
        let at = j.min(len - BLOCK);
        let mut acc = [T::ZERO; BLOCK];
        for (a, &s) in acc.iter_mut().zip(&lines[0][at..at + BLOCK]) {
            *a = s * weights[0];
        }
        for (line, &t) in lines[1..].iter().zip(&weights[1..]) {
            for (a, &s) in acc.iter_mut().zip(&line[at..at + BLOCK]) {
                *a = s.fma(t, *a);
            }
        }
        out[at..at + BLOCK].copy_from_slice(&acc);
        if at + BLOCK == len {
            return;
        }
        j += BLOCK;
    }
}

/// `out[j] = Σ_i taps[i] · src[j + i·stride]` for every `j < out.len()`, accumulated in tap order.
/// `stride` 1 filters along a row; the row length of a plane filters along its columns.
#[inline]
pub fn correlate_line<T: Real>(src: &[T], stride: usize, taps: &[T], out: &mut [T]) {
    let mut lines: [&[T]; MAX_TAPS] = [&[]; MAX_TAPS];
    for (i, line) in lines.iter_mut().enumerate().take(taps.len()) {
        *line = &src[i * stride..];
    }
    combine_lines(&lines[..taps.len()], taps, out);
}

/// The adjoint of [`correlate_line`] with stride 1: `out[x] = Σ_i taps[i] · src[x − i]` over the `i`
/// with `0 ≤ x − i < src.len()`, so `out` holds `src.len() + taps.len() − 1` values (the full
/// correlation of the zero-padded `src` with the flipped kernel). `padded` is scratch space.
#[inline]
pub fn correlate_line_adjoint<T: Real>(src: &[T], taps: &[T], padded: &mut Vec<T>, out: &mut [T]) {
    let n = taps.len();
    debug_assert_eq!(out.len(), src.len() + n - 1);
    padded.clear();
    padded.resize(src.len() + 2 * (n - 1), T::ZERO);
    padded[n - 1..n - 1 + src.len()].copy_from_slice(src);
    let mut flipped = [T::ZERO; MAX_TAPS];
    for (f, &t) in flipped.iter_mut().zip(taps.iter().rev()) {
        *f = t;
    }
    correlate_line(padded, 1, &flipped[..n], out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_util::uniform;

    #[test]
    fn a_line_matches_the_definition_to_the_last_bit() {
        let taps = [0.1, 0.2, 0.4, 0.2, 0.1];
        let (stride, len) = (3, 37); // two register blocks and a tail
        let src = uniform(len + (taps.len() - 1) * stride, 1);
        let mut out = vec![0.0; len];
        correlate_line(&src, stride, &taps, &mut out);
        for (j, &o) in out.iter().enumerate() {
            let want = (1..taps.len()).fold(src[j] * taps[0], |acc, i| src[j + i * stride].fma(taps[i], acc));
            assert_eq!(o, want);
        }
    }

    #[test]
    fn the_adjoint_satisfies_the_inner_product_identity() {
        // ⟨K x, y⟩ = ⟨x, Kᵀ y⟩ for an asymmetric kernel.
        let taps = [0.5, -0.25, 0.125, 1.0];
        let x = uniform(20, 2);
        let y = uniform(17, 3);
        let mut kx = vec![0.0; 17];
        correlate_line(&x, 1, &taps, &mut kx);
        let mut kty = vec![0.0; 20];
        correlate_line_adjoint(&y, &taps, &mut Vec::new(), &mut kty);
        let lhs: f64 = kx.iter().zip(&y).map(|(a, b)| a * b).sum();
        let rhs: f64 = x.iter().zip(&kty).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() < 1e-12, "{lhs} vs {rhs}");
    }
}

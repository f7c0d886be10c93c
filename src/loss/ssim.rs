//! SSIM of image pairs with a separable Gaussian window, and its gradient, in one pass each.
//!
//! Per pixel `x` of the "valid" region (where the window lies wholly inside the image), with `G` the
//! window and population statistics `μa = G∗a`, `sa = G∗a²`, `sab = G∗ab` (and the same for `b`):
//!
//! `S = (2μaμb + c1)(2(sab − μaμb) + c2) / ((μa² + μb² + c1)(sa − μa² + sb − μb² + c2))`,
//!
//! and the value is the mean of `S` over the valid region (scikit-image's `structural_similarity` with
//! `gaussian_weights=True, use_sample_covariance=False`). Writing `S = A1·A2 / (B1·B2)`, its partials are
//! `∂S/∂μa = 2μb(A2 − A1)/(B1B2) − 2μa·S·(1/B1 − 1/B2)` (and symmetrically for `μb`),
//! `∂S/∂sa = ∂S/∂sb = −S/B2` and `∂S/∂sab = 2A1/(B1B2)`; each statistic is a blur of `a`, `a²` or `ab`,
//! so the gradient is the adjoint blur of those partial maps, e.g.
//! `∂S̄/∂a = Gᵀ(∂S/∂μa) + 2a·Gᵀ(∂S/∂sa) + b·Gᵀ(∂S/∂sab)` (over the region's size).
//!
//! Both passes run over rows in parallel; the mean is summed per row in float64 and then in row order,
//! so the value does not depend on the thread count.

use rayon::prelude::*;

use super::blur::{combine_lines, correlate_line, correlate_line_adjoint, MAX_TAPS};
use super::{ordered_sum, Planes, Real};
use crate::error::{Error, Result};

/// The window and the stabilising constants (`c1 = (0.01·L)²`, `c2 = (0.03·L)²` for data range `L`).
#[derive(Debug, Clone, Copy)]
pub struct SsimWindow<'a, T> {
    pub taps: &'a [T],
    pub c1: T,
    pub c2: T,
}

/// Mean SSIM of each image pair and, when asked for, its gradient with respect to both images.
#[derive(Debug, Clone, PartialEq)]
pub struct Ssim<T> {
    pub values: Vec<T>,
    /// `(∂values[i]/∂a, ∂values[i]/∂b)`, laid out as the inputs: image `i`'s part of each is the
    /// derivative of `values[i]` (an image's SSIM depends on that image alone).
    pub grad: Option<(Vec<T>, Vec<T>)>,
}

/// Statistics per pixel, in the order the row pass stores them.
const STATS: usize = 5; // μa, μb, sa, sb, sab
/// Partial maps the gradient needs (`∂/∂sb = ∂/∂sa`).
const PARTIALS: usize = 4; // ∂μa, ∂μb, ∂sa, ∂sab

/// SSIM of each of the `shape.planes` image pairs `a[i]`, `b[i]`; with `with_grad`, its gradient too.
pub fn ssim<T: Real>(
    a: &[T],
    b: &[T],
    shape: Planes,
    window: &SsimWindow<'_, T>,
    with_grad: bool,
) -> Result<Ssim<T>> {
    let n = window.taps.len();
    let Planes { planes, height, width } = shape;
    if n == 0 || n > MAX_TAPS {
        return Err(Error::Invalid(format!("ssim: a window of {n} px (1 to {MAX_TAPS} supported)")));
    }
    if n > height || n > width {
        return Err(Error::Invalid(format!(
            "ssim: a {n}-px window needs images of at least {n}×{n} pixels, got {height}×{width}"
        )));
    }
    shape.check("ssim", &[a, b])?;
    let size = height * width;
    let mut values = Vec::with_capacity(planes);
    let mut grads = with_grad.then(|| (vec![T::ZERO; a.len()], vec![T::ZERO; b.len()]));
    for i in 0..planes {
        let image = Pair { a: &a[i * size..(i + 1) * size], b: &b[i * size..(i + 1) * size], height, width };
        let grad = grads
            .as_mut()
            .map(|(ga, gb)| (&mut ga[i * size..(i + 1) * size], &mut gb[i * size..(i + 1) * size]));
        values.push(image.ssim(window, grad));
    }
    Ok(Ssim { values, grad: grads })
}

struct Pair<'a, T> {
    a: &'a [T],
    b: &'a [T],
    height: usize,
    width: usize,
}

impl<T: Real> Pair<'_, T> {
    fn ssim(&self, window: &SsimWindow<'_, T>, grad: Option<(&mut [T], &mut [T])>) -> T {
        let taps = window.taps;
        let (h, w) = (self.height, self.width);
        let n = taps.len();
        let (vh, vw) = (h - n + 1, w - n + 1);
        let (rows_len, parts_len) = (h * STATS * vw, if grad.is_some() { vh * PARTIALS * vw } else { 0 });
        T::with_scratch(rows_len + parts_len, |scratch| {
            let (rows, parts) = scratch.split_at_mut(rows_len);
            self.row_pass(taps, vw, rows);
            let rows = &*rows;
            let stride = STATS * vw;
            // Column pass and the pointwise map, one output row at a time; with the gradient, each row
            // also keeps its partial maps (already over the region's size, so the mean's 1/N is in them).
            let scale = T::from_f64(1.0 / (vh * vw) as f64);
            let column = |r: usize, scratch: &mut Vec<T>, parts: Option<&mut [T]>| -> f64 {
                let (stats, map) = scratch.split_at_mut(STATS * vw);
                for s in 0..STATS {
                    correlate_line(
                        &rows[r * stride + s * vw..],
                        stride,
                        taps,
                        &mut stats[s * vw..(s + 1) * vw],
                    );
                }
                pointwise(stats, map, window.c1, window.c2, scale, parts)
            };
            let line_scratch = || vec![T::ZERO; (STATS + 1) * vw];
            let sums: Vec<f64> = match grad {
                None => (0..vh).into_par_iter().map_init(line_scratch, |st, r| column(r, st, None)).collect(),
                Some((ga, gb)) => {
                    let sums = parts
                        .par_chunks_mut(PARTIALS * vw)
                        .enumerate()
                        .map_init(line_scratch, |st, (r, p)| column(r, st, Some(p)))
                        .collect();
                    self.adjoint(taps, parts, vh, vw, ga, gb);
                    sums
                }
            };
            T::from_f64(ordered_sum(sums) / (vh * vw) as f64)
        })
    }

    /// Every input row filtered along the row for the five statistics: row `r`'s are the `STATS`
    /// consecutive lines of `vw` values at `r · STATS · vw` of `rows`.
    fn row_pass(&self, taps: &[T], vw: usize, rows: &mut [T]) {
        let w = self.width;
        rows.par_chunks_mut(STATS * vw).enumerate().for_each_init(
            || vec![T::ZERO; 3 * w],
            |sq, (r, out)| {
                let (a, b) = (&self.a[r * w..(r + 1) * w], &self.b[r * w..(r + 1) * w]);
                let (aa, rest) = sq.split_at_mut(w);
                let (bb, ab) = rest.split_at_mut(w);
                for x in 0..w {
                    aa[x] = a[x] * a[x];
                    bb[x] = b[x] * b[x];
                    ab[x] = a[x] * b[x];
                }
                for (s, src) in [a, b, &*aa, &*bb, &*ab].into_iter().enumerate() {
                    correlate_line(src, 1, taps, &mut out[s * vw..(s + 1) * vw]);
                }
            },
        );
    }

    /// `ga`, `gb` = the adjoint blur of the partial maps, combined per pixel with the images.
    fn adjoint(&self, taps: &[T], parts: &[T], vh: usize, vw: usize, ga: &mut [T], gb: &mut [T]) {
        let (w, n) = (self.width, taps.len());
        let two = T::ONE + T::ONE;
        ga.par_chunks_mut(w).zip(gb.par_chunks_mut(w)).enumerate().for_each_init(
            || (vec![T::ZERO; PARTIALS * vw], vec![T::ZERO; PARTIALS * w], Vec::new()),
            |(cols, full, padded), (r, (ga, gb))| {
                // Along the columns: input row r gathers the partial rows r − i it contributed to (i in
                // lo..hi, never empty), each line of each partial.
                let (lo, hi) = ((r + 1).saturating_sub(vh), n.min(r + 1));
                for s in 0..PARTIALS {
                    let mut lines: [&[T]; MAX_TAPS] = [&[]; MAX_TAPS];
                    for (line, i) in lines.iter_mut().zip(lo..hi) {
                        let pr = r - i;
                        *line = &parts[(pr * PARTIALS + s) * vw..(pr * PARTIALS + s + 1) * vw];
                    }
                    combine_lines(&lines[..hi - lo], &taps[lo..hi], &mut cols[s * vw..(s + 1) * vw]);
                }
                // Along the row.
                for s in 0..PARTIALS {
                    correlate_line_adjoint(
                        &cols[s * vw..(s + 1) * vw],
                        taps,
                        padded,
                        &mut full[s * w..(s + 1) * w],
                    );
                }
                debug_assert_eq!(vw + n - 1, w);
                let (a, b) = (&self.a[r * w..(r + 1) * w], &self.b[r * w..(r + 1) * w]);
                let line = |s: usize| &full[s * w..(s + 1) * w];
                let (dma, dmb, ds, dab) = (line(0), line(1), line(2), line(3));
                for x in 0..w {
                    ga[x] = dma[x] + two * a[x] * ds[x] + b[x] * dab[x];
                    gb[x] = dmb[x] + two * b[x] * ds[x] + a[x] * dab[x];
                }
            },
        );
    }
}

/// The SSIM map of one output row from its statistics (the `STATS` lines of `vw` in `stats`, the map
/// written to `map`); its sum in float64. With `parts`, also the partial maps times `scale`, as
/// `PARTIALS` lines of `vw`. The loops hold no reduction, so they vectorise; the sum runs after them.
#[inline]
fn pointwise<T: Real>(stats: &[T], map: &mut [T], c1: T, c2: T, scale: T, parts: Option<&mut [T]>) -> f64 {
    let vw = map.len();
    let line = |s: usize| &stats[s * vw..(s + 1) * vw];
    let (ma, mb, sa, sb, sab) = (line(0), line(1), line(2), line(3), line(4));
    let two = T::ONE + T::ONE;
    match parts {
        None => {
            for x in 0..vw {
                let (a1, a2, b1, b2) = terms(ma[x], mb[x], sa[x], sb[x], sab[x], c1, c2);
                map[x] = (a1 * a2) / (b1 * b2);
            }
        }
        Some(parts) => {
            let (pma, rest) = parts[..PARTIALS * vw].split_at_mut(vw);
            let (pmb, rest) = rest.split_at_mut(vw);
            let (ps, pab) = rest.split_at_mut(vw);
            for x in 0..vw {
                let (a1, a2, b1, b2) = terms(ma[x], mb[x], sa[x], sb[x], sab[x], c1, c2);
                let d = b1 * b2;
                let s = (a1 * a2) / d;
                map[x] = s;
                let shared = two * (a2 - a1) / d;
                let spread = two * s * (T::ONE / b1 - T::ONE / b2);
                pma[x] = scale * (mb[x] * shared - ma[x] * spread);
                pmb[x] = scale * (ma[x] * shared - mb[x] * spread);
                ps[x] = -scale * s / b2;
                pab[x] = scale * two * a1 / d;
            }
        }
    }
    map.iter().fold(0.0, |acc, v| acc + v.to_f64())
}

/// `(A1, A2, B1, B2)` of the module docs from one pixel's statistics.
#[inline(always)]
fn terms<T: Real>(ma: T, mb: T, sa: T, sb: T, sab: T, c1: T, c2: T) -> (T, T, T, T) {
    let two = T::ONE + T::ONE;
    let mab = ma * mb;
    let (a1, a2) = (two * mab + c1, two * (sab - mab) + c2);
    let (b1, b2) = (ma * ma + mb * mb + c1, (sa - ma * ma) + (sb - mb * mb) + c2);
    (a1, a2, b1, b2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_util::{assert_gradient, uniform};

    fn gaussian(n: usize, sigma: f64) -> Vec<f64> {
        let half = (n - 1) as f64 / 2.0;
        let k: Vec<f64> =
            (0..n).map(|i| (-((i as f64 - half).powi(2)) / (2.0 * sigma * sigma)).exp()).collect();
        let sum: f64 = k.iter().sum();
        k.into_iter().map(|v| v / sum).collect()
    }

    /// A smooth pattern with noise on it, in [0.2, 1).
    fn smooth_noise(len: usize, seed: u64) -> Vec<f64> {
        uniform(len, seed)
            .iter()
            .enumerate()
            .map(|(i, u)| 0.5 + 0.3 * ((i as f64) * 0.37).sin() + 0.2 * u)
            .collect()
    }

    /// The definition, one window at a time.
    fn naive(a: &[f64], b: &[f64], h: usize, w: usize, k: &[f64], c1: f64, c2: f64) -> f64 {
        let n = k.len();
        let (vh, vw) = (h - n + 1, w - n + 1);
        let mut total = 0.0;
        for r in 0..vh {
            for c in 0..vw {
                let [mut ma, mut mb, mut sa, mut sb, mut sab] = [0.0; 5];
                for i in 0..n {
                    for j in 0..n {
                        let g = k[i] * k[j];
                        let (x, y) = (a[(r + i) * w + c + j], b[(r + i) * w + c + j]);
                        ma += g * x;
                        mb += g * y;
                        sa += g * x * x;
                        sb += g * y * y;
                        sab += g * x * y;
                    }
                }
                let (va, vb, cov) = (sa - ma * ma, sb - mb * mb, sab - ma * mb);
                total +=
                    ((2.0 * ma * mb + c1) * (2.0 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2));
            }
        }
        total / (vh * vw) as f64
    }

    #[test]
    fn matches_the_definition_and_identical_images_give_one() {
        let (h, w) = (14, 19);
        let k = gaussian(5, 1.2);
        let (a, b) = (smooth_noise(2 * h * w, 1), smooth_noise(2 * h * w, 2));
        let win = SsimWindow { taps: &k, c1: 1e-4, c2: 9e-4 };
        let got = ssim(&a, &b, Planes { planes: 2, height: h, width: w }, &win, false).unwrap();
        for i in 0..2 {
            let want = naive(&a[i * h * w..], &b[i * h * w..], h, w, &k, 1e-4, 9e-4);
            assert!((got.values[i] - want).abs() < 1e-13, "{} vs {want}", got.values[i]);
        }
        let same = ssim(&a, &a, Planes { planes: 2, height: h, width: w }, &win, true).unwrap();
        assert!(same.values.iter().all(|v| (v - 1.0).abs() < 1e-14));
        assert!(got.grad.is_none() && same.grad.is_some());
    }

    #[test]
    fn gradient_matches_central_differences() {
        let (h, w) = (12, 15);
        let k = gaussian(5, 1.2);
        let shape = Planes { planes: 1, height: h, width: w };
        let (a, b) = (smooth_noise(h * w, 3), smooth_noise(h * w, 4));
        let win = SsimWindow { taps: &k, c1: 1e-4, c2: 9e-4 };
        let (ga, gb) = ssim(&a, &b, shape, &win, true).unwrap().grad.unwrap();
        let value = |x: &[Vec<f64>]| ssim(&x[0], &x[1], shape, &win, false).unwrap().values[0];
        assert_gradient(value, &[a, b], &[&ga, &gb], [0, 7, 3 * w + 4, 6 * w + 7, h * w - 1], 1e-6, 1e-8);
    }

    #[test]
    fn float32_agrees_with_float64_and_any_thread_count_gives_the_same_bits() {
        let (h, w) = (40, 53);
        let k = gaussian(11, 1.5);
        let shape = Planes { planes: 2, height: h, width: w };
        let (a, b) = (smooth_noise(2 * h * w, 5), smooth_noise(2 * h * w, 6));
        let want = ssim(&a, &b, shape, &SsimWindow { taps: &k, c1: 1e-4, c2: 9e-4 }, true).unwrap();
        let f = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let k32 = f(&k);
        let win32 = SsimWindow { taps: &k32, c1: 1e-4f32, c2: 9e-4f32 };
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| ssim(&f(&a), &f(&b), shape, &win32, true).unwrap())
        };
        let one = run(1);
        assert_eq!(one, run(3));
        for (got, want) in one.values.iter().zip(&want.values) {
            assert!((*got as f64 - want).abs() < 1e-5);
        }
        let (ga, _) = one.grad.unwrap();
        let (wa, _) = want.grad.unwrap();
        let scale = wa.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(ga.iter().zip(&wa).all(|(g, w)| (*g as f64 - w).abs() < 1e-3 * scale));
    }

    #[test]
    fn images_smaller_than_the_window_or_of_the_wrong_size_are_refused() {
        let k = [0.25f32, 0.5, 0.25];
        let win = SsimWindow { taps: &k, c1: 1e-4, c2: 9e-4 };
        let err = ssim(&[0f32; 4], &[0f32; 4], Planes { planes: 1, height: 2, width: 2 }, &win, false);
        assert!(err.unwrap_err().to_string().contains("at least 3×3"));
        let err = ssim(&[0f32; 20], &[0f32; 19], Planes { planes: 1, height: 4, width: 5 }, &win, false);
        assert!(err.unwrap_err().to_string().contains("19 values"));
    }
}

//! The relief prior on rendered depth (`loss.depth_tv`) and its gradient.
//!
//! From the rendered expected depth `D` and opacity `α` of a batch of views: the mean depth
//! `D̄ = D / max(α, α_min)` over the opaque pixels (`α > α_min`), made scale-free by its median `m` over
//! every opaque pixel of the batch (the lower median, as torch's `median`), `v = D̄ / m`; the value is
//! the mean of `|v_p − v_q|` over horizontally adjacent pairs of opaque pixels plus the same mean over
//! vertical pairs (a direction without pairs adds 0; no opaque pixel gives 0).
//!
//! The gradient follows `v` through `D̄` and through `m` alike: the value is homogeneous of degree −1
//! in `m`, so `∂value/∂m = −value / m`, which reaches the one pixel the median is. `|·|` has derivative 0
//! at 0, as in torch.

use rayon::prelude::*;

use super::{line_sum, ordered_sum, Planes, Real};

/// The prior's value and, when asked for, its gradient with respect to `D` and `α`.
#[derive(Debug, Clone, PartialEq)]
pub struct Relief<T> {
    pub value: T,
    pub grad: Option<(Vec<T>, Vec<T>)>,
}

/// The relief prior of `shape.planes` views (module docs); `with_grad` adds its gradient.
pub fn depth_variation<T: Real>(
    depth: &[T],
    alpha: &[T],
    shape: Planes,
    min_alpha: T,
    with_grad: bool,
) -> crate::Result<Relief<T>> {
    shape.check("depth variation", &[depth, alpha])?;
    let (w, h, len) = (shape.width, shape.height, depth.len());
    let zero =
        || Relief { value: T::ZERO, grad: with_grad.then(|| (vec![T::ZERO; len], vec![T::ZERO; len])) };
    if len == 0 {
        return Ok(zero());
    }
    // Every pass is a loop over whole rows, in parallel over rows, that vectorises: the opaque mask is
    // held as 1 and 0 and multiplies, instead of a branch per pixel (a render's mask edges are where a
    // branch would mispredict).
    let line = |r: usize| r * w..(r + 1) * w;
    let flag = |b: bool| if b { T::ONE } else { T::ZERO };
    let mut v = vec![T::ZERO; len]; // D̄ until the median is known, then D̄ / m
    let mut opaque = vec![T::ZERO; len];
    v.par_chunks_mut(w).zip(opaque.par_chunks_mut(w)).enumerate().for_each(|(r, (mean, o))| {
        let (d, a) = (&depth[line(r)], &alpha[line(r)]);
        for c in 0..w {
            mean[c] = d[c] / if a[c] > min_alpha { a[c] } else { min_alpha };
            o[c] = flag(a[c] > min_alpha);
        }
    });
    let Some((m, at)) = lower_median(&v, &opaque) else {
        return Ok(zero());
    };
    v.par_chunks_mut(w).for_each(move |row| row.iter_mut().for_each(|x| *x = *x / m));
    // Row r of the batch (view r / h, line r % h) pairs with the row below when r % h + 1 < h.
    let below = |r: usize| (r % h + 1 < h).then(|| line(r + 1));
    let per_row: Vec<[f64; 4]> = (0..shape.planes * h)
        .into_par_iter()
        .map_init(
            || vec![T::ZERO; 2 * w],
            |scratch, r| {
                let (diff, pairs) = scratch.split_at_mut(w);
                let (o, x) = (&opaque[line(r)], &v[line(r)]);
                let mut acc = [0.0; 4]; // Σ|Δx|, #x, Σ|Δy|, #y
                for c in 0..w - 1 {
                    let k = o[c] * o[c + 1];
                    diff[c] = k * abs(x[c] - x[c + 1]);
                    pairs[c] = k;
                }
                (acc[0], acc[1]) = (line_sum(&diff[..w - 1]), line_sum(&pairs[..w - 1]));
                if let Some(next) = below(r) {
                    let (ob, xb) = (&opaque[next.clone()], &v[next]);
                    for c in 0..w {
                        let k = o[c] * ob[c];
                        diff[c] = k * abs(x[c] - xb[c]);
                        pairs[c] = k;
                    }
                    (acc[2], acc[3]) = (line_sum(diff), line_sum(pairs));
                }
                acc
            },
        )
        .collect();
    let total = |i: usize| ordered_sum(per_row.iter().map(|acc| acc[i]));
    let (nx, ny) = (total(1), total(3));
    let term = |sum: f64, count: f64| if count > 0.0 { sum / count } else { 0.0 };
    let value = term(total(0), nx) + term(total(2), ny);
    if !with_grad {
        return Ok(Relief { value: T::from_f64(value), grad: None });
    }
    // ∂value/∂D̄ per pixel, gathered from the pairs it is in (each row writes only its own entries):
    // sign(v_p − v_q) over the direction's pair count, over m; the median's pixel also gets −value/m;
    // then through D̄ = D / max(α, α_min) to D and, where opaque, to α.
    let weight = |count: f64| T::from_f64(if count > 0.0 { 1.0 / count } else { 0.0 }) / m;
    let (wx, wy) = (weight(nx), weight(ny));
    let median_term = -T::from_f64(value) / m;
    let mut grad_depth = vec![T::ZERO; len];
    let mut grad_alpha = vec![T::ZERO; len];
    grad_depth.par_chunks_mut(w).zip(grad_alpha.par_chunks_mut(w)).enumerate().for_each_init(
        || vec![T::ZERO; w],
        |right, (r, (g, ga))| {
            let (o, x) = (&opaque[line(r)], &v[line(r)]);
            // right[c]: the pair (c, c + 1)'s sign, which pixel c gains and pixel c + 1 loses.
            for c in 0..w - 1 {
                right[c] = o[c] * o[c + 1] * sign(x[c] - x[c + 1]);
            }
            g[0] = wx * right[0];
            for c in 1..w - 1 {
                g[c] = wx * (right[c] - right[c - 1]);
            }
            g[w - 1] = -wx * right[w - 2];
            let above = (r % h > 0).then(|| line(r - 1));
            for next in [below(r), above].into_iter().flatten() {
                let (on, xn) = (&opaque[next.clone()], &v[next]);
                for c in 0..w {
                    g[c] += wy * (o[c] * on[c] * sign(x[c] - xn[c]));
                }
            }
            if line(r).contains(&at) {
                g[at - r * w] += median_term;
            }
            let (d, a) = (&depth[line(r)], &alpha[line(r)]);
            for c in 0..w {
                let k = if a[c] > min_alpha { a[c] } else { min_alpha };
                ga[c] = o[c] * (-g[c] * d[c] / (k * k));
                g[c] = g[c] / k;
            }
        },
    );
    Ok(Relief { value: T::from_f64(value), grad: Some((grad_depth, grad_alpha)) })
}

#[inline(always)]
fn abs<T: Real>(x: T) -> T {
    if x < T::ZERO {
        -x
    } else {
        x
    }
}

/// 1, −1 or 0 as `x` is positive, negative or zero (the derivative of `|x|`, 0 at 0 as in torch).
#[inline(always)]
fn sign<T: Real>(x: T) -> T {
    (if x > T::ZERO { T::ONE } else { T::ZERO }) - (if x < T::ZERO { T::ONE } else { T::ZERO })
}

/// The lower median of `values` over the pixels `keep` marks and the first pixel holding it; None
/// when none is kept. The selection runs on [`Real::order_key`]s, gathered without a branch per pixel.
fn lower_median<T: Real>(values: &[T], keep: &[T]) -> Option<(T, usize)> {
    let mut keys = vec![0i64; values.len()];
    let mut n = 0;
    for (&v, &k) in values.iter().zip(keep) {
        keys[n] = v.order_key();
        n += usize::from(k > T::ZERO);
    }
    if n == 0 {
        return None;
    }
    keys.truncate(n);
    let median = *keys.select_nth_unstable((n - 1) / 2).1;
    let at = values.iter().zip(keep).position(|(&v, &k)| k > T::ZERO && v.order_key() == median)?;
    Some((values[at], at))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_util::{assert_gradient, uniform};

    fn shape(planes: usize, height: usize, width: usize) -> Planes {
        Planes { planes, height, width }
    }

    #[test]
    fn a_tilted_plane_scale_free_and_transparent_pixels_left_out() {
        // Depth 3 + 0.1·x over 8 columns: median 3.3 (the lower middle), each horizontal pair 0.1 apart.
        let (h, w) = (6, 8);
        let tilted: Vec<f64> = (0..h * w).map(|p| 3.0 + 0.1 * (p % w) as f64).collect();
        let ones = vec![1.0; h * w];
        let got = depth_variation(&tilted, &ones, shape(1, h, w), 0.5, false).unwrap().value;
        assert!((got - 0.1 / 3.3).abs() < 1e-12, "{got}");
        let five: Vec<f64> = tilted.iter().map(|d| 5.0 * d).collect();
        let got5 = depth_variation(&five, &ones, shape(1, h, w), 0.5, false).unwrap().value;
        assert!((got5 - got).abs() < 1e-12);
        // The first row transparent, with wild depths: it does not count.
        let (mut d, mut a) = (tilted.clone(), ones.clone());
        for x in 0..w {
            d[x] = 100.0;
            a[x] = 0.1;
        }
        let got = depth_variation(&d, &a, shape(1, h, w), 0.5, true).unwrap();
        assert!((got.value - 0.1 / 3.3).abs() < 1e-12);
        let (gd, ga) = got.grad.unwrap();
        assert!(gd[..w].iter().chain(&ga[..w]).all(|&g| g == 0.0));
        let none = depth_variation(&d, &vec![0.0; h * w], shape(1, h, w), 0.5, true).unwrap();
        assert_eq!(none.value, 0.0);
        assert!(none.grad.unwrap().0.iter().all(|&g| g == 0.0));
    }

    #[test]
    fn pairs_do_not_cross_rows_or_views() {
        // Two 1×2 views: one horizontal pair each, none vertical; view 0 flat, view 1 a step.
        let depth = [1.0f64, 1.0, 1.0, 3.0];
        let got = depth_variation(&depth, &[1.0; 4], shape(2, 1, 2), 0.5, false).unwrap().value;
        assert!((got - 1.0).abs() < 1e-12, "{got}"); // median 1: pairs 0 and 2, mean 1
    }

    #[test]
    fn gradient_matches_central_differences() {
        let (planes, h, w) = (2, 5, 6);
        let n = planes * h * w;
        let alpha: Vec<f64> = uniform(n, 7).iter().map(|u| 0.55 + 0.45 * u).collect();
        let depth: Vec<f64> = alpha.iter().zip(uniform(n, 8)).map(|(a, u)| (2.0 + u) * a).collect();
        let shp = shape(planes, h, w);
        let (gd, ga) = depth_variation(&depth, &alpha, shp, 0.5, true).unwrap().grad.unwrap();
        let value = |x: &[Vec<f64>]| depth_variation(&x[0], &x[1], shp, 0.5, false).unwrap().value;
        assert_gradient(value, &[depth, alpha], &[&gd, &ga], 0..n, 1e-7, 1e-6);
    }
}

//! A branch-free `exp` that LLVM vectorises (the libm call in `f32::exp` blocks vectorisation of the
//! per-pixel loops). Cephes-style: `exp(x) = 2ⁿ·exp(r)`, `|r| ≤ ln2/2`, degree-6 polynomial; within
//! 3 ulp of the correctly rounded result on the range the rasterizer uses.

const LOG2E: f32 = std::f32::consts::LOG2_E;
/// ln 2 split into an exactly representable high part and a correction.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
const P: [f32; 6] = [1.987_569_1e-4, 1.398_199_9e-3, 8.333_452e-3, 4.166_579_6e-2, 0.166_666_65, 0.5];

/// `e^x` for any `x` (clamped to `[-87, 88]`, so very negative inputs give ~1.6e-38; NaN gives e^-87).
#[inline(always)]
pub(crate) fn exp(x: f32) -> f32 {
    // Comparisons rather than `clamp`: one vmaxps/vminps each, no NaN-propagation fix-ups.
    let x = if x > -87.0 { x } else { -87.0 };
    let x = if x < 88.0 { x } else { 88.0 };
    // Fused multiply-adds (one vfmadd each on x86-64-v3): the polynomial is a dependent chain, so
    // fusing halves its latency.
    let n = x.mul_add(LOG2E, 0.5).floor();
    let r = (-n).mul_add(LN2_LO, (-n).mul_add(LN2_HI, x));
    let mut p = P[0];
    for c in &P[1..] {
        p = p.mul_add(r, *c);
    }
    let e = (p * r).mul_add(r, r) + 1.0;
    // 2ⁿ without a float→int conversion (Rust's saturating `as` does not vectorise well): adding
    // 1.5·2²³ puts the integer n + 127 ∈ [0, 254] in the low mantissa bits; shifting by 23 moves it into
    // the exponent field and pushes every other bit out.
    let biased = (n + (127.0 + 12_582_912.0)).to_bits();
    e * f32::from_bits(biased << 23)
}

#[cfg(test)]
mod tests {
    #[test]
    fn exp_matches_libm() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -87.0 + 88.0 * 2.0 * i as f32 / 200_000.0 - 0.0;
            let x = x.min(88.0);
            let want = (x as f64).exp();
            let got = super::exp(x) as f64;
            worst = worst.max(((got - want) / want).abs());
        }
        assert!(worst < 3.0 * f32::EPSILON as f64, "worst relative error {worst}");
        assert_eq!(super::exp(0.0), 1.0);
        assert!(super::exp(-1e30) >= 0.0 && super::exp(-1e30) < 1e-37);
        assert!(super::exp(f32::NAN).is_finite() && super::exp(1e30).is_finite());
    }
}

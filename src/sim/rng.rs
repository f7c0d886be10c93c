//! A small counter-seeded generator (SplitMix64). Each (seed, stream, substream) triple gets an
//! independent sequence, which is what makes the simulator's output independent of rayon's scheduling:
//! a pixel row draws from the stream of its own (frame, row) pair, whichever thread runs it.

/// SplitMix64 finaliser: a bijective 64-bit mixer with good avalanche.
#[inline]
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

const GOLDEN: u64 = 0x9e37_79b9_7f4a_7c15;

/// SplitMix64 stream: fast, statistically sound for simulation (not cryptographic).
#[derive(Debug, Clone)]
pub struct Rng {
    state: u64,
}

impl Rng {
    /// The stream for `(seed, stream, substream)`; distinct triples give unrelated sequences.
    pub fn new(seed: u64, stream: u64, substream: u64) -> Self {
        let s = mix(mix(mix(seed ^ GOLDEN) ^ stream.wrapping_mul(GOLDEN)) ^ substream);
        Rng { state: s }
    }

    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(GOLDEN);
        mix(self.state)
    }

    /// Uniform in [0, 1) with 53 random bits.
    #[inline]
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Standard normal (Box–Muller; one of the pair is discarded to keep the stream stateless).
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform(); // (0, 1]: ln stays finite
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// Poisson count with mean `lambda`, by inversion of the CDF on pieces of mean ≤ 30 (a sum of
    /// Poisson variables is Poisson; the pieces keep `exp(−λ)` far from underflow). Cost ∝ `lambda`,
    /// fine for sensor noise.
    pub fn poisson(&mut self, lambda: f64) -> u64 {
        const PIECE: f64 = 30.0;
        let mut total = 0u64;
        let mut rest = lambda.max(0.0);
        while rest > 0.0 {
            let l = rest.min(PIECE);
            rest -= l;
            let u = self.uniform();
            let mut p = (-l).exp();
            let mut cdf = p;
            let mut k = 0u32;
            while u >= cdf && p > 0.0 {
                k += 1;
                p *= l / f64::from(k);
                cdf += p;
            }
            total += u64::from(k);
        }
        total
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_reproducible_and_distinct() {
        let a: Vec<u64> = (0..4)
            .map({
                let mut r = Rng::new(7, 1, 2);
                move |_| r.next_u64()
            })
            .collect();
        let b: Vec<u64> = (0..4)
            .map({
                let mut r = Rng::new(7, 1, 2);
                move |_| r.next_u64()
            })
            .collect();
        let c = Rng::new(7, 2, 1).next_u64();
        assert_eq!(a, b);
        assert_ne!(a[0], c);
    }

    #[test]
    fn moments_are_right() {
        let mut r = Rng::new(1, 0, 0);
        let n = 200_000;
        let (mut su, mut sn, mut sn2, mut sp) = (0.0, 0.0, 0.0, 0.0);
        for _ in 0..n {
            su += r.uniform();
            let z = r.normal();
            sn += z;
            sn2 += z * z;
            sp += r.poisson(0.7) as f64;
        }
        let n = f64::from(n);
        assert!((su / n - 0.5).abs() < 0.005);
        assert!((sn / n).abs() < 0.01);
        assert!((sn2 / n - 1.0).abs() < 0.02);
        assert!((sp / n - 0.7).abs() < 0.01);
        // Large means (pieced): mean and variance both ≈ λ.
        let big: Vec<f64> = (0..2000).map(|_| r.poisson(1000.0) as f64).collect();
        let mean = big.iter().sum::<f64>() / 2000.0;
        let var = big.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 1999.0;
        assert!((mean - 1000.0).abs() < 3.0, "{mean}");
        assert!((var / 1000.0 - 1.0).abs() < 0.15, "{var}");
    }
}

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

    /// Poisson count with mean `lambda` by inversion of the CDF. Meant for the small means of sensor
    /// noise per pixel and frame (the loop runs about `lambda` + 1 times).
    pub fn poisson(&mut self, lambda: f64) -> u32 {
        if lambda <= 0.0 {
            return 0;
        }
        let u = self.uniform();
        let mut p = (-lambda).exp();
        let mut cdf = p;
        let mut k = 0u32;
        while u >= cdf && p > 0.0 {
            k += 1;
            p *= lambda / f64::from(k);
            cdf += p;
        }
        k
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
            sp += f64::from(r.poisson(0.7));
        }
        let n = f64::from(n);
        assert!((su / n - 0.5).abs() < 0.005);
        assert!((sn / n).abs() < 0.01);
        assert!((sn2 / n - 1.0).abs() < 0.02);
        assert!((sp / n - 0.7).abs() < 0.01);
    }
}

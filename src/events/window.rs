//! The paper's §3.1 window sampler: random end index and window length, seeded.
//!
//! Windows are counted in events, not time, and are half-open index ranges `[start, end)` inside an
//! event index range (a chunk, or a sliding window of chunks). Two modes:
//!
//! - [`WindowMode::Paper`] (default), §3.1: with `N` events in the range, `max_n_winsize` is clamped to
//!   `N`; `end ~ U{max, …, N}` (relative to the range start) and `w ~ U{min, …, max}`, both inclusive;
//!   `start = end − w ≥ 0`. An impossible `min_n_winsize` is an [`Error::Invalid`] that says the numbers.
//! - [`WindowMode::Reference`], the public IncEventGS code: candidate ends `linspace(10, N − 10, seg_num)`
//!   truncated to integers, ends `≤ max` (or `> N`, which only happens for tiny `N`) dropped; each call
//!   picks `batch` distinct candidates in random order and gives each `w ~ U{min, …, max − 1}` (just `min`
//!   when `min == max`). `max` is not clamped (the code does not clamp; too few events leave no candidate,
//!   which is an error here where the code asserts).
//!
//! Randomness comes from [`SplitMix64`], a fixed, tiny generator: the same seed gives the same windows on
//! every platform and for any thread count (sampling is sequential and cheap).

use std::ops::Range;

use crate::error::{Error, Result};

/// SplitMix64 (Steele, Lea & Flood 2014): a 64-bit state, full period, passes BigCrush. Chosen because it
/// is a few lines with no dependency and bit-identical everywhere.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        SplitMix64 { state: seed }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform integer in `[0, n)`, `n > 0`, without modulo bias (Lemire's multiply-and-reject).
    pub fn below(&mut self, n: u64) -> u64 {
        debug_assert!(n > 0);
        let mut m = u128::from(self.next_u64()) * u128::from(n);
        if (m as u64) < n {
            let threshold = n.wrapping_neg() % n;
            while (m as u64) < threshold {
                m = u128::from(self.next_u64()) * u128::from(n);
            }
        }
        (m >> 64) as u64
    }

    /// Uniform integer in `[lo, hi]` (inclusive), `lo ≤ hi`.
    pub fn between(&mut self, lo: usize, hi: usize) -> usize {
        lo + self.below((hi - lo) as u64 + 1) as usize
    }
}

/// How end indices and lengths are drawn (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WindowMode {
    Paper,
    Reference { seg_num: usize },
}

/// Draws batches of event windows `[start, end)` from a fixed event index range.
#[derive(Debug, Clone)]
pub struct WindowSampler {
    range: Range<usize>,
    min_w: usize,
    /// After clamping (paper mode).
    max_w: usize,
    mode: WindowMode,
    /// Reference mode: surviving candidate ends relative to `range.start`, permuted in place by sampling.
    candidates: Vec<usize>,
    rng: SplitMix64,
}

impl WindowSampler {
    pub fn new(range: Range<usize>, min_w: usize, max_w: usize, mode: WindowMode, seed: u64) -> Result<Self> {
        let n = range.len();
        let where_ = format!("events [{}, {})", range.start, range.end);
        if min_w == 0 {
            return Err(Error::Invalid("window sampler: min_n_winsize must be at least 1 event".into()));
        }
        if min_w > max_w {
            return Err(Error::Invalid(format!(
                "window sampler: min_n_winsize = {min_w} is larger than max_n_winsize = {max_w}"
            )));
        }
        let mut sampler =
            WindowSampler { range, min_w, max_w, mode, candidates: Vec::new(), rng: SplitMix64::new(seed) };
        match mode {
            WindowMode::Paper => {
                sampler.max_w = max_w.min(n);
                if min_w > n {
                    return Err(Error::Invalid(format!(
                        "window sampler: min_n_winsize = {min_w} events cannot be met: \
                         only {n} events in {where_}"
                    )));
                }
            }
            WindowMode::Reference { seg_num } => {
                sampler.candidates = reference_ends(n, seg_num, max_w);
                if sampler.candidates.is_empty() {
                    return Err(Error::Invalid(format!(
                        "window sampler (reference mode): no candidate end in \
                         linspace(10, {n} - 10, {seg_num}) is above max_n_winsize = {max_w} and within the {n} events in {where_}"
                    )));
                }
            }
        }
        Ok(sampler)
    }

    /// The effective `(min, max)` window size in events (max after clamping).
    pub fn sizes(&self) -> (usize, usize) {
        (self.min_w, self.max_w)
    }

    /// Number of distinct candidate ends (reference mode; 0 in paper mode).
    pub fn n_candidates(&self) -> usize {
        self.candidates.len()
    }

    /// Draw `batch` windows as absolute event index ranges `(start, end)`.
    pub fn sample(&mut self, batch: usize) -> Result<Vec<(usize, usize)>> {
        let base = self.range.start;
        let (min_w, max_w) = (self.min_w, self.max_w);
        match self.mode {
            WindowMode::Paper => {
                let n = self.range.len();
                Ok((0..batch)
                    .map(|_| {
                        let end = self.rng.between(max_w, n);
                        let w = self.rng.between(min_w, max_w);
                        (base + end - w, base + end)
                    })
                    .collect())
            }
            WindowMode::Reference { .. } => {
                let k = self.candidates.len();
                if batch > k {
                    return Err(Error::Invalid(format!(
                        "window sampler (reference mode): batch of {batch} windows requested but only {k} \
                         distinct candidate ends exist (raise seg_num or lower the batch)"
                    )));
                }
                // Partial Fisher–Yates: the first `batch` slots become a uniform random ordered subset.
                for i in 0..batch {
                    let j = self.rng.between(i, k - 1);
                    self.candidates.swap(i, j);
                }
                let hi = max_w.max(min_w + 1) - 1;
                Ok((0..batch)
                    .map(|i| {
                        let end = self.candidates[i];
                        let w = self.rng.between(min_w, hi);
                        (base + end - w, base + end)
                    })
                    .collect())
            }
        }
    }
}

/// `linspace(10, n − 10, seg_num)` truncated toward zero as numpy's `astype(int)` does, keeping ends in
/// `(max_w, n]`.
fn reference_ends(n: usize, seg_num: usize, max_w: usize) -> Vec<usize> {
    let (a, b) = (10.0, n as f64 - 10.0);
    let step = if seg_num > 1 { (b - a) / (seg_num - 1) as f64 } else { 0.0 };
    (0..seg_num)
        .map(|i| if i + 1 == seg_num && seg_num > 1 { b } else { a + i as f64 * step })
        .map(|v| v.trunc() as i64)
        .filter(|&e| e > max_w as i64 && e <= n as i64)
        .map(|e| e as usize)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_paper(ws: &[(usize, usize)], range: Range<usize>, min_w: usize, max_w: usize) {
        for &(s, e) in ws {
            assert!(range.start <= s && e <= range.end, "({s}, {e}) outside {range:?}");
            assert!((min_w..=max_w).contains(&(e - s)), "length {} not in [{min_w}, {max_w}]", e - s);
            assert!(e - range.start >= max_w, "end {e} below start + max");
        }
    }

    #[test]
    fn splitmix_reference_values() {
        // First outputs for seed 1234567, as listed by Rosetta Code's "Pseudo-random numbers/Splitmix64".
        let mut r = SplitMix64::new(1234567);
        let got: Vec<u64> = (0..5).map(|_| r.next_u64()).collect();
        assert_eq!(
            got,
            [
                6457827717110365317,
                3203168211198807973,
                9817491932198370423,
                4593380528125082431,
                16408922859458223821
            ]
        );
    }

    #[test]
    fn below_is_uniform_and_in_range() {
        let mut r = SplitMix64::new(7);
        let mut hist = [0u32; 6];
        for _ in 0..60_000 {
            hist[r.below(6) as usize] += 1;
        }
        // Each bin expects 10 000 with sd ≈ 91; 6 sd is a bound that never fails for a correct generator.
        assert!(hist.iter().all(|&h| (9_450..=10_550).contains(&h)), "{hist:?}");
        assert_eq!(r.between(5, 5), 5);
    }

    #[test]
    fn paper_windows_respect_bounds_and_cover_extremes() {
        let mut s = WindowSampler::new(100..1100, 10, 200, WindowMode::Paper, 1).unwrap();
        let ws = s.sample(20_000).unwrap();
        check_paper(&ws, 100..1100, 10, 200);
        assert!(ws.iter().any(|&(s, e)| e - s == 10) && ws.iter().any(|&(s, e)| e - s == 200));
        assert!(ws.iter().any(|&(_, e)| e == 1100) && ws.iter().any(|&(_, e)| e == 300));
    }

    #[test]
    fn max_larger_than_range_is_clamped() {
        let mut s = WindowSampler::new(0..50, 5, 1000, WindowMode::Paper, 3).unwrap();
        assert_eq!(s.sizes(), (5, 50));
        let ws = s.sample(100).unwrap();
        check_paper(&ws, 0..50, 5, 50);
        assert!(ws.iter().all(|&(_, e)| e == 50));
    }

    #[test]
    fn min_larger_than_range_is_a_clear_error() {
        let e = WindowSampler::new(10..40, 31, 100, WindowMode::Paper, 0).unwrap_err().to_string();
        assert!(e.contains("min_n_winsize = 31") && e.contains("only 30 events in events [10, 40)"), "{e}");
        let e = WindowSampler::new(5..5, 1, 1, WindowMode::Paper, 0).unwrap_err().to_string();
        assert!(e.contains("only 0 events"), "{e}");
        let e = WindowSampler::new(0..9, 0, 3, WindowMode::Paper, 0).unwrap_err().to_string();
        assert!(e.contains("at least 1"), "{e}");
        let e = WindowSampler::new(0..9, 4, 3, WindowMode::Paper, 0).unwrap_err().to_string();
        assert!(e.contains("larger than max_n_winsize = 3"), "{e}");
    }

    #[test]
    fn min_equal_max_and_tiny_ranges() {
        let mut s = WindowSampler::new(0..1000, 64, 64, WindowMode::Paper, 9).unwrap();
        assert!(s.sample(50).unwrap().iter().all(|&(a, b)| b - a == 64));
        let mut s = WindowSampler::new(7..8, 1, 1, WindowMode::Paper, 9).unwrap();
        assert_eq!(s.sample(3).unwrap(), vec![(7, 8); 3]);
        assert!(s.sample(0).unwrap().is_empty());
    }

    #[test]
    fn same_seed_same_windows() {
        let draw = |seed| WindowSampler::new(0..10_000, 5, 500, WindowMode::Paper, seed).unwrap().sample(64);
        assert_eq!(draw(42).unwrap(), draw(42).unwrap());
        assert_ne!(draw(42).unwrap(), draw(43).unwrap());
    }

    #[test]
    fn reference_candidates_follow_linspace() {
        // linspace(10, 90, 5) = 10, 30, 50, 70, 90; ends <= 40 dropped.
        assert_eq!(reference_ends(100, 5, 40), vec![50, 70, 90]);
        // linspace(10, 1000 - 10, 4) = 10, 336.67, 663.33, 990 → truncated.
        assert_eq!(reference_ends(1000, 4, 0), vec![10, 336, 663, 990]);
        assert_eq!(reference_ends(1000, 1, 0), vec![10]);
        // Tiny N: linspace runs backwards past N; those ends are dropped.
        assert_eq!(reference_ends(12, 3, 0), vec![10, 6, 2]);
        assert_eq!(reference_ends(5, 3, 0), vec![2]);
    }

    #[test]
    fn reference_mode_draws_distinct_candidates() {
        let mut s =
            WindowSampler::new(1000..2000, 20, 100, WindowMode::Reference { seg_num: 11 }, 5).unwrap();
        // Candidates linspace(10, 990, 11) = 10, 108, 206, ... > 100 → 10 of them.
        assert_eq!(s.n_candidates(), 10);
        for _ in 0..50 {
            let ws = s.sample(10).unwrap();
            let mut ends: Vec<usize> = ws.iter().map(|w| w.1 - 1000).collect();
            ends.sort_unstable();
            assert_eq!(ends, (1..11).map(|i| 10 + 98 * i).collect::<Vec<_>>());
            assert!(ws.iter().all(|&(a, b)| (20..100).contains(&(b - a)) && a >= 1000));
        }
        let e = s.sample(11).unwrap_err().to_string();
        assert!(e.contains("only 10 distinct"), "{e}");
        let mut s = WindowSampler::new(0..1000, 30, 30, WindowMode::Reference { seg_num: 4 }, 5).unwrap();
        assert!(s.sample(3).unwrap().iter().all(|&(a, b)| b - a == 30));
        let e = WindowSampler::new(0..100, 5, 95, WindowMode::Reference { seg_num: 4 }, 0).unwrap_err();
        assert!(e.to_string().contains("no candidate end"), "{e}");
    }
}

//! Helpers for the crate's unit tests.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};

/// A fresh directory under the system temp dir, removed with its contents when dropped, so tests
/// that write files leave nothing behind (and parallel tests never share one).
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        static NEXT: AtomicUsize = AtomicUsize::new(0);
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("evgs-{tag}-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        TempDir(dir)
    }

    /// The path of `name` inside the directory, as a string (the readers' and writers' argument).
    pub fn path(&self, name: &str) -> String {
        self.0.join(name).to_string_lossy().into_owned()
    }

    /// Writes `bytes` to `name` inside the directory and returns its path.
    pub fn write(&self, name: &str, bytes: &[u8]) -> String {
        let p = self.path(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// `len` values uniform in [0, 1) from a seeded xorshift generator (the same on every machine).
pub fn uniform(len: usize, seed: u64) -> Vec<f64> {
    let mut s = 0x9e37_79b9_7f4a_7c15_u64 ^ seed.wrapping_mul(0x2545_f491_4f6c_dd1d);
    (0..len)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64
        })
        .collect()
}

/// Asserts that `grads[i][p]` is the central difference (step `eps`, within `tol`) of `value` along
/// element `p` of input `i`, for every input and every `p` in `at`.
pub fn assert_gradient(
    value: impl Fn(&[Vec<f64>]) -> f64,
    inputs: &[Vec<f64>],
    grads: &[&[f64]],
    at: impl IntoIterator<Item = usize> + Clone,
    eps: f64,
    tol: f64,
) {
    for (i, grad) in grads.iter().enumerate() {
        for p in at.clone() {
            let (mut lo, mut hi) = (inputs.to_vec(), inputs.to_vec());
            lo[i][p] -= eps;
            hi[i][p] += eps;
            let fd = (value(&hi) - value(&lo)) / (2.0 * eps);
            assert!(
                (fd - grad[p]).abs() < tol,
                "input {i}, element {p}: {fd} by differences, {} analytic",
                grad[p]
            );
        }
    }
}

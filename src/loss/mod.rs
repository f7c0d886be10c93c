//! Kernels of the SLAM losses that torch runs slowly on two CPU cores, forward and gradient in one
//! pass each: [`ssim`], the SSIM term of eq. 8 (Gaussian window by the separable lines of [`blur`]),
//! and [`relief`], the relief prior on the rendered depth. Torch spent most of these terms' time in
//! the dispatch of a few hundred small element-wise ops and their autograd (docs/ablations.md §81);
//! `evgs.slam.loss` wraps them as autograd functions.

pub mod blur;
pub mod relief;
pub mod ssim;

use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

/// The float types the kernels run on (the SLAM's float32, the tests' float64).
pub trait Real:
    Copy
    + Send
    + Sync
    + Default
    + PartialOrd
    + Add<Output = Self>
    + AddAssign
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    const ZERO: Self;
    const ONE: Self;
    /// `self · a + b` with one rounding.
    fn fma(self, a: Self, b: Self) -> Self;
    fn from_f64(v: f64) -> Self;
    fn to_f64(self) -> f64;
    /// An integer that orders as IEEE 754's total order does (`total_cmp`): a selection on these keys
    /// compares integers, several times faster than a comparator on floats.
    fn order_key(self) -> i64;
    /// Runs `f` on this thread's scratch buffer of at least `len` values (contents unspecified),
    /// which is kept for the next call: the kernels' large intermediates would otherwise be fresh pages
    /// on every call, and the page faults cost a third of an SSIM step.
    fn with_scratch<R>(len: usize, f: impl FnOnce(&mut [Self]) -> R) -> R;
}

macro_rules! impl_real {
    ($t:ty, $signed:ty, $unsigned:ty) => {
        impl Real for $t {
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            #[inline(always)]
            fn fma(self, a: Self, b: Self) -> Self {
                self.mul_add(a, b)
            }
            #[inline(always)]
            fn from_f64(v: f64) -> Self {
                v as $t
            }
            #[inline(always)]
            fn to_f64(self) -> f64 {
                self as f64
            }
            #[inline(always)]
            fn order_key(self) -> i64 {
                // The bits as a signed integer order the positive values; for negative ones the
                // magnitude bits are flipped, so that a larger magnitude orders lower.
                let s = self.to_bits() as $signed;
                (s ^ (((s >> (<$signed>::BITS - 1)) as $unsigned) >> 1) as $signed) as i64
            }
            fn with_scratch<R>(len: usize, f: impl FnOnce(&mut [Self]) -> R) -> R {
                thread_local! {
                    static SCRATCH: std::cell::RefCell<Vec<$t>> = const { std::cell::RefCell::new(Vec::new()) };
                }
                SCRATCH.with(|cell| match cell.try_borrow_mut() {
                    Ok(mut buf) => {
                        if buf.len() < len {
                            buf.resize(len, 0.0);
                        }
                        f(&mut buf[..len])
                    }
                    // Already lent out further up this thread's stack: a fresh buffer.
                    Err(_) => f(&mut vec![0.0; len]),
                })
            }
        }
    };
}

impl_real!(f32, i32, u32);
impl_real!(f64, i64, u64);

/// `planes × height × width` images as one flat slice: checked once, so the kernels index freely.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Planes {
    pub planes: usize,
    pub height: usize,
    pub width: usize,
}

impl Planes {
    pub fn len(&self) -> usize {
        self.planes * self.height * self.width
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// An error naming `what` unless every slice in `inputs` holds exactly these planes.
    pub fn check<T>(&self, what: &str, inputs: &[&[T]]) -> crate::Result<()> {
        for x in inputs {
            if x.len() != self.len() {
                return Err(crate::Error::Invalid(format!(
                    "{what}: {} values are not {} planes of {}×{}",
                    x.len(),
                    self.planes,
                    self.height,
                    self.width
                )));
            }
        }
        Ok(())
    }
}

/// The sum of `line` in float64, through eight running sums of `T` (so the loop vectorises), in a fixed
/// order.
#[inline]
pub(crate) fn line_sum<T: Real>(line: &[T]) -> f64 {
    let mut lanes = [T::ZERO; 8];
    let chunks = line.chunks_exact(8);
    let tail = chunks.remainder();
    for chunk in chunks {
        for (l, &v) in lanes.iter_mut().zip(chunk) {
            *l += v;
        }
    }
    lanes.iter().chain(tail).fold(0.0, |acc, v| acc + v.to_f64())
}

/// The sum of per-row partial sums in row order: the same result whatever rayon's split.
pub(crate) fn ordered_sum(parts: impl IntoIterator<Item = f64>) -> f64 {
    parts.into_iter().fold(0.0, |acc, v| acc + v)
}

#[cfg(test)]
mod tests {
    use super::Real;

    #[test]
    fn order_keys_order_as_the_floats_do() {
        let xs = [-f64::INFINITY, -3.5, -1e-300, -0.0, 0.0, 1e-300, 2.0, 7.25, f64::INFINITY];
        for pair in xs.windows(2) {
            assert!(pair[0].order_key() < pair[1].order_key(), "{pair:?}");
            assert!((pair[0] as f32).order_key() <= (pair[1] as f32).order_key(), "{pair:?}");
        }
        assert!((-2.0f32).order_key() < (-1.0f32).order_key() && 1.0f32.order_key() < 1.5f32.order_key());
    }
}

//! Event streams: the in-memory struct-of-arrays and everything that fills or slices it.

pub mod accumulate;
pub mod aedat4;
pub mod detect;
pub mod evt2;
pub mod evt3;
pub mod index;
pub mod npy;
pub mod raw_header;
pub mod reader;
pub mod text;
pub mod undistort;
pub mod window;
pub mod writer;

use rayon::prelude::*;

use crate::error::{Error, Result};

/// A format decoder fed a file's payload in consecutive pieces, so any file decodes in bounded memory.
pub trait Decoder {
    /// Decode as much of `data` as possible, appending events to `out`. `data` starts at absolute file
    /// offset `offset` (for error messages). Returns the number of bytes consumed; the caller keeps the
    /// unconsumed tail and passes it again at the front of the next piece.
    fn decode(&mut self, data: &[u8], offset: u64, out: &mut Events) -> Result<usize>;

    /// End of file: `tail` is whatever was never consumed (a truncated record is reported here).
    fn finish(&mut self, tail: &[u8], offset: u64, out: &mut Events) -> Result<()>;
}

/// A stream of events as struct-of-arrays. Columns hand to numpy without copying.
///
/// Invariants checked by [`Events::validate`]: equal column lengths, `p ∈ {−1, +1}`, coordinates
/// inside the sensor, and (for the canonical form) `t` non-decreasing.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Events {
    /// Timestamps in microseconds.
    pub t: Vec<i64>,
    pub x: Vec<u16>,
    pub y: Vec<u16>,
    /// Polarity, −1 or +1.
    pub p: Vec<i8>,
    /// Sensor width and height in pixels; 0 when unknown.
    pub width: u32,
    pub height: u32,
}

impl Events {
    pub fn with_capacity(n: usize, width: u32, height: u32) -> Self {
        Events {
            t: Vec::with_capacity(n),
            x: Vec::with_capacity(n),
            y: Vec::with_capacity(n),
            p: Vec::with_capacity(n),
            width,
            height,
        }
    }

    pub fn len(&self) -> usize {
        self.t.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    #[inline]
    pub fn push(&mut self, t: i64, x: u16, y: u16, p: i8) {
        self.t.push(t);
        self.x.push(x);
        self.y.push(y);
        self.p.push(p);
    }

    /// Append `n` zeroed events for a decoder to fill by index (in parallel); returns the old length.
    ///
    /// An empty stream without spare capacity gets fresh zeroed allocations (calloc: the kernel's zero
    /// pages, so no memset and the page faults land on the threads that fill the columns); otherwise
    /// the columns grow by zeroing in parallel (a serial resize would cost as much as decoding).
    pub fn append_zeroed(&mut self, n: usize) -> usize {
        fn grow<T: Copy + Default + Send + Sync>(v: &mut Vec<T>, n: usize) {
            if v.is_empty() && v.capacity() < n {
                *v = vec![T::default(); n];
            } else {
                v.par_extend(rayon::iter::repeat_n(T::default(), n));
            }
        }
        let old = self.len();
        grow(&mut self.t, n);
        grow(&mut self.x, n);
        grow(&mut self.y, n);
        grow(&mut self.p, n);
        old
    }

    /// Mutable column slices of consecutive runs of `counts` events starting at index `from`, for
    /// filling disjoint parts of the output in parallel.
    pub fn split_mut(&mut self, from: usize, counts: impl IntoIterator<Item = usize>) -> Vec<ColumnsMut<'_>> {
        let (mut t, mut x, mut y, mut p) =
            (&mut self.t[from..], &mut self.x[from..], &mut self.y[from..], &mut self.p[from..]);
        let mut parts = Vec::new();
        for n in counts {
            let (t0, t1) = std::mem::take(&mut t).split_at_mut(n);
            let (x0, x1) = std::mem::take(&mut x).split_at_mut(n);
            let (y0, y1) = std::mem::take(&mut y).split_at_mut(n);
            let (p0, p1) = std::mem::take(&mut p).split_at_mut(n);
            parts.push(ColumnsMut { t: t0, x: x0, y: y0, p: p0 });
            (t, x, y, p) = (t1, x1, y1, p1);
        }
        parts
    }

    /// Append the events of `parts` in order, copying them in parallel (a serial gather would cost as
    /// much as the parallel decode that produced them).
    pub fn append_all<'a>(&mut self, parts: impl IntoIterator<Item = &'a Events>) {
        let parts: Vec<&Events> = parts.into_iter().collect();
        let old = self.append_zeroed(parts.iter().map(|e| e.len()).sum());
        let dest = self.split_mut(old, parts.iter().map(|e| e.len()));
        parts.into_par_iter().zip(dest).for_each(|(src, dst)| {
            dst.t.copy_from_slice(&src.t);
            dst.x.copy_from_slice(&src.x);
            dst.y.copy_from_slice(&src.y);
            dst.p.copy_from_slice(&src.p);
        });
    }

    /// Drop events from index `len` on.
    pub fn truncate(&mut self, len: usize) {
        self.t.truncate(len);
        self.x.truncate(len);
        self.y.truncate(len);
        self.p.truncate(len);
    }

    /// Append all events of `other` (sensor size taken as the larger of the two).
    pub fn extend(&mut self, other: &Events) {
        self.t.extend_from_slice(&other.t);
        self.x.extend_from_slice(&other.x);
        self.y.extend_from_slice(&other.y);
        self.p.extend_from_slice(&other.p);
        self.width = self.width.max(other.width);
        self.height = self.height.max(other.height);
    }

    /// Borrow the columns as a view (what the algorithms take, so numpy arrays can be used directly).
    pub fn view(&self) -> EventsView<'_> {
        EventsView { t: &self.t, x: &self.x, y: &self.y, p: &self.p, width: self.width, height: self.height }
    }

    /// See [`EventsView::validate`].
    pub fn validate(&self, source: &str) -> Result<()> {
        self.view().validate(source)
    }
}

/// Mutable slices of a run of events (see [`Events::split_mut`]).
#[derive(Debug)]
pub struct ColumnsMut<'a> {
    pub t: &'a mut [i64],
    pub x: &'a mut [u16],
    pub y: &'a mut [u16],
    pub p: &'a mut [i8],
}

/// Borrowed event columns: an [`Events`] or four numpy arrays seen from Rust without copying.
#[derive(Debug, Clone, Copy)]
pub struct EventsView<'a> {
    pub t: &'a [i64],
    pub x: &'a [u16],
    pub y: &'a [u16],
    pub p: &'a [i8],
    pub width: u32,
    pub height: u32,
}

impl EventsView<'_> {
    pub fn len(&self) -> usize {
        self.t.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// Whether timestamps are non-decreasing.
    pub fn is_sorted(&self) -> bool {
        self.t.windows(2).all(|w| w[0] <= w[1])
    }

    /// Check the invariants; `source` names the data in the error message.
    pub fn validate(&self, source: &str) -> Result<()> {
        let n = self.t.len();
        if self.x.len() != n || self.y.len() != n || self.p.len() != n {
            return Err(Error::Invalid(format!("{source}: event columns have different lengths")));
        }
        for i in 0..n {
            if self.p[i] != 1 && self.p[i] != -1 {
                return Err(Error::format(
                    source,
                    format!("event {i}"),
                    format!("polarity {} is not ±1", self.p[i]),
                ));
            }
            if (self.width > 0 && u32::from(self.x[i]) >= self.width)
                || (self.height > 0 && u32::from(self.y[i]) >= self.height)
            {
                return Err(Error::format(
                    source,
                    format!("event {i}"),
                    format!(
                        "({}, {}) outside the {}x{} sensor",
                        self.x[i], self.y[i], self.width, self.height
                    ),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_catches_bad_polarity_and_coordinates() {
        let mut ev = Events::with_capacity(2, 4, 4);
        ev.push(0, 1, 1, 1);
        assert!(ev.validate("mem").is_ok());
        ev.push(1, 4, 0, 1);
        assert!(ev.validate("mem").unwrap_err().to_string().contains("event 1"));
        ev.x[1] = 0;
        ev.p[1] = 0;
        assert!(ev.validate("mem").unwrap_err().to_string().contains("polarity"));
    }
}

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

use std::mem::MaybeUninit;

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

    /// Reserve room for `counts` more events and hand out the uninitialised column slices of
    /// consecutive runs of `counts` events after the current end, for decoders to fill in parallel;
    /// [`Events::assume_filled`] then appends them.
    ///
    /// Nothing is zeroed: the fresh pages are faulted once, by the thread that writes them, and large
    /// columns are advised as transparent huge pages (see [`reserve_huge`]).
    pub fn spare_parts(&mut self, counts: impl IntoIterator<Item = usize>) -> Vec<ColumnsMut<'_>> {
        let counts: Vec<usize> = counts.into_iter().collect();
        let n = counts.iter().sum();
        let mut t = reserve_huge(&mut self.t, n);
        let mut x = reserve_huge(&mut self.x, n);
        let mut y = reserve_huge(&mut self.y, n);
        let mut p = reserve_huge(&mut self.p, n);
        let mut parts = Vec::with_capacity(counts.len());
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

    /// Reserve room for at least `n` more events (see [`reserve_huge`]).
    pub fn reserve(&mut self, n: usize) {
        reserve_huge(&mut self.t, n);
        reserve_huge(&mut self.x, n);
        reserve_huge(&mut self.y, n);
        reserve_huge(&mut self.p, n);
    }

    /// All spare (reserved, unused) slots of the columns, e.g. to close up gaps between filled runs.
    pub fn spare_mut(&mut self) -> ColumnsMut<'_> {
        ColumnsMut {
            t: self.t.spare_capacity_mut(),
            x: self.x.spare_capacity_mut(),
            y: self.y.spare_capacity_mut(),
            p: self.p.spare_capacity_mut(),
        }
    }

    /// Append the first `n` spare slots as events.
    ///
    /// # Safety
    /// Slots `0..n` of every column of [`Events::spare_parts`] / [`Events::spare_mut`] must have
    /// been written.
    pub unsafe fn assume_filled(&mut self, n: usize) {
        let len = self.len() + n;
        assert!(
            len <= self.t.capacity().min(self.x.capacity()).min(self.y.capacity()).min(self.p.capacity())
        );
        // SAFETY: within capacity (checked) and initialised (the caller's contract).
        unsafe {
            self.t.set_len(len);
            self.x.set_len(len);
            self.y.set_len(len);
            self.p.set_len(len);
        }
    }

    /// Append the events of `parts` in order, copying them in parallel (a serial gather would cost as
    /// much as the parallel decode that produced them).
    pub fn append_all<'a>(&mut self, parts: impl IntoIterator<Item = &'a Events>) {
        let parts: Vec<&Events> = parts.into_iter().collect();
        let n = parts.iter().map(|e| e.len()).sum();
        let dest = self.spare_parts(parts.iter().map(|e| e.len()));
        parts.into_par_iter().zip(dest).for_each(|(src, dst)| dst.copy_from(src.view(), 0..src.len()));
        // SAFETY: every part was copied whole, and the parts cover the first `n` spare slots.
        unsafe { self.assume_filled(n) };
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

/// Uninitialised column slices of a run of events to be written (see [`Events::spare_parts`]).
#[derive(Debug)]
pub struct ColumnsMut<'a> {
    pub t: &'a mut [MaybeUninit<i64>],
    pub x: &'a mut [MaybeUninit<u16>],
    pub y: &'a mut [MaybeUninit<u16>],
    pub p: &'a mut [MaybeUninit<i8>],
}

impl ColumnsMut<'_> {
    /// Write event `k`.
    #[inline(always)]
    pub fn set(&mut self, k: usize, t: i64, x: u16, y: u16, p: i8) {
        self.t[k].write(t);
        self.x[k].write(x);
        self.y[k].write(y);
        self.p[k].write(p);
    }

    /// Write events `range` of `src` to the start of these slices.
    pub fn copy_from(self, src: EventsView<'_>, range: std::ops::Range<usize>) {
        write_slice(self.t, &src.t[range.clone()]);
        write_slice(self.x, &src.x[range.clone()]);
        write_slice(self.y, &src.y[range.clone()]);
        write_slice(self.p, &src.p[range]);
    }
}

/// Copy `src` into the start of `dst` (a memcpy; `<[MaybeUninit<T>]>::write_copy_of_slice` needs a
/// newer Rust than the crate's minimum).
#[inline]
pub fn write_slice<T: Copy>(dst: &mut [MaybeUninit<T>], src: &[T]) {
    for (d, &s) in dst[..src.len()].iter_mut().zip(src) {
        d.write(s);
    }
}

/// Columns at least this large are advised as transparent huge pages: 512× fewer page faults.
const HUGE_MIN_BYTES: usize = 4 << 20;

/// Reserve room for `n` more elements in `v` and return exactly those `n` spare slots.
///
/// A large buffer is advised `MADV_HUGEPAGE` (on Linux; the 2 MiB-aligned interior, before the new
/// pages are touched), so its pages fault in as huge pages where THP is in `madvise` mode. Growth
/// goes through `realloc`, which for large blocks remaps the pages instead of copying them.
pub fn reserve_huge<T>(v: &mut Vec<T>, n: usize) -> &mut [MaybeUninit<T>] {
    let cap = v.capacity();
    v.reserve(n);
    let bytes = v.capacity() * std::mem::size_of::<T>();
    if v.capacity() != cap && bytes >= HUGE_MIN_BYTES {
        advise_huge(v.as_mut_ptr().cast(), bytes);
    }
    &mut v.spare_capacity_mut()[..n]
}

#[cfg(target_os = "linux")]
fn advise_huge(ptr: *mut u8, bytes: usize) {
    const HUGE: usize = 2 << 20;
    let start = (ptr as usize).next_multiple_of(HUGE);
    let end = (ptr as usize + bytes) / HUGE * HUGE;
    if end > start {
        // SAFETY: the range lies inside the allocation; MADV_HUGEPAGE only changes how its pages
        // are backed, never their contents. A failure (THP disabled) just leaves normal pages.
        unsafe { libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE) };
    }
}

#[cfg(not(target_os = "linux"))]
fn advise_huge(_ptr: *mut u8, _bytes: usize) {}

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
    fn spare_parts_fill_after_existing_events_and_large_columns_grow() {
        let mut ev = Events::with_capacity(0, 0, 0);
        ev.push(-1, 9, 9, -1);
        // Large enough for the huge-page advice path (t column > 4 MiB).
        let counts = [3, 0, 700_000];
        let parts = ev.spare_parts(counts);
        assert_eq!(parts.iter().map(|c| c.t.len()).collect::<Vec<_>>(), counts);
        parts.into_par_iter().enumerate().for_each(|(j, mut part)| {
            for k in 0..part.t.len() {
                part.set(k, (j * 10 + k) as i64, k as u16, j as u16, 1);
            }
        });
        // SAFETY: every part was written whole above.
        unsafe { ev.assume_filled(700_003) };
        assert_eq!(ev.len(), 700_004);
        assert_eq!((ev.t[0], ev.t[1], ev.t[3], ev.t[4], ev.y[4]), (-1, 0, 2, 20, 2));
        assert_eq!((ev.t[700_003], ev.x[700_003]), (20 + 699_999, (699_999 % 65_536) as u16));
        let mut all = Events::default();
        all.append_all([&ev, &ev]);
        assert_eq!((all.len(), all.t[700_004], all.p[1_400_007]), (1_400_008, -1, 1));
    }

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

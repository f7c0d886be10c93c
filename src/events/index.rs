//! Chunk index: frame timestamps → half-open event index ranges.
//!
//! Chunk `k` holds the events with `frame_t[k] ≤ t < frame_t[k+1]`, i.e. the index range
//! `[i_k, i_{k+1})` where `i_k` is the first event with `t ≥ frame_t[k]` (a lower-bound binary search).
//! The paper's eq. 5 writes the chunk with strict inequalities on both sides, `t_i < t < t_i + Δt`, which
//! would silently lose every event that lands exactly on a frame timestamp (common with µs clocks and
//! simulated data). The half-open convention makes consecutive chunks tile `[frame_t[0], frame_t[F-1])`
//! with every event in exactly one chunk; events before the first or at/after the last frame timestamp
//! belong to no chunk and are reported by [`ChunkIndex::outside`].

use crate::error::{Error, Result};

/// The event index ranges of the chunks between consecutive frame timestamps.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChunkIndex {
    /// `bounds[k]` = index of the first event with `t ≥ frame_t[k]`; chunk `k` is `bounds[k]..bounds[k+1]`.
    pub bounds: Vec<usize>,
    /// Total number of events indexed.
    pub n_events: usize,
}

impl ChunkIndex {
    /// Index `t` (sorted event timestamps) by `frame_t` (strictly increasing frame timestamps, ≥ 2).
    pub fn new(t: &[i64], frame_t: &[i64]) -> Result<Self> {
        if frame_t.len() < 2 {
            return Err(Error::Invalid(format!(
                "chunk index: need at least 2 frame timestamps to form a chunk, got {}",
                frame_t.len()
            )));
        }
        if let Some(k) = frame_t.windows(2).position(|w| w[0] >= w[1]) {
            return Err(Error::Invalid(format!(
                "chunk index: frame timestamps must be strictly increasing, \
                 but frame {} ({} µs) ≤ frame {} ({} µs)",
                k + 1,
                frame_t[k + 1],
                k,
                frame_t[k]
            )));
        }
        if let Some(i) = t.windows(2).position(|w| w[0] > w[1]) {
            return Err(Error::Invalid(format!(
                "chunk index: event timestamps must be sorted, but event {} ({} µs) < event {} ({} µs)",
                i + 1,
                t[i + 1],
                i,
                t[i]
            )));
        }
        let bounds = frame_t.iter().map(|&f| t.partition_point(|&ti| ti < f)).collect();
        Ok(ChunkIndex { bounds, n_events: t.len() })
    }

    /// Number of chunks (frames − 1).
    pub fn len(&self) -> usize {
        self.bounds.len() - 1
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Event index range of chunk `k`.
    pub fn chunk(&self, k: usize) -> std::ops::Range<usize> {
        self.bounds[k]..self.bounds[k + 1]
    }

    /// Event index range spanned by chunks `first..last` (a sliding window of chunks); `last` exclusive.
    pub fn chunks(&self, first: usize, last: usize) -> std::ops::Range<usize> {
        self.bounds[first]..self.bounds[last]
    }

    /// Events that fall in no chunk: `(before the first frame timestamp, at or after the last)`.
    pub fn outside(&self) -> (usize, usize) {
        (self.bounds[0], self.n_events - self.bounds[self.bounds.len() - 1])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_on_a_boundary_open_the_next_chunk() {
        let t = [0, 5, 10, 10, 15, 20, 25];
        let idx = ChunkIndex::new(&t, &[5, 10, 20]).unwrap();
        assert_eq!(idx.len(), 2);
        assert_eq!(idx.chunk(0), 1..2); // t = 5
        assert_eq!(idx.chunk(1), 2..5); // t = 10, 10, 15 (20 belongs to no chunk: it is the end)
        assert_eq!(idx.chunks(0, 2), 1..5);
        assert_eq!(idx.outside(), (1, 2));
    }

    #[test]
    fn matches_a_linear_scan() {
        let t: Vec<i64> = (0..1000).map(|i| (i * i) % 977 / 3).collect::<Vec<_>>();
        let mut t = t;
        t.sort_unstable();
        let frames = [-5, 0, 17, 100, 101, 250, 400];
        let idx = ChunkIndex::new(&t, &frames).unwrap();
        for k in 0..idx.len() {
            let expect: Vec<usize> =
                (0..t.len()).filter(|&i| frames[k] <= t[i] && t[i] < frames[k + 1]).collect();
            let r = idx.chunk(k);
            assert_eq!(r.clone().collect::<Vec<_>>(), expect, "chunk {k}");
        }
    }

    #[test]
    fn empty_stream_and_empty_chunks() {
        let idx = ChunkIndex::new(&[], &[0, 1, 2]).unwrap();
        assert_eq!(idx.chunk(1), 0..0);
        let idx = ChunkIndex::new(&[3, 4], &[0, 1, 2]).unwrap();
        assert_eq!(idx.chunk(0), 0..0);
        assert_eq!(idx.outside(), (0, 2));
    }

    #[test]
    fn bad_inputs_are_named() {
        let e = ChunkIndex::new(&[0, 1], &[0]).unwrap_err().to_string();
        assert!(e.contains("at least 2"), "{e}");
        let e = ChunkIndex::new(&[0, 1], &[0, 3, 3]).unwrap_err().to_string();
        assert!(e.contains("frame 2 (3 µs) ≤ frame 1"), "{e}");
        let e = ChunkIndex::new(&[0, 2, 1], &[0, 3]).unwrap_err().to_string();
        assert!(e.contains("event 2 (1 µs) < event 1"), "{e}");
    }
}

//! Event frames: `E(x, y) = C_on·n_on − C_off·n_off` over event index ranges, batched.
//!
//! Each window is first reduced to integer per-pixel counts, then turned into floats once per pixel:
//! `n_on − n_off` when there is one C (the paper's case; the frame is `C·Σp` rounded once), the pair
//! `(n_on, n_off)` otherwise. Integer counts make the result exact and independent of how the work is split:
//! windows run in parallel, and when there are fewer windows than threads to keep busy, a large window
//! is cut into fixed-size event sub-ranges counted in parallel and summed in order. Integer sums do not
//! depend on grouping, so the frame is bitwise identical for any thread count (tests compare 1 and 2).
//!
//! Undistortion (optional) uses a per-pixel map (see [`super::undistort`]): counts are kept at the raw
//! sensor pixels and each pixel's value `C_on·n_on − C_off·n_off` is then splatted bilinearly at its
//! undistorted position. That is exactly a bilinear splat of every event, at O(pixels) instead of
//! O(events) cost. Bilinear rather than nearest because rounding to the nearest pixel leaves empty
//! pixels where the lens stretches the image and doubles up where it compresses it — a moiré pattern
//! the event loss would try to explain; the bilinear splat keeps each event's mass at sub-pixel
//! accuracy. Events whose undistorted position falls outside the image (or whose pixel could not be
//! undistorted) are counted per window in [`Frames::dropped`].
//!
//! Downsampling by `2^k` (coarse-to-fine optimisation) sums `2^k × 2^k` pixel blocks; the output is
//! `ceil(W / 2^k) × ceil(H / 2^k)` so no event is lost. With undistortion the splat targets the coarse
//! grid, whose pixel centres sit at `(u + 0.5) / 2^k − 0.5` in full-resolution coordinates `u`.

use rayon::prelude::*;

use super::EventsView;
use crate::error::{Error, Result};

/// A window is split into event sub-ranges of at least this many events (more for large images, so that
/// merging the per-part count buffers stays cheap next to counting).
const MIN_PART_EVENTS: usize = 1 << 20;

/// How events become frame values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameParams {
    pub c_on: f32,
    pub c_off: f32,
    /// Downsampling factor `2^downsample_log2` (0 = full resolution).
    pub downsample_log2: u32,
}

impl Default for FrameParams {
    fn default() -> Self {
        FrameParams { c_on: 1.0, c_off: 1.0, downsample_log2: 0 }
    }
}

/// A batch of event frames.
#[derive(Debug, Clone, PartialEq)]
pub struct Frames {
    /// `(B, height, width)` row-major.
    pub data: Vec<f32>,
    pub width: usize,
    pub height: usize,
    /// Per window: events that landed outside the image after undistortion (always 0 without a map).
    pub dropped: Vec<u64>,
}

/// Output frame size `(width, height)` for a `width × height` sensor: `ceil(size / 2^downsample_log2)`.
pub fn frame_size(width: u32, height: u32, params: FrameParams) -> (usize, usize) {
    let f = 1usize << params.downsample_log2.min(31);
    ((width as usize).div_ceil(f), (height as usize).div_ceil(f))
}

/// Event frames of `windows` (half-open event index ranges) over `ev`; `map` is an undistortion map of
/// the sensor (`2·W·H` interleaved `(u, v)` pixel positions, NaN = invalid).
pub fn accumulate(
    ev: EventsView<'_>,
    windows: &[(usize, usize)],
    params: FrameParams,
    map: Option<&[f32]>,
) -> Result<Frames> {
    let (width, height) = frame_size(ev.width, ev.height, params);
    let mut data = vec![0f32; windows.len() * width * height];
    let dropped = accumulate_into(ev, windows, params, map, &mut data)?;
    Ok(Frames { data, width, height, dropped })
}

/// [`accumulate`] into a caller's buffer of `B × frame_size(..)` floats (fully overwritten). Reusing one
/// buffer across calls saves the page faults of fresh output memory, which cost more than counting for
/// windows that are small next to the frame. Returns the dropped-event count per window.
pub fn accumulate_into(
    ev: EventsView<'_>,
    windows: &[(usize, usize)],
    params: FrameParams,
    map: Option<&[f32]>,
    out: &mut [f32],
) -> Result<Vec<u64>> {
    let (w, h) = (ev.width as usize, ev.height as usize);
    if w == 0 || h == 0 {
        return Err(Error::Invalid("event frames: the sensor size is unknown (0)".into()));
    }
    let n = ev.len();
    if ev.x.len() != n || ev.y.len() != n || ev.p.len() != n {
        return Err(Error::Invalid("event frames: event columns have different lengths".into()));
    }
    if let Some(b) = windows.iter().position(|&(s, e)| s > e || e > n) {
        let (s, e) = windows[b];
        return Err(Error::Invalid(format!("event frames: window {b} = [{s}, {e}) is not inside [0, {n})")));
    }
    if params.downsample_log2 > 8 {
        return Err(Error::Invalid(format!(
            "event frames: downsampling by 2^{} is too coarse",
            params.downsample_log2
        )));
    }
    if let Some(m) = map {
        if m.len() != 2 * w * h {
            return Err(Error::Invalid(format!(
                "event frames: undistortion map has {} values, expected 2 x {w} x {h}",
                m.len()
            )));
        }
    }
    let (ow, oh) = frame_size(ev.width, ev.height, params);
    if out.len() != windows.len() * ow * oh {
        return Err(Error::Invalid(format!(
            "event frames: output buffer has {} values, expected {} windows x {oh} x {ow}",
            out.len(),
            windows.len()
        )));
    }
    // Counts live on the output grid, except with a map: then on the sensor grid, splatted afterwards.
    let grid = if map.is_some() {
        Grid { w, h, shift: 0, cw: w }
    } else {
        Grid { w, h, shift: params.downsample_log2, cw: ow }
    };
    let cells = 2 * grid.cw * if map.is_some() { h } else { oh };

    // Splitting windows only pays when the windows alone cannot keep every thread busy.
    let split = windows.len() < 2 * rayon::current_num_threads();
    // One C and no splat: only `n_on − n_off` matters, counted in the output frame itself (as wrapping
    // i32 bits) — half the memory traffic of separate counts and no scratch buffer.
    let signed = map.is_none() && params.c_on == params.c_off;
    let results: Vec<(u64, usize)> = out
        .par_chunks_mut(ow * oh)
        .zip(windows.par_iter())
        .map(|(frame, &(s, e))| {
            if signed {
                frame.fill(0.0);
                let bad = count_window::<true>(ev, s..e, grid, bytemuck::cast_slice_mut(frame), split);
                for v in frame.iter_mut() {
                    *v = params.c_on * (v.to_bits() as i32) as f32;
                }
                return (0, bad);
            }
            let mut counts = pool::take(cells);
            let bad = count_window::<false>(ev, s..e, grid, &mut counts, split);
            let dropped = match map {
                None => {
                    to_frame(&mut counts, frame, params);
                    0
                }
                Some(m) => {
                    frame.fill(0.0);
                    splat(&mut counts, m, frame, ow, oh, params)
                }
            };
            pool::give(counts);
            (dropped, bad)
        })
        .collect();

    if results.iter().any(|r| r.1 > 0) {
        let i = windows
            .iter()
            .flat_map(|&(s, e)| s..e)
            .find(|&i| usize::from(ev.x[i]) >= w || usize::from(ev.y[i]) >= h)
            .expect("a counted bad event exists");
        return Err(Error::Invalid(format!(
            "event frames: event {i} at ({}, {}) is outside the {w}x{h} sensor",
            ev.x[i], ev.y[i]
        )));
    }
    Ok(results.into_iter().map(|r| r.0).collect())
}

/// Count buffers kept between calls: fresh multi-megabyte buffers cost page faults on first touch, which
/// for a 50 k-event window on a 640×480 sensor cost more than the counting. A buffer is only handed
/// back all zero (every finishing step clears what it read), so `take` never has to clear it.
mod pool {
    use std::sync::Mutex;

    static POOL: Mutex<Vec<Vec<u32>>> = Mutex::new(Vec::new());
    /// Enough for every thread's window plus the parts of a split window, without hoarding memory.
    const KEEP: usize = 16;

    pub(super) fn take(cells: usize) -> Vec<u32> {
        let mut buf = POOL.lock().map(|mut p| p.pop()).ok().flatten().unwrap_or_default();
        buf.resize(cells, 0);
        buf
    }

    pub(super) fn give(buf: Vec<u32>) {
        debug_assert!(buf.iter().all(|&c| c == 0));
        if let Ok(mut p) = POOL.lock() {
            if p.len() < KEEP {
                p.push(buf);
            }
        }
    }
}

/// Where an event's count goes: pixel `(y >> shift)·cw + (x >> shift)` of a `cw`-wide count grid.
#[derive(Debug, Clone, Copy)]
struct Grid {
    w: usize,
    h: usize,
    shift: u32,
    cw: usize,
}

/// Count a window into `counts`, with `split`: large windows in fixed-size parts counted in parallel and
/// summed in part order. `SIGNED`: one wrapping `n_on − n_off` per pixel, else `(n_on, n_off)` pairs.
/// Returns the number of events outside the sensor.
fn count_window<const SIGNED: bool>(
    ev: EventsView<'_>,
    range: std::ops::Range<usize>,
    grid: Grid,
    counts: &mut [u32],
    split: bool,
) -> usize {
    let part = MIN_PART_EVENTS.max(2 * counts.len());
    let n_parts = if split { range.len().div_ceil(part) } else { 1 };
    if n_parts <= 1 {
        return count_range::<SIGNED>(ev, range, grid, counts);
    }
    let (first, cells) = (range.start..range.start + part, counts.len());
    let (bad0, rest) = rayon::join(
        || count_range::<SIGNED>(ev, first, grid, counts),
        || {
            (1..n_parts)
                .into_par_iter()
                .map(|k| {
                    let mut c = pool::take(cells);
                    let r = range.start + k * part..(range.start + (k + 1) * part).min(range.end);
                    let bad = count_range::<SIGNED>(ev, r, grid, &mut c);
                    (c, bad)
                })
                .collect::<Vec<_>>()
        },
    );
    let mut bad = bad0;
    for (mut c, b) in rest {
        for (acc, v) in counts.iter_mut().zip(c.iter_mut()) {
            *acc = acc.wrapping_add(*v);
            *v = 0;
        }
        pool::give(c);
        bad += b;
    }
    bad
}

/// The hot loop: one table increment per event. Events outside the sensor are skipped and counted.
fn count_range<const SIGNED: bool>(
    ev: EventsView<'_>,
    range: std::ops::Range<usize>,
    g: Grid,
    counts: &mut [u32],
) -> usize {
    let (xs, ys, ps) = (&ev.x[range.clone()], &ev.y[range.clone()], &ev.p[range]);
    let mut bad = 0;
    for ((&x, &y), &p) in xs.iter().zip(ys).zip(ps) {
        let (x, y) = (usize::from(x), usize::from(y));
        if x >= g.w || y >= g.h {
            bad += 1;
            continue;
        }
        let pix = (y >> g.shift) * g.cw + (x >> g.shift);
        let negative = usize::from(p as u8 >> 7);
        if SIGNED {
            // +1 or −1 as a wrapping u32 (two's complement).
            counts[pix] = counts[pix].wrapping_add(1u32.wrapping_sub(2 * negative as u32));
        } else {
            counts[2 * pix + negative] += 1;
        }
    }
    bad
}

#[inline]
fn value(c: &[u32], p: FrameParams) -> f32 {
    p.c_on * c[0] as f32 - p.c_off * c[1] as f32
}

/// Every cell → frame value; clears `counts`.
fn to_frame(counts: &mut [u32], frame: &mut [f32], p: FrameParams) {
    for (v, c) in frame.iter_mut().zip(counts.chunks_exact_mut(2)) {
        *v = value(c, p);
        c.fill(0);
    }
}

/// Bilinear splat of each sensor pixel's value at its undistorted position on the `ow × oh` output grid.
/// Returns the number of events whose position lies outside the image. Clears `counts`.
fn splat(counts: &mut [u32], map: &[f32], frame: &mut [f32], ow: usize, oh: usize, p: FrameParams) -> u64 {
    let scale = 1.0 / (1u32 << p.downsample_log2) as f32;
    let (wf, hf) = (ow as f32, oh as f32);
    let mut dropped = 0u64;
    for (c, uv) in counts.chunks_exact_mut(2).zip(map.chunks_exact(2)) {
        if c[0] == 0 && c[1] == 0 {
            continue;
        }
        let (on, off) = (c[0], c[1]);
        c.fill(0);
        let u = (uv[0] + 0.5) * scale - 0.5;
        let v = (uv[1] + 0.5) * scale - 0.5;
        // Inside the image rectangle [-0.5, W - 0.5) × [-0.5, H - 0.5); false for NaN.
        if !(u >= -0.5 && u < wf - 0.5 && v >= -0.5 && v < hf - 0.5) {
            dropped += u64::from(on) + u64::from(off);
            continue;
        }
        let value = value(&[on, off], p);
        // Within half a pixel of the border the outer neighbour is off-grid: its share goes to the border.
        let (u, v) = (u.clamp(0.0, wf - 1.0), v.clamp(0.0, hf - 1.0));
        let (x0, y0) = (u as usize, v as usize);
        let (x1, y1) = ((x0 + 1).min(ow - 1), (y0 + 1).min(oh - 1));
        let (ax, ay) = (u - x0 as f32, v - y0 as f32);
        frame[y0 * ow + x0] += value * (1.0 - ax) * (1.0 - ay);
        frame[y0 * ow + x1] += value * ax * (1.0 - ay);
        frame[y1 * ow + x0] += value * (1.0 - ax) * ay;
        frame[y1 * ow + x1] += value * ax * ay;
    }
    dropped
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::events::window::SplitMix64;
    use crate::events::Events;

    fn random_events(n: usize, w: u32, h: u32, seed: u64) -> Events {
        let mut r = SplitMix64::new(seed);
        let mut ev = Events::with_capacity(n, w, h);
        for i in 0..n {
            let p = if r.below(3) == 0 { -1 } else { 1 };
            ev.push(i as i64, r.below(u64::from(w)) as u16, r.below(u64::from(h)) as u16, p);
        }
        ev
    }

    /// Straightforward per-event float reference.
    fn reference(ev: &Events, s: usize, e: usize, params: FrameParams) -> Vec<f32> {
        let f = 1usize << params.downsample_log2;
        let (ow, oh) = ((ev.width as usize).div_ceil(f), (ev.height as usize).div_ceil(f));
        let mut on = vec![0f64; ow * oh];
        let mut off = vec![0f64; ow * oh];
        for i in s..e {
            let k = (ev.y[i] as usize / f) * ow + ev.x[i] as usize / f;
            if ev.p[i] > 0 {
                on[k] += 1.0
            } else {
                off[k] += 1.0
            }
        }
        if params.c_on == params.c_off {
            on.iter().zip(&off).map(|(a, b)| params.c_on * (a - b) as f32).collect()
        } else {
            on.iter().zip(&off).map(|(a, b)| params.c_on * *a as f32 - params.c_off * *b as f32).collect()
        }
    }

    #[test]
    fn matches_reference_with_one_or_two_constants_and_downsampling() {
        let ev = random_events(20_000, 37, 23, 1);
        let windows = [(0, 20_000), (5, 5), (100, 7_000), (19_999, 20_000)];
        for (ds, c_off) in (0..3).flat_map(|ds| [(ds, 0.1), (ds, 0.25)]) {
            let params = FrameParams { c_on: 0.25, c_off, downsample_log2: ds };
            let fr = accumulate(ev.view(), &windows, params, None).unwrap();
            assert_eq!((fr.width, fr.height), (37usize.div_ceil(1 << ds), 23usize.div_ceil(1 << ds)));
            let hw = fr.width * fr.height;
            for (b, &(s, e)) in windows.iter().enumerate() {
                assert_eq!(
                    &fr.data[b * hw..(b + 1) * hw],
                    reference(&ev, s, e, params).as_slice(),
                    "ds {ds} b {b}"
                );
            }
            assert_eq!(fr.dropped, vec![0; 4]);
        }
    }

    #[test]
    fn split_windows_equal_unsplit_counts() {
        // 3 M events on a tiny sensor: split into 4 parts; the sums must be exact.
        let ev = random_events(3 * MIN_PART_EVENTS + 17, 5, 3, 2);
        let n = ev.len();
        let grid = Grid { w: 5, h: 3, shift: 0, cw: 5 };
        let (mut split, mut whole) = (vec![0u32; 30], vec![0u32; 30]);
        assert_eq!(count_window::<false>(ev.view(), 1..n, grid, &mut split, true), 0);
        assert_eq!(count_window::<false>(ev.view(), 1..n, grid, &mut whole, false), 0);
        assert_eq!(split, whole);
        assert_eq!(split.iter().map(|&c| c as usize).sum::<usize>(), n - 1);
        let (mut split, mut whole) = (vec![0u32; 15], vec![0u32; 15]);
        count_window::<true>(ev.view(), 1..n, grid, &mut split, true);
        count_window::<true>(ev.view(), 1..n, grid, &mut whole, false);
        assert_eq!(split, whole);
        let net: i64 = ev.p[1..].iter().map(|&p| i64::from(p)).sum();
        assert_eq!(split.iter().map(|&c| i64::from(c as i32)).sum::<i64>(), net);
        let fr = accumulate(ev.view(), &[(1, n)], FrameParams::default(), None).unwrap();
        assert_eq!(fr.data, reference(&ev, 1, n, FrameParams::default()));
    }

    #[test]
    fn identity_map_equals_plain_accumulation() {
        let ev = random_events(5_000, 16, 12, 3);
        let map: Vec<f32> = (0..16 * 12).flat_map(|i| [(i % 16) as f32, (i / 16) as f32]).collect();
        let params = FrameParams { c_on: 0.2, c_off: 0.3, downsample_log2: 0 };
        let a = accumulate(ev.view(), &[(0, 5_000)], params, Some(&map)).unwrap();
        let b = accumulate(ev.view(), &[(0, 5_000)], params, None).unwrap();
        assert_eq!(a.data, b.data);
        // Downsampled identity map: the block's pixel centres splat onto the coarse grid (sum conserved).
        let params = FrameParams { downsample_log2: 1, ..params };
        let a = accumulate(ev.view(), &[(0, 5_000)], params, Some(&map)).unwrap();
        let b = accumulate(ev.view(), &[(0, 5_000)], params, None).unwrap();
        let (sa, sb): (f32, f32) = (a.data.iter().sum(), b.data.iter().sum());
        assert!((sa - sb).abs() < 1e-2 * sb.abs().max(1.0), "{sa} vs {sb}");
    }

    #[test]
    fn splat_shares_mass_and_counts_dropped_events() {
        let mut ev = Events::with_capacity(4, 4, 4);
        ev.push(0, 0, 0, 1); // → (1.25, 2.5): split over 4 pixels
        ev.push(1, 1, 0, -1); // → NaN: dropped
        ev.push(2, 2, 0, 1); // → (4.2, 0): outside, dropped
        ev.push(3, 2, 0, 1);
        let mut map = vec![0f32; 32];
        map[..6].copy_from_slice(&[1.25, 2.5, f32::NAN, 0.0, 4.2, 0.0]);
        let fr = accumulate(ev.view(), &[(0, 4)], FrameParams::default(), Some(&map)).unwrap();
        assert_eq!(fr.dropped, vec![3]);
        let at = |x: usize, y: usize| fr.data[y * 4 + x];
        assert_eq!([at(1, 2), at(2, 2), at(1, 3), at(2, 3)], [0.375, 0.125, 0.375, 0.125]);
        assert_eq!(fr.data.iter().sum::<f32>(), 1.0);
    }

    #[test]
    fn bad_windows_and_coordinates_are_named() {
        let mut ev = random_events(100, 8, 8, 4);
        let e = accumulate(ev.view(), &[(0, 10), (50, 101)], FrameParams::default(), None).unwrap_err();
        assert!(e.to_string().contains("window 1 = [50, 101)"), "{e}");
        ev.x[42] = 8;
        let e = accumulate(ev.view(), &[(0, 10), (40, 50)], FrameParams::default(), None).unwrap_err();
        assert!(e.to_string().contains("event 42 at (8,"), "{e}");
        ev.width = 0;
        assert!(accumulate(ev.view(), &[(0, 10)], FrameParams::default(), None).is_err());
    }
}

//! Event frames: `E(x, y) = C_on·n_on − C_off·n_off` over event index ranges, batched.
//!
//! Each window is first reduced to integer per-pixel `(n_on, n_off)` counts, then turned into floats
//! once per pixel. Integer counts make the result exact and independent of how the work is split: a
//! large window is cut into fixed-size event sub-ranges counted in parallel and summed in order, and
//! the frame is bitwise identical for any thread count.
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

/// Event frames of `windows` (half-open event index ranges) over `ev`; `map` is an undistortion map of
/// the sensor (`2·W·H` interleaved `(u, v)` pixel positions, NaN = invalid).
pub fn accumulate(
    ev: EventsView<'_>,
    windows: &[(usize, usize)],
    params: FrameParams,
    map: Option<&[f32]>,
) -> Result<Frames> {
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
    let f = 1usize << params.downsample_log2;
    let (ow, oh) = (w.div_ceil(f), h.div_ceil(f));
    // Counts live on the output grid, except with a map: then on the sensor grid, splatted afterwards.
    let grid = if map.is_some() {
        Grid { w, h, shift: 0, cw: w }
    } else {
        Grid { w, h, shift: params.downsample_log2, cw: ow }
    };
    let cells = 2 * grid.cw * if map.is_some() { h } else { oh };

    let mut data = vec![0f32; windows.len() * ow * oh];
    let results: Vec<(u64, usize)> = data
        .par_chunks_mut(ow * oh)
        .zip(windows.par_iter())
        .map_init(
            || vec![0u32; cells],
            |counts, (frame, &(s, e))| {
                counts.fill(0);
                let bad = count_window(ev, s..e, grid, counts);
                let dropped = match map {
                    None => {
                        to_frame(counts, frame, params);
                        0
                    }
                    Some(m) => splat(counts, m, frame, ow, oh, params),
                };
                (dropped, bad)
            },
        )
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
    Ok(Frames { data, width: ow, height: oh, dropped: results.into_iter().map(|r| r.0).collect() })
}

/// Where an event's count goes: cell `2·((y >> shift)·cw + (x >> shift)) + (p < 0)`.
#[derive(Debug, Clone, Copy)]
struct Grid {
    w: usize,
    h: usize,
    shift: u32,
    cw: usize,
}

/// Count a window into `counts`, splitting large windows into fixed-size parts counted in parallel and
/// summed in part order. Returns the number of events outside the sensor.
fn count_window(ev: EventsView<'_>, range: std::ops::Range<usize>, grid: Grid, counts: &mut [u32]) -> usize {
    let part = MIN_PART_EVENTS.max(2 * counts.len());
    let n_parts = range.len().div_ceil(part);
    if n_parts <= 1 {
        return count_range(ev, range, grid, counts);
    }
    let (first, cells) = (range.start..range.start + part, counts.len());
    let (bad0, rest) = rayon::join(
        || count_range(ev, first, grid, counts),
        || {
            (1..n_parts)
                .into_par_iter()
                .map(|k| {
                    let mut c = vec![0u32; cells];
                    let r = range.start + k * part..(range.start + (k + 1) * part).min(range.end);
                    let bad = count_range(ev, r, grid, &mut c);
                    (c, bad)
                })
                .collect::<Vec<_>>()
        },
    );
    let mut bad = bad0;
    for (c, b) in rest {
        for (acc, v) in counts.iter_mut().zip(&c) {
            *acc += v;
        }
        bad += b;
    }
    bad
}

/// The hot loop: one table increment per event. Events outside the sensor are skipped and counted.
fn count_range(ev: EventsView<'_>, range: std::ops::Range<usize>, g: Grid, counts: &mut [u32]) -> usize {
    let (xs, ys, ps) = (&ev.x[range.clone()], &ev.y[range.clone()], &ev.p[range]);
    let mut bad = 0;
    for ((&x, &y), &p) in xs.iter().zip(ys).zip(ps) {
        let (x, y) = (usize::from(x), usize::from(y));
        if x >= g.w || y >= g.h {
            bad += 1;
            continue;
        }
        let cell = 2 * ((y >> g.shift) * g.cw + (x >> g.shift)) + usize::from(p as u8 >> 7);
        counts[cell] += 1;
    }
    bad
}

fn to_frame(counts: &[u32], frame: &mut [f32], p: FrameParams) {
    for (v, c) in frame.iter_mut().zip(counts.chunks_exact(2)) {
        *v = p.c_on * c[0] as f32 - p.c_off * c[1] as f32;
    }
}

/// Bilinear splat of each sensor pixel's value at its undistorted position on the `ow × oh` output grid.
/// Returns the number of events whose position lies outside the image.
fn splat(counts: &[u32], map: &[f32], frame: &mut [f32], ow: usize, oh: usize, p: FrameParams) -> u64 {
    let scale = 1.0 / (1u32 << p.downsample_log2) as f32;
    let (wf, hf) = (ow as f32, oh as f32);
    let mut dropped = 0u64;
    for (c, uv) in counts.chunks_exact(2).zip(map.chunks_exact(2)) {
        if c[0] == 0 && c[1] == 0 {
            continue;
        }
        let u = (uv[0] + 0.5) * scale - 0.5;
        let v = (uv[1] + 0.5) * scale - 0.5;
        // Inside the image rectangle [-0.5, W - 0.5) × [-0.5, H - 0.5); false for NaN.
        if !(u >= -0.5 && u < wf - 0.5 && v >= -0.5 && v < hf - 0.5) {
            dropped += u64::from(c[0]) + u64::from(c[1]);
            continue;
        }
        let value = p.c_on * c[0] as f32 - p.c_off * c[1] as f32;
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
        on.iter().zip(&off).map(|(a, b)| params.c_on * *a as f32 - params.c_off * *b as f32).collect()
    }

    #[test]
    fn matches_reference_with_asymmetric_constants_and_downsampling() {
        let ev = random_events(20_000, 37, 23, 1);
        let windows = [(0, 20_000), (5, 5), (100, 7_000), (19_999, 20_000)];
        for ds in 0..3 {
            let params = FrameParams { c_on: 0.25, c_off: 0.1, downsample_log2: ds };
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
        // 3 M events on a tiny sensor: the window is split into parts; the sums must be exact.
        let ev = random_events(3 * MIN_PART_EVENTS + 17, 5, 3, 2);
        let n = ev.len();
        let fr = accumulate(ev.view(), &[(0, n), (1, n - 1)], FrameParams::default(), None).unwrap();
        assert_eq!(&fr.data[..15], reference(&ev, 0, n, FrameParams::default()).as_slice());
        assert_eq!(&fr.data[15..], reference(&ev, 1, n - 1, FrameParams::default()).as_slice());
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

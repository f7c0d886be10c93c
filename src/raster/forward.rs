//! Front-to-back compositing of one 16×16 tile (RASTER_MATH.md, "Compositing").
//!
//! Vectorised across pixels: a tile is 16 rows × 2 segments of 8 lanes (one AVX2 register each).
//! For each splat of the tile (front to back), a [`TilePlan`] computed for all 16 rows at once gives
//! a 32-bit mask of the segments its ellipse reaches; a branch-free loop runs over the 8 lanes of each
//! segment in that mask that still has a live pixel (a second mask). Per-pixel state lives in the
//! tile's stack arrays, and the tile stops when no segment is live.

use super::camera::TILE;
use super::fastmath;
use super::project::{Projected, Splat, ALPHA_MIN};

/// Alpha clamp and the transmittance at which a pixel stops (float32 constants, as gsplat).
pub(crate) const ALPHA_MAX: f32 = 0.99;
pub(crate) const T_MIN: f32 = 1e-4;

/// Lanes per segment and segments per tile row.
pub(crate) const LANES: usize = 8;
pub(crate) const SEGS: usize = TILE / LANES;

/// Per-row constants of a splat: `σ = dx·(½a·dx + b·dy) + ½c·dy²` needs two products per lane.
#[derive(Clone, Copy)]
pub(crate) struct RowTerms {
    pub dy: f32,
    half_a: f32,
    b_dy: f32,
    half_c_dy2: f32,
}

/// What one splat does to one tile, computed for all 16 rows at once (branch-free, so it vectorises):
/// the per-row terms of `σ` and the 8-lane segments the splat can reach with alpha ≥ 1/255.
pub(crate) struct TilePlan {
    dy: [f32; TILE],
    b_dy: [f32; TILE],
    half_c_dy2: [f32; TILE],
    half_a: f32,
    /// Bit `h·16 + r` set: segment `h` of row `r` may hold a pixel with `σ ≤ tau`.
    pub mask: u32,
}

impl TilePlan {
    #[inline(always)]
    pub fn row(&self, r: usize) -> RowTerms {
        RowTerms { dy: self.dy[r], half_a: self.half_a, b_dy: self.b_dy[r], half_c_dy2: self.half_c_dy2[r] }
    }
}

/// Segment `h` and row `r` of mask bit `bit` (see [`TilePlan::mask`]).
#[inline(always)]
pub(crate) fn seg_of_bit(bit: u32) -> (usize, usize) {
    (bit as usize % TILE, bit as usize / TILE)
}

/// `(σ, G = e^{-σ}, α = min(0.99, o·G))` of a splat at offset `dx` = mean − pixel centre on a row.
/// The one definition used by forward and backward, so both see identical bits.
#[inline(always)]
pub(crate) fn alpha_at(s: &Splat, row: &RowTerms, dx: f32) -> (f32, f32, f32) {
    let sigma = dx.mul_add(row.half_a.mul_add(dx, row.b_dy), row.half_c_dy2);
    let g = fastmath::exp(-sigma);
    let og = s.opacity * g;
    (sigma, g, if og < ALPHA_MAX { og } else { ALPHA_MAX })
}

/// Pixel-centre x coordinates of a tile's segments.
#[inline(always)]
pub(crate) fn lane_centres(x0: usize) -> [[f32; LANES]; SEGS] {
    std::array::from_fn(|h| std::array::from_fn(|l| (x0 + h * LANES + l) as f32 + 0.5))
}

/// Where one tile sits and what it composites.
pub(crate) struct TileJob<'a> {
    pub x0: usize,
    pub y0: usize,
    /// Valid lanes and rows (the right and bottom tiles may be partial).
    pub lanes: usize,
    pub rows: usize,
    pub ids: &'a [u32],
    pub splats: &'a [Projected],
}

/// A hint to load the cache line holding `x` (a no-op where there is no prefetch instruction).
#[inline(always)]
fn prefetch<T>(x: &T) {
    // SAFETY: a prefetch never faults and has no architectural effect; the pointer is a valid reference.
    #[cfg(target_arch = "x86_64")]
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>((x as *const T).cast())
    };
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}

/// Splats handled per gather: the splats of a tile list sit at random places in memory, and copying a
/// batch of them in one tight loop lets the loads overlap instead of stalling the compositing loop.
pub(crate) const BATCH: usize = 64;

impl TileJob<'_> {
    /// Copy the splats and colours of tile-list positions `range` into `splats` and `colors`, and ask
    /// for the cache lines of the batch to come (`next`), so that they arrive while this one composites.
    #[inline]
    pub fn gather<const NC: usize>(
        &self,
        range: std::ops::Range<usize>,
        next: std::ops::Range<usize>,
        splats: &mut Vec<Splat>,
        colors: &mut Vec<[f32; NC]>,
    ) {
        splats.clear();
        colors.clear();
        for &g in &self.ids[range] {
            let p = &self.splats[g as usize];
            splats.push(p.splat);
            colors.push(std::array::from_fn(|ch| p.color[ch]));
        }
        for &g in &self.ids[next] {
            prefetch(&self.splats[g as usize]);
        }
    }

    /// The plan of splat `s` on this tile. A segment is reached if the minimum of `σ` over its lanes'
    /// offsets, widened by a pixel on each side, is at most `tau`: on a row `σ(dx)` is a parabola in
    /// `dx` with its vertex at `−b·dy/a`, so the minimum over an interval is at the clamped vertex. No
    /// square roots or divisions, and it trims the tile to the splat's ellipse.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    pub fn plan(&self, s: &Splat) -> TilePlan {
        let half_a = 0.5 * s.a;
        let mut p = TilePlan { dy: [0.0; TILE], b_dy: [0.0; TILE], half_c_dy2: [0.0; TILE], half_a, mask: 0 };
        // dx = u − (x0 + 8h + j + ½), j in 0..8, widened by one pixel.
        let lo: [f32; SEGS] =
            std::array::from_fn(|h| s.u - (self.x0 + h * LANES) as f32 - (LANES as f32 + 0.5));
        let hi: [f32; SEGS] = std::array::from_fn(|h| s.u - (self.x0 + h * LANES) as f32 + 0.5);
        let mut reach = [[0u32; TILE]; SEGS];
        for r in 0..TILE {
            let dy = s.v - ((self.y0 + r) as f32 + 0.5);
            let b_dy = s.b * dy;
            let half_c_dy2 = 0.5 * s.c * dy * dy;
            let vertex = -b_dy * s.inv_a;
            for h in 0..SEGS {
                let d = if vertex > lo[h] { vertex } else { lo[h] };
                let d = if d < hi[h] { d } else { hi[h] };
                let sigma = d.mul_add(half_a.mul_add(d, b_dy), half_c_dy2);
                reach[h][r] = u32::from(sigma <= s.tau) << (h * TILE + r);
            }
            p.dy[r] = dy;
            p.b_dy[r] = b_dy;
            p.half_c_dy2[r] = half_c_dy2;
        }
        p.mask = reach.iter().flatten().fold(0, |m, &b| m | b);
        p
    }

    /// In-image lanes of segment `h`.
    #[inline(always)]
    pub fn seg_lanes(&self, h: usize) -> usize {
        self.lanes.saturating_sub(h * LANES).min(LANES)
    }
}

/// A tile's outputs: its row pieces of the row-major colour (C values per pixel), depth and alpha
/// images, and tile-major (`row*16 + lane`) final T and `last` = 1 + the tile-list index of the last
/// composited splat (0 = none), which the backward pass reads.
pub(crate) struct TileOut<'a> {
    pub color: Vec<&'a mut [f32]>,
    pub depth: Vec<&'a mut [f32]>,
    pub alpha: Vec<&'a mut [f32]>,
    pub t_final: &'a mut [f32],
    pub last: &'a mut [u32],
}

type Lanes = [f32; LANES];

/// Per-pixel compositing state of one 8-lane segment.
#[derive(Clone, Copy)]
struct Seg<const NC: usize> {
    t: Lanes,
    color: [Lanes; NC],
    depth: Lanes,
    last: [u32; LANES],
    /// 1 + the tile-list index of the splat at which the pixel stopped; 0 while it is live (and
    /// `u32::MAX` for a lane outside the image, so that it never is).
    stop_at: [u32; LANES],
}

/// Pixel–splat evaluations of one tile, counted two ways (see [`crate::raster::Forward::evaluations`]).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct TileCounts {
    /// Pixels of the row segments actually evaluated (what this rasterizer computes).
    pub segments: u64,
    /// The standard (3DGS/gsplat) count: per in-image pixel, the tile-list entries up to and including
    /// the one at which it stopped, or the whole list.
    pub standard: u64,
}

impl std::ops::Add for TileCounts {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        TileCounts { segments: self.segments + o.segments, standard: self.standard + o.standard }
    }
}

/// Composite one tile; returns the pixel–splat evaluations performed.
pub(crate) fn render_tile<const NC: usize>(
    job: &TileJob,
    mut out: TileOut,
    background: &[f32],
) -> TileCounts {
    let px = lane_centres(job.x0);
    let mut segs = [[Seg::<NC> {
        t: [1.0; LANES],
        color: [[0.0; LANES]; NC],
        depth: [0.0; LANES],
        last: [0; LANES],
        stop_at: [u32::MAX; LANES],
    }; SEGS]; TILE];
    // Bit `h·16 + r`: segment `h` of row `r` still has a live pixel.
    let mut alive = 0u32;
    for (r, row) in segs.iter_mut().enumerate().take(job.rows) {
        for (h, seg) in row.iter_mut().enumerate() {
            let n = job.seg_lanes(h);
            seg.stop_at = std::array::from_fn(|l| if l < n { 0 } else { u32::MAX });
            alive |= u32::from(n > 0) << (h * TILE + r);
        }
    }
    let mut evaluations = 0u64;
    let (mut splats, mut colors) = (Vec::with_capacity(BATCH), Vec::with_capacity(BATCH));
    let mut start = 0;
    while start < job.ids.len() && alive != 0 {
        let end = job.ids.len().min(start + BATCH);
        job.gather::<NC>(start..end, end..job.ids.len().min(end + BATCH), &mut splats, &mut colors);
        for (j, (&s, &col)) in splats.iter().zip(&colors).enumerate() {
            if alive == 0 {
                break;
            }
            // (Copies: locals that provably do not alias the tile state keep the lane loop vectorised.)
            let plan = job.plan(&s);
            let k1 = (start + j) as u32 + 1;
            let mut work = plan.mask & alive;
            while work != 0 {
                let bit = work.trailing_zeros();
                work &= work - 1;
                let (r, h) = seg_of_bit(bit);
                evaluations += job.seg_lanes(h) as u64;
                let seg = &mut segs[r][h];
                composite_seg::<NC>(&s, &plan.row(r), &col, k1, &px[h], seg);
                if seg.stop_at.iter().all(|&k| k != 0) {
                    alive &= !(1 << bit);
                }
            }
        }
        start = end;
    }
    let list_len = job.ids.len() as u64;
    let mut standard = 0u64;
    for (r, row) in segs.iter().enumerate() {
        for (h, seg) in row.iter().enumerate() {
            if r < job.rows {
                let stops = seg.stop_at.iter().take(job.seg_lanes(h));
                standard += stops.map(|&k| if k > 0 { u64::from(k) } else { list_len }).sum::<u64>();
            }
            let lanes = r * TILE + h * LANES..r * TILE + (h + 1) * LANES;
            out.t_final[lanes.clone()].copy_from_slice(&seg.t);
            out.last[lanes].copy_from_slice(&seg.last);
        }
    }
    for (r, row) in segs.iter().enumerate().take(job.rows) {
        for x in 0..job.lanes {
            let (seg, l) = (&row[x / LANES], x % LANES);
            out.alpha[r][x] = 1.0 - seg.t[l];
            out.depth[r][x] = seg.depth[l];
            for (ch, (c, bg)) in out.color[r][x * NC..(x + 1) * NC].iter_mut().zip(background).enumerate() {
                *c = seg.color[ch][l] + seg.t[l] * bg;
            }
        }
    }
    TileCounts { segments: evaluations, standard }
}

/// One splat over one 8-lane segment; branch-free so that it compiles to vector selects.
/// Indexed lanes (not iterators) keep the loop a plain vectorisable lane loop.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn composite_seg<const NC: usize>(
    s: &Splat,
    row: &RowTerms,
    col: &[f32; NC],
    k1: u32,
    px: &Lanes,
    seg: &mut Seg<NC>,
) {
    for l in 0..LANES {
        let (sigma, _, alpha) = alpha_at(s, row, s.u - px[l]);
        // `&` rather than `&&`: no short-circuit branches in the lane loop.
        let ok = (sigma >= 0.0) & (alpha >= ALPHA_MIN) & (seg.stop_at[l] == 0);
        let t_next = seg.t[l] * (1.0 - alpha);
        let stop = ok & (t_next <= T_MIN);
        let take = ok & !stop;
        let w = if take { alpha * seg.t[l] } else { 0.0 };
        for ch in 0..NC {
            seg.color[ch][l] += col[ch] * w;
        }
        seg.depth[l] += s.z * w;
        seg.t[l] = if take { t_next } else { seg.t[l] };
        seg.last[l] = if take { k1 } else { seg.last[l] };
        seg.stop_at[l] = if stop { k1 } else { seg.stop_at[l] };
    }
}

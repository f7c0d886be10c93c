//! Front-to-back compositing of one 16×16 tile (RASTER_MATH.md, "Compositing").
//!
//! Vectorised across pixels: a tile is 16 rows × 2 segments of 8 lanes (one AVX2 register each).
//! For each splat of the tile (front to back), a branch-free loop runs over the 8 lanes of every
//! segment the splat's extent reaches; per-pixel state lives in the tile's stack arrays. Segments
//! whose pixels have all stopped are skipped, and the tile stops when all have.

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

impl RowTerms {
    #[inline(always)]
    pub fn new(s: &Splat, py: f32) -> Self {
        let dy = s.v - py;
        RowTerms { dy, half_a: 0.5 * s.a, b_dy: s.b * dy, half_c_dy2: 0.5 * s.c * dy * dy }
    }
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

/// Inclusive tile-local index range `[lo, hi]` of `[first, last]` clipped to `[0, n)`, for cells of
/// `cell` pixels starting at pixel `origin`; `None` if empty.
#[inline(always)]
fn clip_span(first: i32, last: i32, origin: usize, cell: usize, n: usize) -> Option<(usize, usize)> {
    let lo = (first - origin as i32).max(0) as usize / cell;
    let hi = (last - origin as i32).min((n * cell) as i32 - 1);
    (hi >= 0 && hi as usize / cell >= lo).then(|| (lo, hi as usize / cell))
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
    pub colors: &'a [f32],
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
            let g = g as usize;
            splats.push(self.splats[g].splat);
            colors.push(std::array::from_fn(|ch| self.colors[g * NC + ch]));
        }
        for &g in &self.ids[next] {
            let g = g as usize;
            prefetch(&self.splats[g]);
            prefetch(&self.colors[g * NC]);
        }
    }

    /// The tile rows and row segments a splat's extent reaches.
    #[inline(always)]
    pub fn span(&self, s: &Splat) -> Option<((usize, usize), (usize, usize))> {
        let rows = clip_span(s.row_lo, s.row_hi, self.y0, 1, self.rows)?;
        let segs = clip_span(s.col_lo, s.col_hi, self.x0, LANES, SEGS)?;
        Some((rows, segs))
    }

    /// The segments of the row described by `row`, within `segs`, where the splat can reach alpha ≥
    /// 1/255: the chord `σ(dx) ≤ tau` of the ellipse, widened by a pixel on each side; `None` if the
    /// row misses it. Cheaper than evaluating a segment, and it trims the square extent to the ellipse.
    #[inline(always)]
    pub fn row_segs(&self, s: &Splat, row: &RowTerms, segs: (usize, usize)) -> Option<(usize, usize)> {
        // ½a·dx² + b·dy·dx + ½c·dy² − tau ≤ 0, a > 0.
        let disc = row.b_dy * row.b_dy - s.a * (2.0 * (row.half_c_dy2 - s.tau));
        if disc.is_nan() || disc < 0.0 {
            return None;
        }
        let root = disc.sqrt();
        let (dx_lo, dx_hi) = ((-row.b_dy - root) / s.a, (-row.b_dy + root) / s.a);
        // Column j has dx = u − (j + ½).
        let first = (s.u - 0.5 - dx_hi).floor().max(-2.0) as i32 - 1;
        let last = (s.u - 0.5 - dx_lo).ceil().min(1e9) as i32 + 1;
        let (h0, h1) = clip_span(first, last, self.x0, LANES, SEGS)?;
        let (h0, h1) = (h0.max(segs.0), h1.min(segs.1));
        (h0 <= h1).then_some((h0, h1))
    }

    /// In-image lanes of segment `h`.
    #[inline(always)]
    pub fn seg_lanes(&self, h: usize) -> usize {
        self.lanes.saturating_sub(h * LANES).min(LANES)
    }
}

/// A tile's outputs, tile-major: colour planes `[ch][row*16 + lane]`, depth, final T, and
/// `last` = 1 + the tile-list index of the last composited splat (0 = none).
pub(crate) struct TileOut<'a> {
    pub color: &'a mut [f32],
    pub depth: &'a mut [f32],
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
    /// 1 + the tile-list index of the splat at which the pixel stopped (0 = it never stopped).
    stop_at: [u32; LANES],
    /// 1 once a pixel has stopped (or lies outside the image).
    done: [u32; LANES],
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
pub(crate) fn render_tile<const NC: usize>(job: &TileJob, out: TileOut) -> TileCounts {
    let px = lane_centres(job.x0);
    let mut segs = [[Seg::<NC> {
        t: [1.0; LANES],
        color: [[0.0; LANES]; NC],
        depth: [0.0; LANES],
        last: [0; LANES],
        stop_at: [0; LANES],
        done: [1; LANES],
    }; SEGS]; TILE];
    let mut alive = [[false; SEGS]; TILE];
    let mut alive_count = 0;
    for (r, row) in segs.iter_mut().enumerate().take(job.rows) {
        for (h, seg) in row.iter_mut().enumerate() {
            let n = job.seg_lanes(h);
            seg.done = std::array::from_fn(|l| u32::from(l >= n));
            alive[r][h] = n > 0;
            alive_count += usize::from(n > 0);
        }
    }
    let mut evaluations = 0u64;
    let (mut splats, mut colors) = (Vec::with_capacity(BATCH), Vec::with_capacity(BATCH));
    let mut start = 0;
    while start < job.ids.len() && alive_count > 0 {
        let end = job.ids.len().min(start + BATCH);
        job.gather::<NC>(start..end, end..job.ids.len().min(end + BATCH), &mut splats, &mut colors);
        for (j, (&s, &col)) in splats.iter().zip(&colors).enumerate() {
            if alive_count == 0 {
                break;
            }
            // (Copies: locals that provably do not alias the tile state keep the lane loop vectorised.)
            let Some(((r0, r1), (h0, h1))) = job.span(&s) else { continue };
            let k1 = (start + j) as u32 + 1;
            for r in r0..=r1 {
                let row = RowTerms::new(&s, (job.y0 + r) as f32 + 0.5);
                let Some((h0, h1)) = job.row_segs(&s, &row, (h0, h1)) else { continue };
                for h in h0..=h1 {
                    if !alive[r][h] {
                        continue;
                    }
                    evaluations += job.seg_lanes(h) as u64;
                    let seg = &mut segs[r][h];
                    composite_seg::<NC>(&s, &row, &col, k1, &px[h], seg);
                    if seg.done.iter().all(|&d| d != 0) {
                        alive[r][h] = false;
                        alive_count -= 1;
                    }
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
            for (ch, plane) in seg.color.iter().enumerate() {
                out.color[ch * TILE * TILE..][lanes.clone()].copy_from_slice(plane);
            }
            out.depth[lanes.clone()].copy_from_slice(&seg.depth);
            out.t_final[lanes.clone()].copy_from_slice(&seg.t);
            out.last[lanes].copy_from_slice(&seg.last);
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
        let ok = (sigma >= 0.0) & (alpha >= ALPHA_MIN) & (seg.done[l] == 0);
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
        seg.done[l] |= u32::from(stop);
    }
}

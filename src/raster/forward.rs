//! Front-to-back compositing of one 16×16 tile (RASTER_MATH.md, "Compositing").
//!
//! Vectorised across pixels: for each splat of the tile (front to back) a branch-free loop runs over
//! the 16 lanes of every tile row the splat's extent reaches; per-pixel state lives in the tile's
//! stack arrays. Rows whose pixels have all stopped are skipped, and the tile stops when all have.

use super::camera::TILE;
use super::fastmath;
use super::project::{Projected, Splat, ALPHA_MIN};

/// Alpha clamp and the transmittance at which a pixel stops (float32 constants, as gsplat).
pub(crate) const ALPHA_MAX: f32 = 0.99;
pub(crate) const T_MIN: f32 = 1e-4;

/// `(σ, G = e^{-σ}, α = min(0.99, o·G))` of a splat at offset `(dx, dy)` = mean − pixel centre. The one
/// definition used by forward and backward, so both see identical bits.
#[inline(always)]
pub(crate) fn alpha_at(s: &Splat, dx: f32, dy: f32) -> (f32, f32, f32) {
    let sigma = 0.5 * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
    let g = fastmath::exp(-sigma);
    (sigma, g, (s.opacity * g).min(ALPHA_MAX))
}

/// Pixel-centre x coordinates of a tile's lanes.
#[inline(always)]
pub(crate) fn lane_centres(x0: usize) -> [f32; TILE] {
    std::array::from_fn(|l| (x0 + l) as f32 + 0.5)
}

/// The tile rows `[lo, hi]` (inclusive, possibly empty) a splat's extent reaches.
#[inline(always)]
pub(crate) fn row_span(s: &Splat, y0: usize, rows: usize) -> std::ops::RangeInclusive<usize> {
    let lo = (s.row_lo - y0 as i32).max(0) as usize;
    let hi = (s.row_hi - y0 as i32).min(rows as i32 - 1);
    if hi < lo as i32 {
        #[allow(clippy::reversed_empty_ranges)]
        return 1..=0;
    }
    lo..=hi as usize
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

/// A tile's outputs, tile-major: colour planes `[ch][row*16 + lane]`, depth, final T, and
/// `last` = 1 + the tile-list index of the last composited splat (0 = none).
pub(crate) struct TileOut<'a> {
    pub color: &'a mut [f32],
    pub depth: &'a mut [f32],
    pub t_final: &'a mut [f32],
    pub last: &'a mut [u32],
}

type Row = [f32; TILE];

/// Composite one tile; returns the number of pixel–splat evaluations performed.
pub(crate) fn render_tile<const NC: usize>(job: &TileJob, out: TileOut) -> u64 {
    let px = lane_centres(job.x0);
    let mut t = [[1.0f32; TILE]; TILE];
    let mut color = [[[0.0f32; TILE]; NC]; TILE];
    let mut depth = [[0.0f32; TILE]; TILE];
    let mut last = [[0u32; TILE]; TILE];
    // Lanes past the image edge start out done so that rows can finish.
    let mut done = [std::array::from_fn::<bool, TILE, _>(|l| l >= job.lanes); TILE];
    let mut row_alive: [bool; TILE] = std::array::from_fn(|r| r < job.rows);
    let mut alive_rows = job.rows;
    let mut evaluations = 0u64;
    for (k, &g) in job.ids.iter().enumerate() {
        if alive_rows == 0 {
            break;
        }
        let s = &job.splats[g as usize].splat;
        let col: [f32; NC] = std::array::from_fn(|ch| job.colors[g as usize * NC + ch]);
        for r in row_span(s, job.y0, job.rows) {
            if !row_alive[r] {
                continue;
            }
            evaluations += job.lanes as u64;
            let py = (job.y0 + r) as f32 + 0.5;
            composite_row::<NC>(
                s,
                &col,
                k as u32 + 1,
                &px,
                py,
                &mut t[r],
                &mut color[r],
                &mut depth[r],
                &mut last[r],
                &mut done[r],
            );
            if done[r].iter().all(|&d| d) {
                row_alive[r] = false;
                alive_rows -= 1;
            }
        }
    }
    for r in 0..TILE {
        let lanes = r * TILE..(r + 1) * TILE;
        for (ch, plane) in color[r].iter().enumerate() {
            out.color[ch * TILE * TILE..][lanes.clone()].copy_from_slice(plane);
        }
        out.depth[lanes.clone()].copy_from_slice(&depth[r]);
        out.t_final[lanes.clone()].copy_from_slice(&t[r]);
        out.last[lanes].copy_from_slice(&last[r]);
    }
    evaluations
}

/// One splat over one 16-pixel tile row; branch-free so that it compiles to vector selects.
#[allow(clippy::too_many_arguments)]
/// Indexed lanes (not iterators) keep the loop a plain vectorisable lane loop.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn composite_row<const NC: usize>(
    s: &Splat,
    col: &[f32; NC],
    k1: u32,
    px: &Row,
    py: f32,
    t: &mut Row,
    color: &mut [Row; NC],
    depth: &mut Row,
    last: &mut [u32; TILE],
    done: &mut [bool; TILE],
) {
    let dy = s.v - py;
    for l in 0..TILE {
        let (sigma, _, alpha) = alpha_at(s, s.u - px[l], dy);
        let ok = sigma >= 0.0 && alpha >= ALPHA_MIN && !done[l];
        let t_next = t[l] * (1.0 - alpha);
        let stop = ok && t_next <= T_MIN;
        let take = ok && !stop;
        let w = if take { alpha * t[l] } else { 0.0 };
        for ch in 0..NC {
            color[ch][l] += col[ch] * w;
        }
        depth[l] += s.z * w;
        t[l] = if take { t_next } else { t[l] };
        last[l] = if take { k1 } else { last[l] };
        done[l] |= stop;
    }
}

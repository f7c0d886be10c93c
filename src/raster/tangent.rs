//! Forward-mode derivative of one tile's colour along the six tangents of its view (the pose JVP).
//!
//! A tracker's Gauss–Newton step needs `∂C/∂ξ` at every pixel for the six pose coordinates `ξ`:
//! central differences cost twelve more renders, each with its own projection, binning and sort. Here
//! the forward pass's tile lists and last contributors are reused and one front-to-back walk carries,
//! beside the transmittance `T`, its six tangents `dT` and the colour's `dC`:
//! `dC += c·(dα·T + α·dT)`, `dT ← dT·(1 − α) − T·dα`, `dα = −α·dσ` below the 0.99 clamp (0 above), and
//! `dσ` from the splat's `(du, dv, da, db, dc)` ([`super::project::project_tangent`]). Culling, the tile
//! rectangles and which splats a pixel composites are held fixed, as in the backward pass.

use super::camera::TILE;
use super::forward::{alpha_at, lane_centres, seg_of_bit, TileJob, ALPHA_MAX, BATCH, LANES, SEGS};
use super::project::{Splat, SplatTangent, ALPHA_MIN};

/// The tangent directions per view (the six coordinates of a pose).
pub(crate) const DIRS: usize = 6;

type Lanes = [f32; LANES];

/// Per-pixel state of one 8-lane segment.
#[derive(Clone, Copy)]
struct Seg<const NC: usize> {
    t: Lanes,
    dt: [Lanes; DIRS],
    dc: [[Lanes; NC]; DIRS],
    last: [u32; LANES],
}

/// Per-row terms of `dσ = dx·(q·dx + l) + m` (`dx`, `dy` = mean − pixel centre), one per direction.
struct RowTangent {
    q: [f32; DIRS],
    l: [f32; DIRS],
    m: [f32; DIRS],
}

fn row_tangent(s: &Splat, tan: &[SplatTangent; DIRS], dy: f32) -> RowTangent {
    // σ = ½a·dx² + b·dx·dy + ½c·dy², differentiated in (u, v, a, b, c) and collected by powers of dx.
    let q = tan.map(|[_, _, da, _, _]| 0.5 * da);
    let l = tan.map(|[du, dv, _, db, _]| s.a * du + s.b * dv + dy * db);
    let m = tan.map(|[du, dv, _, _, dc]| dy * (s.b * du + s.c * dv + 0.5 * dy * dc));
    RowTangent { q, l, m }
}

/// The colour tangents of one tile: writes `(rows, lanes × DIRS × NC)` row pieces of the
/// `(H, W, DIRS, NC)` image; `last` is the forward pass's tile-major last contributor (1-based).
pub(crate) fn tangent_tile<const NC: usize>(
    job: &TileJob,
    tangents: &[[SplatTangent; DIRS]],
    last: &[u32],
    background: &[f32],
    mut out: Vec<&mut [f32]>,
) {
    let px = lane_centres(job.x0);
    let zero = [0.0f32; LANES];
    let mut segs: Vec<[Seg<NC>; SEGS]> = (0..job.rows)
        .map(|r| {
            std::array::from_fn(|h| {
                let at = r * TILE + h * LANES;
                let last: [u32; LANES] = last[at..at + LANES].try_into().unwrap();
                Seg { t: [1.0; LANES], dt: [zero; DIRS], dc: [[zero; NC]; DIRS], last }
            })
        })
        .collect();
    // Bit `h·16 + r` while segment (r, h) still has a pixel whose last contributor is ahead.
    let max_last: Vec<[u32; SEGS]> =
        segs.iter().map(|row| row.each_ref().map(|s| *s.last.iter().max().unwrap())).collect();
    let mut live = 0u32;
    for (r, row) in max_last.iter().enumerate() {
        for (h, &m) in row.iter().enumerate() {
            live |= u32::from(m > 0) << (h * TILE + r);
        }
    }
    let k_end = max_last.iter().flatten().copied().max().unwrap_or(0) as usize;
    let (mut splats, mut colors) = (Vec::with_capacity(BATCH), Vec::with_capacity(BATCH));
    let mut tans = Vec::with_capacity(BATCH);
    let mut start = 0;
    while start < k_end && live != 0 {
        let end = k_end.min(start + BATCH);
        job.gather::<NC>(start..end, end..k_end.min(end + BATCH), &mut splats, &mut colors);
        tans.clear();
        tans.extend(job.ids[start..end].iter().map(|&g| tangents[g as usize]));
        for (j, ((&s, &col), tan)) in splats.iter().zip(&colors).zip(&tans).enumerate() {
            let k1 = (start + j) as u32 + 1;
            let plan = job.plan(&s);
            let mut work = plan.mask & live;
            while work != 0 {
                let bit = work.trailing_zeros();
                work &= work - 1;
                let (r, h) = seg_of_bit(bit);
                if k1 > max_last[r][h] {
                    live &= !(1 << bit);
                    continue;
                }
                let row = plan.row(r);
                tangent_seg::<NC>(&s, &row, &row_tangent(&s, tan, row.dy), &col, k1, &px[h], &mut segs[r][h]);
            }
        }
        start = end;
    }
    for (r, row) in segs.iter().enumerate() {
        for x in 0..job.lanes {
            let (seg, l) = (&row[x / LANES], x % LANES);
            let pixel = &mut out[r][x * DIRS * NC..(x + 1) * DIRS * NC];
            for d in 0..DIRS {
                for ch in 0..NC {
                    pixel[d * NC + ch] = seg.dc[d][ch][l] + seg.dt[d][l] * background[ch];
                }
            }
        }
    }
}

/// One splat (1-based list index `k1`) over one segment, front to back; branch-free (vector selects).
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn tangent_seg<const NC: usize>(
    s: &Splat,
    row: &super::forward::RowTerms,
    tan: &RowTangent,
    col: &[f32; NC],
    k1: u32,
    px: &Lanes,
    st: &mut Seg<NC>,
) {
    for l in 0..LANES {
        let dx = s.u - px[l];
        let (sigma, g, alpha) = alpha_at(s, row, dx);
        // The forward pass composited exactly these: past its last contributor a pixel had stopped.
        let taken = (k1 <= st.last[l]) & (sigma >= 0.0) & (alpha >= ALPHA_MIN);
        let a = if taken { alpha } else { 0.0 };
        let slope = if taken & (s.opacity * g < ALPHA_MAX) { -alpha } else { 0.0 };
        let t = st.t[l];
        for d in 0..DIRS {
            let d_alpha = slope * dx.mul_add(tan.q[d].mul_add(dx, tan.l[d]), tan.m[d]);
            let dt = st.dt[d][l];
            let w = d_alpha * t + a * dt;
            for ch in 0..NC {
                st.dc[d][ch][l] += col[ch] * w;
            }
            st.dt[d][l] = dt * (1.0 - a) - t * d_alpha;
        }
        st.t[l] = t * (1.0 - a);
    }
}

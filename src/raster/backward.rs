//! Back-to-front gradient pass of one tile (RASTER_MATH.md, "Backward"), vectorised across the 16 lanes
//! of a tile row like the forward pass. Each (tile, splat) pair gets its own gradient slot: the sum
//! over the tile's pixels in lane order, so no two threads ever write the same memory.

use super::camera::TILE;
use super::forward::{alpha_at, lane_centres, row_span, TileJob, ALPHA_MAX};
use super::project::{Splat, SplatGrad, ALPHA_MIN};

type Row = [f32; TILE];

/// The forward state and upstream gradients of one tile (tile-major, as stored by the forward pass),
/// plus the upstream image gradients (row-major, whole image) and the background.
pub(crate) struct TileGradIn<'a> {
    pub t_final: &'a [f32],
    pub last: &'a [u32],
    pub width: usize,
    pub grad_color: &'a [f32],
    pub grad_depth: &'a [f32],
    pub grad_alpha: &'a [f32],
    pub background: &'a [f32],
}

/// Per-lane gradient sums of one splat over the rows of a tile.
struct LaneAcc<const NC: usize> {
    u: Row,
    v: Row,
    a: Row,
    b: Row,
    c: Row,
    opacity: Row,
    z: Row,
    color: [Row; NC],
}

impl<const NC: usize> LaneAcc<NC> {
    fn new() -> Self {
        let z = [0.0; TILE];
        LaneAcc { u: z, v: z, a: z, b: z, c: z, opacity: z, z, color: [z; NC] }
    }

    fn reduce(&self) -> SplatGrad {
        let sum = |r: &Row| r.iter().sum::<f32>();
        let mut color = [0.0; 3];
        for (ch, c) in color.iter_mut().take(NC).enumerate() {
            *c = sum(&self.color[ch]);
        }
        SplatGrad {
            u: sum(&self.u),
            v: sum(&self.v),
            a: sum(&self.a),
            b: sum(&self.b),
            c: sum(&self.c),
            opacity: sum(&self.opacity),
            z: sum(&self.z),
            color,
        }
    }
}

/// Per-pixel running state of the backward pass for one tile row.
struct RowState<const NC: usize> {
    t: Row,
    /// Colour and depth composited behind the current splat.
    s_color: [Row; NC],
    s_depth: Row,
    g_color: [Row; NC],
    g_depth: Row,
    /// `T_final·(∂L/∂V − Σ_k bg_k ∂L/∂C_k)`: the alpha and background terms of `∂L/∂α`, times `1 − α`.
    g_final: Row,
    last: [u32; TILE],
}

/// Gradient pass of one tile; fills `out[k]` for every tile-list index `k`, returns the evaluations.
pub(crate) fn backward_tile<const NC: usize>(
    job: &TileJob,
    input: &TileGradIn,
    out: &mut [SplatGrad],
) -> u64 {
    let px = lane_centres(job.x0);
    let mut rows: Vec<RowState<NC>> = (0..job.rows).map(|r| row_state::<NC>(job, input, r)).collect();
    let row_last: Vec<u32> = rows.iter().map(|s| *s.last.iter().max().unwrap()).collect();
    let k_end = row_last.iter().copied().max().unwrap_or(0) as usize;
    out.fill(SplatGrad::default());
    let mut evaluations = 0u64;
    for k in (0..k_end).rev() {
        let g = job.ids[k] as usize;
        let s = &job.splats[g].splat;
        let col: [f32; NC] = std::array::from_fn(|ch| job.colors[g * NC + ch]);
        let mut acc = LaneAcc::<NC>::new();
        for r in row_span(s, job.y0, job.rows) {
            if row_last[r] as usize <= k {
                continue;
            }
            evaluations += job.lanes as u64;
            let py = (job.y0 + r) as f32 + 0.5;
            backward_row::<NC>(s, &col, k as u32, &px, py, &mut rows[r], &mut acc);
        }
        out[k] = acc.reduce();
    }
    evaluations
}

fn row_state<const NC: usize>(job: &TileJob, input: &TileGradIn, r: usize) -> RowState<NC> {
    let z = [0.0f32; TILE];
    let mut st = RowState {
        t: input.t_final[r * TILE..(r + 1) * TILE].try_into().unwrap(),
        s_color: [z; NC],
        s_depth: z,
        g_color: [z; NC],
        g_depth: z,
        g_final: z,
        last: input.last[r * TILE..(r + 1) * TILE].try_into().unwrap(),
    };
    for l in 0..job.lanes {
        let p = (job.y0 + r) * input.width + job.x0 + l;
        let mut bg_dot = 0.0;
        for ch in 0..NC {
            st.g_color[ch][l] = input.grad_color[p * NC + ch];
            bg_dot += input.background[ch] * st.g_color[ch][l];
        }
        st.g_depth[l] = input.grad_depth[p];
        st.g_final[l] = st.t[l] * (input.grad_alpha[p] - bg_dot);
    }
    st
}

/// One splat (tile-list index `k`) over one tile row, back to front; branch-free (vector selects).
/// Indexed lanes (not iterators) keep the loop a plain vectorisable lane loop.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn backward_row<const NC: usize>(
    s: &Splat,
    col: &[f32; NC],
    k: u32,
    px: &Row,
    py: f32,
    st: &mut RowState<NC>,
    acc: &mut LaneAcc<NC>,
) {
    let dy = s.v - py;
    for l in 0..TILE {
        let dx = s.u - px[l];
        let (sigma, g, alpha) = alpha_at(s, dx, dy);
        let valid = k < st.last[l] && sigma >= 0.0 && alpha >= ALPHA_MIN;
        let ra = 1.0 / (1.0 - alpha);
        let t = if valid { st.t[l] * ra } else { st.t[l] };
        let w = if valid { alpha * t } else { 0.0 };
        let mut g_alpha = (s.z * t - st.s_depth[l] * ra) * st.g_depth[l] + st.g_final[l] * ra;
        for ch in 0..NC {
            g_alpha += (col[ch] * t - st.s_color[ch][l] * ra) * st.g_color[ch][l];
            acc.color[ch][l] += w * st.g_color[ch][l];
            st.s_color[ch][l] += col[ch] * w;
        }
        acc.z[l] += w * st.g_depth[l];
        st.s_depth[l] += s.z * w;
        st.t[l] = t;
        let og = s.opacity * g;
        let unclamped = valid && og < ALPHA_MAX;
        let g_sigma = if unclamped { -og * g_alpha } else { 0.0 };
        acc.opacity[l] += if unclamped { g * g_alpha } else { 0.0 };
        acc.a[l] += 0.5 * g_sigma * dx * dx;
        acc.b[l] += g_sigma * dx * dy;
        acc.c[l] += 0.5 * g_sigma * dy * dy;
        acc.u[l] += g_sigma * (s.a * dx + s.b * dy);
        acc.v[l] += g_sigma * (s.b * dx + s.c * dy);
    }
}

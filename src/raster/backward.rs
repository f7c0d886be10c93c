//! Back-to-front gradient pass of one tile (RASTER_MATH.md, "Backward"), vectorised across the 8
//! lanes of a tile segment like the forward pass. Each (tile, splat) pair gets its own gradient slot:
//! the sum over the tile's pixels in a fixed lane order, so no two threads ever write the same memory.

use super::camera::TILE;
use super::forward::{alpha_at, lane_centres, seg_of_bit, RowTerms, TileJob, ALPHA_MAX, BATCH, LANES, SEGS};
use super::project::{Splat, SplatGrad, ALPHA_MIN};

type Lanes = [f32; LANES];

/// The forward state of one tile (tile-major, as stored by the forward pass), the upstream image
/// gradients of its view (row-major, whole image) and the background.
pub(crate) struct TileGradIn<'a> {
    pub t_final: &'a [f32],
    pub last: &'a [u32],
    pub width: usize,
    pub grad_color: &'a [f32],
    pub grad_depth: &'a [f32],
    pub grad_alpha: &'a [f32],
    pub background: &'a [f32],
}

/// Per-lane gradient sums of one splat over the segments of a tile.
struct LaneAcc<const NC: usize> {
    u: Lanes,
    v: Lanes,
    a: Lanes,
    b: Lanes,
    c: Lanes,
    opacity: Lanes,
    z: Lanes,
    color: [Lanes; NC],
}

impl<const NC: usize> LaneAcc<NC> {
    fn new() -> Self {
        let z = [0.0; LANES];
        LaneAcc { u: z, v: z, a: z, b: z, c: z, opacity: z, z, color: [z; NC] }
    }

    fn reduce(&self) -> SplatGrad {
        let sum = |r: &Lanes| r.iter().sum::<f32>();
        let mut color = [0.0; 3];
        for (c, lanes) in color.iter_mut().zip(&self.color) {
            *c = sum(lanes);
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

/// Per-pixel running state of the backward pass for one segment.
struct Seg<const NC: usize> {
    t: Lanes,
    /// Colour and depth composited behind the current splat.
    s_color: [Lanes; NC],
    s_depth: Lanes,
    g_color: [Lanes; NC],
    g_depth: Lanes,
    /// `T_final·(∂L/∂V − Σ_k bg_k ∂L/∂C_k)`: the alpha and background terms of `∂L/∂α`, times `1 − α`.
    g_final: Lanes,
    last: [u32; LANES],
    /// The largest `last` of the segment: splats behind it are skipped.
    max_last: u32,
}

/// Gradient pass of one tile; fills `out[k]` for every tile-list index `k`, returns the evaluations.
pub(crate) fn backward_tile<const NC: usize>(
    job: &TileJob,
    input: &TileGradIn,
    out: &mut [SplatGrad],
) -> u64 {
    let px = lane_centres(job.x0);
    let mut segs: Vec<[Seg<NC>; SEGS]> =
        (0..job.rows).map(|r| std::array::from_fn(|h| seg_state::<NC>(job, input, r, h))).collect();
    // Segments in the order in which they become relevant going back to front: segment (r, h) needs
    // the splats before its largest `last`; `relevant` has bit `h·16 + r` once it does.
    let mut activation: Vec<(u32, u32)> = segs
        .iter()
        .enumerate()
        .flat_map(|(r, row)| row.iter().enumerate().map(move |(h, s)| (s.max_last, (h * TILE + r) as u32)))
        .filter(|&(max_last, _)| max_last > 0)
        .collect();
    activation.sort_unstable_by(|a, b| b.cmp(a));
    let k_end = activation.first().map_or(0, |a| a.0 as usize);
    let (mut relevant, mut next) = (0u32, 0);
    out.fill(SplatGrad::default());
    let mut evaluations = 0u64;
    let (mut splats, mut colors) = (Vec::with_capacity(BATCH), Vec::with_capacity(BATCH));
    let mut end = k_end;
    while end > 0 {
        let start = end.saturating_sub(BATCH);
        job.gather::<NC>(start..end, start.saturating_sub(BATCH)..start, &mut splats, &mut colors);
        for (j, (&s, &col)) in splats.iter().zip(&colors).enumerate().rev() {
            let k = start + j;
            while next < activation.len() && activation[next].0 as usize > k {
                relevant |= 1 << activation[next].1;
                next += 1;
            }
            // (Copies: locals that provably do not alias the tile state keep the lane loop vectorised.)
            let plan = job.plan(&s);
            let mut work = plan.mask & relevant;
            if work == 0 {
                continue;
            }
            let mut acc = LaneAcc::<NC>::new();
            while work != 0 {
                let bit = work.trailing_zeros();
                work &= work - 1;
                let (r, h) = seg_of_bit(bit);
                evaluations += job.seg_lanes(h) as u64;
                backward_seg::<NC>(&s, &plan.row(r), &col, k as u32, &px[h], &mut segs[r][h], &mut acc);
            }
            out[k] = acc.reduce();
        }
        end = start;
    }
    evaluations
}

fn seg_state<const NC: usize>(job: &TileJob, input: &TileGradIn, r: usize, h: usize) -> Seg<NC> {
    let z = [0.0f32; LANES];
    let at = r * TILE + h * LANES;
    let mut st = Seg {
        t: input.t_final[at..at + LANES].try_into().unwrap(),
        s_color: [z; NC],
        s_depth: z,
        g_color: [z; NC],
        g_depth: z,
        g_final: z,
        last: input.last[at..at + LANES].try_into().unwrap(),
        max_last: 0,
    };
    st.max_last = *st.last.iter().max().unwrap();
    for l in 0..job.seg_lanes(h) {
        let p = (job.y0 + r) * input.width + job.x0 + h * LANES + l;
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

/// One splat (tile-list index `k`) over one segment, back to front; branch-free (vector selects).
/// Indexed lanes (not iterators) keep the loop a plain vectorisable lane loop.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn backward_seg<const NC: usize>(
    s: &Splat,
    row: &RowTerms,
    col: &[f32; NC],
    k: u32,
    px: &Lanes,
    st: &mut Seg<NC>,
    acc: &mut LaneAcc<NC>,
) {
    let dy = row.dy;
    for l in 0..LANES {
        let dx = s.u - px[l];
        let (sigma, g, alpha) = alpha_at(s, row, dx);
        let valid = (k < st.last[l]) & (sigma >= 0.0) & (alpha >= ALPHA_MIN);
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
        let unclamped = valid & (og < ALPHA_MAX);
        let g_sigma = if unclamped { -og * g_alpha } else { 0.0 };
        acc.opacity[l] += if unclamped { g * g_alpha } else { 0.0 };
        acc.a[l] += 0.5 * g_sigma * dx * dx;
        acc.b[l] += g_sigma * dx * dy;
        acc.c[l] += 0.5 * g_sigma * dy * dy;
        acc.u[l] += g_sigma * (s.a * dx + s.b * dy);
        acc.v[l] += g_sigma * (s.b * dx + s.c * dy);
    }
}

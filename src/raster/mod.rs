//! The multithreaded CPU Gaussian rasterizer (forward and analytic backward), gsplat semantics.
//!
//! Stages, each in its own module: [`project`] (EWA projection per Gaussian and view), [`tiles`]
//! (16×16 binning, per-tile depth order), [`forward`] (front-to-back compositing per tile),
//! [`backward`] (per-tile gradients, reduced per Gaussian in a fixed order, then the projection's
//! backward). Parallel with rayon over Gaussians and over (view, tile); no atomics anywhere, so the
//! results are bitwise identical for any thread count. Conventions: `RASTER_MATH.md`.

mod backward;
mod camera;
mod fastmath;
mod forward;
mod project;
mod tangent;
mod tiles;

use rayon::prelude::*;

pub use camera::{Camera, TILE};

use crate::error::{Error, Result};
use backward::{backward_tile, TileGradIn};
use camera::View;
use forward::{render_tile, TileCounts, TileJob, TileOut};
use project::{project, project_backward, project_tangent, Params, Projected, SplatGrad, SplatTangent};
use tangent::{tangent_tile, DIRS};
use tiles::{bin, pairs_by_splat, split_by_offsets, Bins};

/// Pixels per tile.
const AREA: usize = TILE * TILE;

/// The Gaussians to render, as flat row-major arrays. Opacities are already activated (in (0, 1)).
#[derive(Clone, Copy, Debug)]
pub struct Gaussians<'a> {
    /// (N, 3) world positions.
    pub means: &'a [f32],
    /// (N, 3) log standard deviations.
    pub log_scales: &'a [f32],
    /// (N, 4) `(w, x, y, z)`, normalised inside; a zero quaternion renders as the identity.
    pub quats: &'a [f32],
    /// (N,)
    pub opacities: &'a [f32],
    /// (N, C), C in 1..=3.
    pub colors: &'a [f32],
    /// C (explicit, so that N = 0 still has a channel count).
    pub channels: usize,
}

/// Owned buffers of a [`Gaussians`] set, for code that builds its own clouds (benches, tests); the
/// bindings borrow numpy's arrays instead.
#[derive(Clone, Debug, Default)]
pub struct GaussianBuffers {
    pub means: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub quats: Vec<f32>,
    pub opacities: Vec<f32>,
    pub colors: Vec<f32>,
    pub channels: usize,
}

impl GaussianBuffers {
    /// Empty buffers for `channels` colour channels.
    pub fn new(channels: usize) -> Self {
        Self { channels, ..Self::default() }
    }

    pub fn view(&self) -> Gaussians<'_> {
        Gaussians {
            means: &self.means,
            log_scales: &self.log_scales,
            quats: &self.quats,
            opacities: &self.opacities,
            colors: &self.colors,
            channels: self.channels,
        }
    }
}

impl Gaussians<'_> {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    fn params(&self, i: usize) -> Params<'_> {
        Params {
            mean: &self.means[3 * i..3 * i + 3],
            log_scale: &self.log_scales[3 * i..3 * i + 3],
            quat: &self.quats[4 * i..4 * i + 4],
            opacity: self.opacities[i],
            color: &self.colors[self.channels * i..self.channels * (i + 1)],
        }
    }

    fn validate(&self) -> Result<usize> {
        let n = self.len();
        let shapes = [
            ("means", self.means.len(), 3),
            ("log_scales", self.log_scales.len(), 3),
            ("quats", self.quats.len(), 4),
        ];
        for (name, len, width) in shapes {
            if len != n * width {
                return Err(Error::Invalid(format!("raster: {name} has {len} values, expected {n}×{width}")));
            }
        }
        let c = self.channels;
        if !(1..=3).contains(&c) || self.colors.len() != n * c {
            return Err(Error::Invalid(format!(
                "raster: colors has {} values, expected {n}×{c} with 1 to 3 channels",
                self.colors.len()
            )));
        }
        Ok(c)
    }
}

struct ViewState {
    proj: Vec<Projected>,
    bins: Bins,
    /// Tile-major per-pixel final transmittance and `last` (see [`forward::TileOut`]).
    t_final: Vec<f32>,
    last: Vec<u32>,
}

/// What the backward pass needs from the forward pass: projections, per-tile sorted lists and the
/// per-pixel final transmittance and last contributor. Opaque to callers.
pub struct RasterState {
    cam: Camera,
    channels: usize,
    num_gaussians: usize,
    background: Vec<f32>,
    views: Vec<ViewState>,
    /// Pixel–Gaussian evaluations of the forward pass (see [`Forward::evaluations`]).
    pub forward_evaluations: u64,
    /// The same in the standard (3DGS/gsplat) sense: every in-image pixel × every entry of its tile's
    /// depth-sorted list, up to and including the one at which the pixel saturated.
    pub forward_evaluations_standard: u64,
    /// The backward pass's standard count: every in-image pixel × the list entries up to and including
    /// its last contributor (the ones a gsplat-style backward visits for it).
    pub backward_evaluations_standard: u64,
}

impl RasterState {
    pub fn num_views(&self) -> usize {
        self.views.len()
    }

    pub fn channels(&self) -> usize {
        self.channels
    }
}

/// Forward outputs, row-major: colour (B, H, W, C), depth D and alpha V (B, H, W), radii (B, N).
pub struct Forward {
    pub color: Vec<f32>,
    pub depth: Vec<f32>,
    pub alpha: Vec<f32>,
    pub radii: Vec<i32>,
    pub state: RasterState,
}

impl Forward {
    /// Pixel–Gaussian evaluations: (pixel, Gaussian) pairs whose alpha was computed, i.e. for every
    /// tile and every splat in its list until the tile stopped, the in-image pixels of the 8-pixel
    /// row segments that the splat's ellipse may reach (its tile plan) and that still had a live
    /// pixel. (The backward pass counts the same way, over segments with a pixel the splat was
    /// composited into or in front of.)
    /// This is fewer than the standard count, [`RasterState::forward_evaluations_standard`].
    pub fn evaluations(&self) -> u64 {
        self.state.forward_evaluations
    }
}

/// Gradients of the loss; same shapes as the inputs. `viewmats` is (B, 4, 4) with a zero last row;
/// `grad2d_norm` (B, N) is the norm of `∂L/∂(u, v)` per view (the densification signal).
pub struct Gradients {
    pub means: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub quats: Vec<f32>,
    pub opacities: Vec<f32>,
    pub colors: Vec<f32>,
    pub viewmats: Vec<f32>,
    pub grad2d_norm: Vec<f32>,
    pub evaluations: u64,
}

fn check_views(viewmats: &[f32]) -> Result<usize> {
    if viewmats.len() % 16 != 0 || viewmats.iter().any(|v| !v.is_finite()) {
        return Err(Error::Invalid(format!(
            "raster: viewmats must be finite (B, 4, 4); got {} values",
            viewmats.len()
        )));
    }
    Ok(viewmats.len() / 16)
}

/// Where the tiles of a view are and what each composites.
fn tile_jobs<'a>(cam: &Camera, view: &'a ViewState) -> impl Iterator<Item = TileJob<'a>> {
    let (w, h, tx) = (cam.width as usize, cam.height as usize, cam.tiles_x());
    (0..cam.num_tiles()).map(move |t| {
        let (x0, y0) = ((t % tx) * TILE, (t / tx) * TILE);
        TileJob {
            x0,
            y0,
            lanes: TILE.min(w - x0),
            rows: TILE.min(h - y0),
            ids: view.bins.tile(t),
            splats: &view.proj,
        }
    })
}

/// The pieces of a row-major (B, H, W, `per_px`) image that each tile covers (one per tile row), in
/// job order (views, then tiles): disjoint mutable slices, so that tiles write their pixels in parallel.
fn tile_rows<'a>(img: &'a mut [f32], cam: &Camera, per_px: usize) -> Vec<Vec<&'a mut [f32]>> {
    let (w, h, tx, nt) = (cam.width as usize, cam.height as usize, cam.tiles_x(), cam.num_tiles());
    let views = img.len() / (w * h * per_px);
    let mut tiles: Vec<Vec<&mut [f32]>> = (0..views * nt).map(|_| Vec::with_capacity(TILE)).collect();
    for (row, line) in img.chunks_mut(w * per_px).enumerate() {
        let first = (row / h) * nt + (row % h / TILE) * tx;
        for (t, piece) in line.chunks_mut(TILE * per_px).enumerate() {
            tiles[first + t].push(piece);
        }
    }
    tiles
}

/// Run `f` with the channel count as a compile-time constant (the per-pixel loops unroll over it).
macro_rules! with_channels {
    ($nc:expr, $f:ident, $($arg:expr),*) => {
        match $nc {
            1 => $f::<1>($($arg),*),
            2 => $f::<2>($($arg),*),
            _ => $f::<3>($($arg),*),
        }
    };
}

/// Render B views of the Gaussians. `background` has one value per colour channel.
pub fn forward(gs: &Gaussians, viewmats: &[f32], cam: &Camera, background: &[f32]) -> Result<Forward> {
    cam.validate()?;
    let nc = gs.validate()?;
    let b = check_views(viewmats)?;
    if background.len() != nc {
        return Err(Error::Invalid(format!(
            "raster: background has {} values for {nc} colour channels",
            background.len()
        )));
    }
    let lims = cam.fov_limits();
    let nt = cam.num_tiles();
    let mut views: Vec<ViewState> = viewmats
        .chunks_exact(16)
        .map(|m| {
            let view = View::from_row_major(m);
            let proj: Vec<Projected> = (0..gs.len())
                .into_par_iter()
                .map(|i| project(&gs.params(i), &view, cam, &lims).unwrap_or_default())
                .collect();
            let bins = bin(&proj, cam.tiles_x(), cam.tiles_y());
            ViewState { proj, bins, t_final: Vec::new(), last: Vec::new() }
        })
        .collect();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut color = vec![0.0f32; b * h * w * nc];
    let mut depth = vec![0.0f32; b * h * w];
    let mut alpha = vec![0.0f32; b * h * w];
    let mut t_final: Vec<Vec<f32>> = (0..b).map(|_| vec![0.0; nt * AREA]).collect();
    let mut last: Vec<Vec<u32>> = (0..b).map(|_| vec![0; nt * AREA]).collect();
    let jobs: Vec<TileJob> = views.iter().flat_map(|v| tile_jobs(cam, v)).collect();
    let outs: Vec<TileOut> = tile_rows(&mut color, cam, nc)
        .into_iter()
        .zip(tile_rows(&mut depth, cam, 1))
        .zip(tile_rows(&mut alpha, cam, 1))
        .zip(t_final.iter_mut().flat_map(|v| v.chunks_mut(AREA)))
        .zip(last.iter_mut().flat_map(|v| v.chunks_mut(AREA)))
        .map(|((((color, depth), alpha), t_final), last)| TileOut { color, depth, alpha, t_final, last })
        .collect();
    let counts = jobs
        .par_iter()
        .zip(outs.into_par_iter())
        .map(|(job, out)| with_channels!(nc, render_tile, job, out, background))
        .reduce(TileCounts::default, |a, b| a + b);
    let backward_standard = last.iter().flatten().map(|&k| u64::from(k)).sum();
    for ((v, t), l) in views.iter_mut().zip(t_final).zip(last) {
        v.t_final = t;
        v.last = l;
    }
    let radii = views.iter().flat_map(|v| v.proj.iter().map(|p| p.radius)).collect();
    let state = RasterState {
        cam: *cam,
        channels: nc,
        num_gaussians: gs.len(),
        background: background.to_vec(),
        views,
        forward_evaluations: counts.segments,
        forward_evaluations_standard: counts.standard,
        backward_evaluations_standard: backward_standard,
    };
    Ok(Forward { color, depth, alpha, radii, state })
}

/// The (B, 6, 4, 4) tangents `d(exp(ε·ξ̂)·V)/dε = ξ̂·V` of B row-major view matrices along the six unit
/// twists `ξ` (translation x, y, z, then rotation about x, y, z), perturbing each view on the left, in
/// its camera frame: the directions a pose solver moves a camera in, as [`forward_jvp`] takes them.
pub fn twist_tangents(viewmats: &[f32]) -> Vec<f32> {
    let mut out = Vec::with_capacity(viewmats.len() * DIRS);
    for m in viewmats.chunks_exact(16) {
        for d in 0..DIRS {
            let mut hat = [[0.0f32; 4]; 4];
            if d < 3 {
                hat[d][3] = 1.0;
            } else {
                let (i, j) = [(2, 1), (0, 2), (1, 0)][d - 3];
                hat[i][j] = 1.0;
                hat[j][i] = -1.0;
            }
            for row in hat {
                out.extend((0..4).map(|c| (0..4).map(|k| row[k] * m[4 * k + c]).sum::<f32>()));
            }
        }
    }
    out
}

/// One tile of the tangent pass: its job, its view's splat tangents, the forward pass's last contributors.
type TangentJob<'a> = (TileJob<'a>, &'a [[SplatTangent; DIRS]], &'a [u32]);

/// A forward pass and the derivative of its colour along six tangents of each view.
pub struct PoseJvp {
    pub forward: Forward,
    /// (B, H, W, 6, C): `∂C/∂s` along each view's six tangents.
    pub d_color: Vec<f32>,
}

/// Render B views and, in forward mode, the colour's derivative along six tangents `(dR, dt)` of each
/// view, `tangents` (B, 6, 4, 4) row-major (the last rows are ignored): one pass where central
/// differences would take twelve renders. Its derivative is the backward pass's transpose: culling,
/// tile lists and which splats each pixel composites are held fixed.
pub fn forward_jvp(
    gs: &Gaussians,
    viewmats: &[f32],
    tangents: &[f32],
    cam: &Camera,
    background: &[f32],
) -> Result<PoseJvp> {
    let forward = forward(gs, viewmats, cam, background)?;
    let b = forward.state.views.len();
    if tangents.len() != b * DIRS * 16 || tangents.iter().any(|v| !v.is_finite()) {
        return Err(Error::Invalid(format!(
            "raster: tangents must be finite ({b}, {DIRS}, 4, 4); got {} values",
            tangents.len()
        )));
    }
    let (nc, lims) = (forward.state.channels, cam.fov_limits());
    let splat_tangents: Vec<Vec<[SplatTangent; DIRS]>> = viewmats
        .chunks_exact(16)
        .zip(tangents.chunks_exact(DIRS * 16))
        .zip(&forward.state.views)
        .map(|((m, dm), vs)| {
            let view = View::from_row_major(m);
            let dirs: [View; DIRS] = std::array::from_fn(|d| View::from_row_major(&dm[16 * d..16 * (d + 1)]));
            (0..gs.len())
                .into_par_iter()
                .map(|i| match vs.proj[i].radius {
                    0 => [[0.0; 5]; DIRS],
                    _ => project_tangent(&gs.params(i), &view, cam, &lims, &dirs),
                })
                .collect()
        })
        .collect();
    let mut d_color = vec![0.0f32; forward.color.len() * DIRS];
    let jobs: Vec<TangentJob> = forward
        .state
        .views
        .iter()
        .zip(&splat_tangents)
        .flat_map(|(v, tan)| {
            tile_jobs(cam, v).zip(v.last.chunks(AREA)).map(move |(job, last)| (job, &tan[..], last))
        })
        .collect();
    let bg = &forward.state.background;
    jobs.into_par_iter()
        .zip(tile_rows(&mut d_color, cam, DIRS * nc).into_par_iter())
        .for_each(|((job, tan, last), out)| with_channels!(nc, tangent_tile, &job, tan, last, bg, out));
    Ok(PoseJvp { forward, d_color })
}

/// Gaussians per block of the projection backward; the per-view pose gradient is summed per block
/// and then over blocks in order, so its bits do not depend on the thread count.
const BLOCK: usize = 512;

/// Gradients of a loss on the forward outputs, given its gradients wrt colour (B, H, W, C), depth and
/// alpha (B, H, W). `gs` and `viewmats` must be the forward pass's inputs.
pub fn backward(
    gs: &Gaussians,
    viewmats: &[f32],
    state: &RasterState,
    grad_color: &[f32],
    grad_depth: &[f32],
    grad_alpha: &[f32],
) -> Result<Gradients> {
    let nc = gs.validate()?;
    let b = check_views(viewmats)?;
    let (n, cam) = (gs.len(), &state.cam);
    let hw = cam.num_pixels();
    let sizes = [
        ("gaussians", n, state.num_gaussians),
        ("colour channels", nc, state.channels),
        ("views", b, state.views.len()),
        ("grad_color values", grad_color.len(), b * hw * nc),
        ("grad_depth values", grad_depth.len(), b * hw),
        ("grad_alpha values", grad_alpha.len(), b * hw),
    ];
    for (what, got, want) in sizes {
        if got != want {
            return Err(Error::Invalid(format!(
                "raster backward: {got} {what}, the forward pass had {want}"
            )));
        }
    }
    let w = cam.width as usize;

    // 1. Per-tile gradients, one slot per (tile, Gaussian) pair.
    let mut pair_grads: Vec<Vec<SplatGrad>> =
        state.views.iter().map(|v| vec![SplatGrad::default(); v.bins.num_pairs()]).collect();
    let mut tasks = Vec::new();
    for (vi, (v, pg)) in state.views.iter().zip(pair_grads.iter_mut()).enumerate() {
        let outs = split_by_offsets(pg, &v.bins.offsets);
        for ((t, job), out) in tile_jobs(cam, v).enumerate().zip(outs) {
            let input = TileGradIn {
                t_final: &v.t_final[t * AREA..(t + 1) * AREA],
                last: &v.last[t * AREA..(t + 1) * AREA],
                width: w,
                grad_color: &grad_color[vi * hw * nc..(vi + 1) * hw * nc],
                grad_depth: &grad_depth[vi * hw..(vi + 1) * hw],
                grad_alpha: &grad_alpha[vi * hw..(vi + 1) * hw],
                background: &state.background,
            };
            tasks.push((job, input, out));
        }
    }
    let evaluations: u64 = tasks
        .into_par_iter()
        .map(|(job, input, out)| with_channels!(nc, backward_tile, &job, &input, out))
        .sum();

    // 2. Per-Gaussian sums of the pair gradients, in tile order.
    let splat_grads: Vec<Vec<SplatGrad>> = state
        .views
        .iter()
        .zip(&pair_grads)
        .map(|(v, pg)| {
            let (offsets, positions) = pairs_by_splat(&v.bins, &v.proj);
            (0..n)
                .into_par_iter()
                .map(|i| {
                    let mut g = SplatGrad::default();
                    for &k in &positions[offsets[i]..offsets[i + 1]] {
                        g += &pg[k];
                    }
                    g
                })
                .collect()
        })
        .collect();
    drop(pair_grads);

    // 3. Through the projection, per Gaussian (summed over views) and per view (summed over Gaussians).
    let views: Vec<View> = viewmats.chunks_exact(16).map(View::from_row_major).collect();
    let lims = cam.fov_limits();
    let mut g = Gradients {
        means: vec![0.0; n * 3],
        log_scales: vec![0.0; n * 3],
        quats: vec![0.0; n * 4],
        opacities: vec![0.0; n],
        colors: vec![0.0; n * nc],
        viewmats: vec![0.0; b * 16],
        grad2d_norm: splat_grads.iter().flat_map(|sg| sg.iter().map(|s| s.u.hypot(s.v))).collect(),
        evaluations,
    };
    let partials: Vec<Vec<f64>> = g
        .means
        .par_chunks_mut(BLOCK * 3)
        .zip(g.log_scales.par_chunks_mut(BLOCK * 3))
        .zip(g.quats.par_chunks_mut(BLOCK * 4))
        .zip(g.opacities.par_chunks_mut(BLOCK))
        .zip(g.colors.par_chunks_mut(BLOCK * nc))
        .enumerate()
        .map(|(blk, ((((gm, gl), gq), go), gc))| {
            let mut pose = vec![0.0f64; b * 12];
            for j in 0..go.len() {
                let i = blk * BLOCK + j;
                for (vi, view) in views.iter().enumerate() {
                    let sg = &splat_grads[vi][i];
                    if state.views[vi].proj[i].radius == 0 {
                        continue;
                    }
                    go[j] += sg.opacity;
                    for ch in 0..nc {
                        gc[j * nc + ch] += sg.color[ch];
                    }
                    if !sg.touches_geometry() {
                        continue;
                    }
                    let pg = project_backward(&gs.params(i), view, cam, &lims, sg);
                    accumulate(&mut gm[3 * j..3 * j + 3], &pg.mean);
                    accumulate(&mut gl[3 * j..3 * j + 3], &pg.log_scale);
                    accumulate(&mut gq[4 * j..4 * j + 4], &pg.quat);
                    let acc = &mut pose[vi * 12..(vi + 1) * 12];
                    for (a, v) in acc.iter_mut().zip(pg.view_r.iter().chain(&pg.view_t)) {
                        *a += f64::from(*v);
                    }
                }
            }
            pose
        })
        .collect();
    for vi in 0..b {
        let mut sum = [0.0f64; 12];
        for p in &partials {
            for (s, v) in sum.iter_mut().zip(&p[vi * 12..(vi + 1) * 12]) {
                *s += v;
            }
        }
        let out = &mut g.viewmats[vi * 16..(vi + 1) * 16];
        for r in 0..3 {
            for c in 0..3 {
                out[r * 4 + c] = sum[r * 3 + c] as f32;
            }
            out[r * 4 + 3] = sum[9 + r] as f32;
        }
    }
    Ok(g)
}

fn accumulate(dst: &mut [f32], src: &[f32]) {
    for (d, s) in dst.iter_mut().zip(src) {
        *d += s;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CAM: Camera =
        Camera { width: 37, height: 21, fx: 30.0, fy: 30.0, cx: 18.0, cy: 10.0, near: 0.01, far: 100.0 };
    const VIEWS: [f32; 32] = [
        1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, //
        0.995, 0.0, 0.0998, 0.1, 0.0, 1.0, 0.0, -0.05, -0.0998, 0.0, 0.995, 0.2, 0.0, 0.0, 0.0, 1.0,
    ];

    /// A deterministic pseudo-random cloud in front of the camera, two colour channels.
    fn cloud(n: usize) -> GaussianBuffers {
        let mut state = 1u32;
        let mut r = move || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32
        };
        let mut s = GaussianBuffers::new(2);
        for _ in 0..n {
            s.means.extend([r() - 0.5, 0.6 * (r() - 0.5), 2.0 + r()]);
            s.log_scales.extend([-3.5 + r(), -3.5 + r(), -3.5 + r()]);
            s.quats.extend([r() - 0.5, r() - 0.5, r() - 0.5, r() - 0.5]);
            s.opacities.push(0.2 + 0.7 * r());
            s.colors.extend([r(), r()]);
        }
        s
    }

    /// Every output bit of a forward + backward pass.
    fn run_bits(gs: &Gaussians) -> Vec<u32> {
        let f = forward(gs, &VIEWS, &CAM, &[0.1, 0.2]).unwrap();
        let up: Vec<f32> = (0..f.color.len()).map(|i| ((i * 37) % 11) as f32 / 5.0 - 1.0).collect();
        let hw = f.depth.len();
        let g = backward(gs, &VIEWS, &f.state, &up, &up[..hw], &up[hw..2 * hw]).unwrap();
        [
            &f.color,
            &f.depth,
            &f.alpha,
            &g.means,
            &g.log_scales,
            &g.quats,
            &g.opacities,
            &g.colors,
            &g.viewmats,
            &g.grad2d_norm,
        ]
        .iter()
        .flat_map(|v| v.iter().map(|x| x.to_bits()))
        .collect()
    }

    #[test]
    fn identical_bits_for_any_thread_count() {
        let scene = cloud(600);
        let gs = scene.view();
        let with = |threads| {
            rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| run_bits(&gs))
        };
        let one = with(1);
        assert!(one.iter().any(|&b| b != 0));
        assert_eq!(one, with(2));
        assert_eq!(one, with(3));
    }

    /// Three huge opaque splats: every pixel composites the first (alpha clamped to 0.99), saturates at
    /// the second and never sees the third, so both counts are known exactly.
    #[test]
    fn evaluation_counts() {
        let means = [0.0, 0.0, 2.0, 0.0, 0.0, 3.0, 0.0, 0.0, 4.0];
        let quats = [1.0, 0.0, 0.0, 0.0].repeat(3);
        let gs = Gaussians {
            means: &means,
            log_scales: &[4.0; 9],
            quats: &quats,
            opacities: &[0.999; 3],
            colors: &[0.5; 3],
            channels: 1,
        };
        let f = forward(&gs, &VIEWS[..16], &CAM, &[0.0]).unwrap();
        let pixels = CAM.num_pixels() as u64;
        assert!(f.alpha.iter().all(|&a| (a - 0.99).abs() < 1e-6));
        assert_eq!(f.evaluations(), 2 * pixels);
        assert_eq!(f.state.forward_evaluations_standard, 2 * pixels);
        assert_eq!(f.state.backward_evaluations_standard, pixels);
        // Behind a translucent splat nothing saturates: every pixel walks the whole list.
        let ops = [0.5, 0.5, 0.5];
        let f = forward(&Gaussians { opacities: &ops, ..gs }, &VIEWS[..16], &CAM, &[0.0]).unwrap();
        assert_eq!(f.state.forward_evaluations_standard, 3 * pixels);
        assert_eq!(f.state.backward_evaluations_standard, 3 * pixels);
    }

    /// `⟨y, J·t⟩` from the JVP equals `⟨Jᵀ·y, t⟩` from the backward pass's view gradient, for every
    /// view and direction: the two passes linearise the same function.
    #[test]
    fn pose_jvp_is_the_transpose_of_the_backward_pass() {
        let scene = cloud(300);
        let gs = scene.view();
        let tangents = twist_tangents(&VIEWS);
        let jvp = forward_jvp(&gs, &VIEWS, &tangents, &CAM, &[0.1, 0.2]).unwrap();
        let f = &jvp.forward;
        let y: Vec<f32> = (0..f.color.len()).map(|i| ((i * 37) % 11) as f32 / 5.0 - 1.0).collect();
        let zeros = vec![0.0; f.depth.len()];
        let g = backward(&gs, &VIEWS, &f.state, &y, &zeros, &zeros).unwrap();
        let (hw, nc) = (CAM.num_pixels(), 2);
        for v in 0..2 {
            for d in 0..DIRS {
                let mut forward_mode = 0.0f64;
                for p in 0..hw {
                    for ch in 0..nc {
                        let at = ((v * hw + p) * DIRS + d) * nc + ch;
                        forward_mode += f64::from(y[(v * hw + p) * nc + ch]) * f64::from(jvp.d_color[at]);
                    }
                }
                let t = &tangents[(v * DIRS + d) * 16..(v * DIRS + d + 1) * 16];
                let reverse: f64 = (0..12).map(|k| f64::from(g.viewmats[v * 16 + k]) * f64::from(t[k])).sum();
                let tol = 2e-4 * forward_mode.abs().max(reverse.abs()).max(1.0);
                assert!(
                    (forward_mode - reverse).abs() < tol,
                    "view {v} dir {d}: {forward_mode} vs {reverse}"
                );
            }
        }
        assert_eq!(jvp.d_color.len(), f.color.len() * DIRS);
        assert!(jvp.d_color.iter().any(|&x| x.abs() > 1e-3));
    }

    #[test]
    fn pose_jvp_has_identical_bits_for_any_thread_count() {
        let scene = cloud(600);
        let gs = scene.view();
        let tangents = twist_tangents(&VIEWS);
        let with = |threads| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| forward_jvp(&gs, &VIEWS, &tangents, &CAM, &[0.1, 0.2]).unwrap().d_color)
        };
        let one: Vec<u32> = with(1).iter().map(|x| x.to_bits()).collect();
        assert_eq!(one, with(2).iter().map(|x| x.to_bits()).collect::<Vec<_>>());
        let bad = forward_jvp(&gs, &VIEWS, &tangents[..95], &CAM, &[0.1, 0.2]);
        assert!(matches!(bad, Err(Error::Invalid(m)) if m.contains("tangents")));
    }

    #[test]
    fn empty_scene_shows_the_background() {
        let scene = cloud(0);
        let f = forward(&scene.view(), &VIEWS, &CAM, &[0.1, 0.2]).unwrap();
        assert!(f.color.chunks(2).all(|c| c == [0.1, 0.2]));
        assert!(f.alpha.iter().all(|&a| a == 0.0) && f.radii.is_empty() && f.evaluations() == 0);
    }

    #[test]
    fn bad_inputs_are_reported() {
        let scene = cloud(3);
        let mut gs = scene.view();
        let err = |gs: &Gaussians, views: &[f32], bg: &[f32]| match forward(gs, views, &CAM, bg) {
            Err(Error::Invalid(m)) => m,
            _ => panic!("expected an error"),
        };
        assert!(err(&gs, &VIEWS[..15], &[0.0, 0.0]).contains("viewmats"));
        assert!(err(&gs, &VIEWS, &[0.0]).contains("background"));
        gs.quats = &scene.quats[..8];
        assert!(err(&gs, &VIEWS, &[0.0, 0.0]).contains("quats"));
        gs = scene.view();
        gs.channels = 4;
        assert!(err(&gs, &VIEWS, &[0.0; 4]).contains("colors"));
        let f = forward(&scene.view(), &VIEWS, &CAM, &[0.0, 0.0]).unwrap();
        let up = vec![0.0; 5];
        assert!(
            matches!(backward(&scene.view(), &VIEWS, &f.state, &up, &up, &up), Err(Error::Invalid(m)) if m.contains("grad_color"))
        );
    }
}

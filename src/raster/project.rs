//! EWA projection of 3-D Gaussians to screen-space splats (forward) and its analytic backward.
//!
//! Conventions (RASTER_MATH.md): `Σ = R(q̂) S² R(q̂)ᵀ`, `Σ2D = J W Σ Wᵀ Jᵀ + 0.3 I` with the 3DGS
//! field-of-view clamp inside `J`, opacity-aware screen extent, cull below `near`, above `far`, on a
//! non-positive determinant, below 1/255 opacity, or when the extent box misses the image.

use nalgebra::{Matrix2, Matrix2x3, Matrix3, Vector3};

use super::camera::{Camera, View, TILE};

/// Compositing skips a Gaussian whose alpha is below this (float32 constant, as gsplat).
pub const ALPHA_MIN: f32 = 1.0 / 255.0;
/// Low-pass dilation added to the diagonal of the screen covariance (px²).
const DILATION: f32 = 0.3;
/// Cap on the extent in standard deviations.
const MAX_EXTENT: f32 = 3.33;
/// Slack on the per-row reach test (1 % in G), so that rounding can only widen the pixels evaluated.
const TAU_MARGIN: f32 = 0.01;

/// A projected Gaussian: everything the per-pixel loops read, packed in one cache line.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Splat {
    pub u: f32,
    pub v: f32,
    /// Conic `(a, b, c)`: entries of `Σ2D⁻¹`, so `σ = ½(a dx² + c dy²) + b dx dy`.
    pub a: f32,
    pub b: f32,
    pub c: f32,
    pub opacity: f32,
    pub z: f32,
    /// `ln(255·o)` plus a small margin: pixels with `σ > tau` cannot reach alpha ≥ 1/255.
    pub tau: f32,
    /// `1/a`: locates the minimum of `σ` along a pixel row.
    pub inv_a: f32,
}

/// One Gaussian projected into one view; a culled one has radius 0 and an empty rectangle.
/// Exactly one cache line holding all the tile loops read (they read these in depth order, i.e. at
/// random addresses: one miss per splat, not two).
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(64))]
pub(crate) struct Projected {
    pub splat: Splat,
    /// The colour (C channels; the rest zero).
    pub color: [f32; 3],
    pub rect: Rect,
    pub radius: i32,
}

/// Tile rectangle `[x0, x1) × [y0, y1)`; empty for a culled Gaussian.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Rect {
    pub x0: u16,
    pub x1: u16,
    pub y0: u16,
    pub y1: u16,
}

impl Rect {
    pub fn area(&self) -> usize {
        (self.x1 - self.x0) as usize * (self.y1 - self.y0) as usize
    }
}

/// One Gaussian's parameters, borrowed from the caller's flat arrays.
#[derive(Clone, Copy)]
pub(crate) struct Params<'a> {
    pub mean: &'a [f32],
    pub log_scale: &'a [f32],
    pub quat: &'a [f32],
    pub opacity: f32,
    pub color: &'a [f32],
}

/// Normalised quaternion `(w, x, y, z)` and `1/|q|`; a zero (or non-finite) quaternion is the identity
/// with no gradient, so degenerate input can never produce NaN.
fn normalise(q: &[f32]) -> ([f32; 4], f32) {
    let n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if !(n2 > 1e-24 && n2.is_finite()) {
        return ([1.0, 0.0, 0.0, 0.0], 0.0);
    }
    let inv = 1.0 / n2.sqrt();
    ([q[0] * inv, q[1] * inv, q[2] * inv, q[3] * inv], inv)
}

#[rustfmt::skip]
fn rotation([w, x, y, z]: [f32; 4]) -> Matrix3<f32> {
    Matrix3::new(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )
}

/// Intermediate quantities shared by the forward projection and its backward.
struct Geometry {
    qhat: [f32; 4],
    inv_qnorm: f32,
    rq: Matrix3<f32>,
    scale: Vector3<f32>,
    cov_world: Matrix3<f32>,
    p: Vector3<f32>,
    cov_cam: Matrix3<f32>,
    /// The (possibly clamped) `x'`, `y'` of the Jacobian and whether each was clamped.
    tx: f32,
    ty: f32,
    clamped_x: bool,
    clamped_y: bool,
    jac: Matrix2x3<f32>,
    cov2d: Matrix2<f32>,
}

/// The projection Jacobian at camera point `p`, with the field-of-view clamp.
struct Jacobian {
    jac: Matrix2x3<f32>,
    /// The (possibly clamped) `x'`, `y'` and whether each was clamped.
    tx: f32,
    ty: f32,
    clamped_x: bool,
    clamped_y: bool,
}

fn jacobian(p: &Vector3<f32>, cam: &Camera, lims: &[f32; 4]) -> Jacobian {
    let z = p.z;
    let (xz, yz) = (p.x / z, p.y / z);
    let cxz = xz.clamp(-lims[0], lims[1]);
    let cyz = yz.clamp(-lims[2], lims[3]);
    let (tx, ty) = (cxz * z, cyz * z);
    let jac =
        Matrix2x3::new(cam.fx / z, 0.0, -cam.fx * tx / (z * z), 0.0, cam.fy / z, -cam.fy * ty / (z * z));
    Jacobian { jac, tx, ty, clamped_x: cxz != xz, clamped_y: cyz != yz }
}

fn camera_point(g: &Params, view: &View) -> Vector3<f32> {
    view.r * Vector3::new(g.mean[0], g.mean[1], g.mean[2]) + view.t
}

fn scales(g: &Params) -> Vector3<f32> {
    Vector3::new(g.log_scale[0].exp(), g.log_scale[1].exp(), g.log_scale[2].exp())
}

fn geometry(g: &Params, view: &View, cam: &Camera, lims: &[f32; 4]) -> Geometry {
    let (qhat, inv_qnorm) = normalise(g.quat);
    let rq = rotation(qhat);
    let scale = scales(g);
    let m = rq * Matrix3::from_diagonal(&scale);
    let cov_world = m * m.transpose();
    let p = camera_point(g, view);
    let cov_cam = view.r * cov_world * view.r.transpose();
    let Jacobian { jac, tx, ty, clamped_x, clamped_y } = jacobian(&p, cam, lims);
    let cov2d = jac * cov_cam * jac.transpose() + Matrix2::identity() * DILATION;
    Geometry { qhat, inv_qnorm, rq, scale, cov_world, p, cov_cam, tx, ty, clamped_x, clamped_y, jac, cov2d }
}

/// Project one Gaussian into one view: the splat, its tile rectangle and its screen radius
/// (`max(r_x, r_y)`), or `None` when culled.
pub(crate) fn project(g: &Params, view: &View, cam: &Camera, lims: &[f32; 4]) -> Option<Projected> {
    let p = camera_point(g, view);
    // Positive tests, so that NaN depths or opacities are culled too.
    let in_range = p.z >= cam.near && p.z <= cam.far && g.opacity >= ALPHA_MIN;
    if !in_range {
        return None;
    }
    // Σ2D = (J·W·R·S)(J·W·R·S)ᵀ + 0.3·I: one 2×3 factor instead of three 3×3 covariance products
    // (the backward pass, which needs those intermediates, uses `geometry`).
    let (qhat, _) = normalise(g.quat);
    let mut wrs = view.r * rotation(qhat);
    for (mut col, s) in wrs.column_iter_mut().zip(scales(g).iter()) {
        col *= *s;
    }
    let factor = jacobian(&p, cam, lims).jac * wrs;
    let s = factor * factor.transpose() + Matrix2::identity() * DILATION;
    let det = s[(0, 0)] * s[(1, 1)] - s[(0, 1)] * s[(1, 0)];
    let invertible = det > 0.0;
    if !invertible {
        return None;
    }
    let inv_det = 1.0 / det;
    let ln_reach = (g.opacity / ALPHA_MIN).ln();
    let extent = MAX_EXTENT.min((2.0 * ln_reach).sqrt());
    let rx = (extent * s[(0, 0)].sqrt()).ceil();
    let ry = (extent * s[(1, 1)].sqrt()).ceil();
    let visible = rx > 0.0 || ry > 0.0;
    if !visible {
        return None;
    }
    let u = cam.fx * p.x / p.z + cam.cx;
    let v = cam.fy * p.y / p.z + cam.cy;
    let (w, h) = (cam.width as f32, cam.height as f32);
    let in_image = u + rx > 0.0 && u - rx < w && v + ry > 0.0 && v - ry < h;
    if !in_image {
        return None;
    }
    let t = TILE as f32;
    let clamp_tile = |val: f32, n: usize| val.clamp(0.0, n as f32) as u16;
    let rect = Rect {
        x0: clamp_tile(((u - rx) / t).floor(), cam.tiles_x()),
        x1: clamp_tile(((u + rx) / t).ceil(), cam.tiles_x()),
        y0: clamp_tile(((v - ry) / t).floor(), cam.tiles_y()),
        y1: clamp_tile(((v + ry) / t).ceil(), cam.tiles_y()),
    };
    if rect.area() == 0 {
        return None;
    }
    let splat = Splat {
        u,
        v,
        a: s[(1, 1)] * inv_det,
        b: -s[(0, 1)] * inv_det,
        c: s[(0, 0)] * inv_det,
        opacity: g.opacity,
        z: p.z,
        tau: ln_reach + TAU_MARGIN,
        inv_a: det / s[(1, 1)],
    };
    let color = std::array::from_fn(|ch| g.color.get(ch).copied().unwrap_or(0.0));
    Some(Projected { splat, color, rect, radius: rx.max(ry) as i32 })
}

/// Upstream gradient of one Gaussian in one view, summed over its pixels.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct SplatGrad {
    pub u: f32,
    pub v: f32,
    pub a: f32,
    pub b: f32,
    pub c: f32,
    pub opacity: f32,
    pub z: f32,
    pub color: [f32; 3],
}

impl std::ops::AddAssign<&SplatGrad> for SplatGrad {
    fn add_assign(&mut self, o: &SplatGrad) {
        self.u += o.u;
        self.v += o.v;
        self.a += o.a;
        self.b += o.b;
        self.c += o.c;
        self.opacity += o.opacity;
        self.z += o.z;
        for (c, oc) in self.color.iter_mut().zip(&o.color) {
            *c += oc;
        }
    }
}

impl SplatGrad {
    /// Whether the splat's geometry receives any gradient (colour and opacity need no projection).
    pub fn touches_geometry(&self) -> bool {
        [self.u, self.v, self.a, self.b, self.c, self.z].iter().any(|&g| g != 0.0)
    }
}

/// Gradients of one Gaussian's 3-D parameters from one view, plus that view's pose gradient share.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct ParamGrad {
    pub mean: [f32; 3],
    pub log_scale: [f32; 3],
    pub quat: [f32; 4],
    /// `∂L/∂R_view` (row-major) and `∂L/∂t_view`.
    pub view_r: [f32; 9],
    pub view_t: [f32; 3],
}

/// Backward of [`project`] for a Gaussian that was not culled (see RASTER_MATH.md, "Backward through
/// the projection").
pub(crate) fn project_backward(
    g: &Params,
    view: &View,
    cam: &Camera,
    lims: &[f32; 4],
    up: &SplatGrad,
) -> ParamGrad {
    let geo = geometry(g, view, cam, lims);
    let (x, y, z) = (geo.p.x, geo.p.y, geo.p.z);
    let (fx, fy) = (cam.fx, cam.fy);
    let conic = geo.cov2d.try_inverse().unwrap_or_else(Matrix2::zeros);
    // Conic → screen covariance.
    let g_conic = Matrix2::new(up.a, 0.5 * up.b, 0.5 * up.b, up.c);
    let g_cov2d = -(conic * g_conic * conic);
    // Screen covariance → camera covariance and Jacobian (both operands symmetric).
    let g_cov_cam = geo.jac.transpose() * g_cov2d * geo.jac;
    let g_jac = 2.0 * g_cov2d * geo.jac * geo.cov_cam;
    // Camera-space mean: pixel mean, depth, and the Jacobian's dependence (clamped x', y' detached).
    let (iz, iz2) = (1.0 / z, 1.0 / (z * z));
    let iz3 = iz2 * iz;
    let mut gp =
        Vector3::new(fx * iz * up.u, fy * iz * up.v, -fx * x * iz2 * up.u - fy * y * iz2 * up.v + up.z);
    if !geo.clamped_x {
        gp.x -= fx * iz2 * g_jac[(0, 2)];
    }
    if !geo.clamped_y {
        gp.y -= fy * iz2 * g_jac[(1, 2)];
    }
    gp.z += -fx * iz2 * g_jac[(0, 0)] + 2.0 * fx * geo.tx * iz3 * g_jac[(0, 2)] - fy * iz2 * g_jac[(1, 1)]
        + 2.0 * fy * geo.ty * iz3 * g_jac[(1, 2)];
    // World side.
    let g_mean = view.r.transpose() * gp;
    let g_cov = view.r.transpose() * g_cov_cam * view.r;
    let s = Matrix3::from_diagonal(&geo.scale);
    let m = geo.rq * s;
    let g_m = (g_cov + g_cov.transpose()) * m;
    let mut g_log_scale = [0.0; 3];
    for (i, gs) in g_log_scale.iter_mut().enumerate() {
        *gs = geo.scale[i] * geo.rq.column(i).dot(&g_m.column(i));
    }
    let g_rq = g_m * s;
    let g_quat = quat_backward(geo.qhat, geo.inv_qnorm, &g_rq);
    // View matrix: p = R μ + t and Σ_c = R Σ Rᵀ.
    let mu = Vector3::new(g.mean[0], g.mean[1], g.mean[2]);
    let g_view_r = gp * mu.transpose()
        + g_cov_cam * view.r * geo.cov_world.transpose()
        + g_cov_cam.transpose() * view.r * geo.cov_world;
    let mut view_r = [0.0; 9];
    for (k, v) in view_r.iter_mut().enumerate() {
        *v = g_view_r[(k / 3, k % 3)];
    }
    ParamGrad {
        mean: [g_mean.x, g_mean.y, g_mean.z],
        log_scale: g_log_scale,
        quat: g_quat,
        view_r,
        view_t: [gp.x, gp.y, gp.z],
    }
}

/// How one splat moves along one tangent of its view: `(du, dv, da, db, dc)`.
pub(crate) type SplatTangent = [f32; 5];

/// Forward-mode derivative of [`project`]'s `(u, v, a, b, c)` along each tangent `(dR, dt)` of the view,
/// for a Gaussian that was not culled. It linearises the same function as [`project_backward`] (the
/// clamped `x'`, `y'` of the field-of-view clamp detached), so the two are each other's transpose.
pub(crate) fn project_tangent<const K: usize>(
    g: &Params,
    view: &View,
    cam: &Camera,
    lims: &[f32; 4],
    tangents: &[View; K],
) -> [SplatTangent; K] {
    let geo = geometry(g, view, cam, lims);
    let (x, y, z) = (geo.p.x, geo.p.y, geo.p.z);
    let (fx, fy) = (cam.fx, cam.fy);
    let (iz, iz2) = (1.0 / z, 1.0 / (z * z));
    let iz3 = iz2 * iz;
    let conic = geo.cov2d.try_inverse().unwrap_or_else(Matrix2::zeros);
    let mu = Vector3::new(g.mean[0], g.mean[1], g.mean[2]);
    let cov_rt = geo.cov_world * view.r.transpose();
    let jac_cov = geo.jac * geo.cov_cam;
    tangents.map(|d| {
        // p = R μ + t, Σ_c = R Σ Rᵀ.
        let dp = d.r * mu + d.t;
        let half = d.r * cov_rt;
        let d_cov_cam = half + half.transpose();
        let dtx = if geo.clamped_x { 0.0 } else { dp.x };
        let dty = if geo.clamped_y { 0.0 } else { dp.y };
        let d_jac = Matrix2x3::new(
            -fx * dp.z * iz2,
            0.0,
            -fx * dtx * iz2 + 2.0 * fx * geo.tx * dp.z * iz3,
            0.0,
            -fy * dp.z * iz2,
            -fy * dty * iz2 + 2.0 * fy * geo.ty * dp.z * iz3,
        );
        // Σ2D = J Σ_c Jᵀ + 0.3 I, and the conic is its inverse.
        let side = d_jac * jac_cov.transpose();
        let d_cov2d = side + side.transpose() + geo.jac * d_cov_cam * geo.jac.transpose();
        let d_conic = -(conic * d_cov2d * conic);
        [
            fx * (dp.x * iz - x * dp.z * iz2),
            fy * (dp.y * iz - y * dp.z * iz2),
            d_conic[(0, 0)],
            d_conic[(0, 1)],
            d_conic[(1, 1)],
        ]
    })
}

/// `∂L/∂q` from `∂L/∂R(q̂)`, through the normalisation `q̂ = q/|q|`.
fn quat_backward([w, x, y, z]: [f32; 4], inv_norm: f32, g: &Matrix3<f32>) -> [f32; 4] {
    let gw = 2.0
        * (-z * g[(0, 1)] + y * g[(0, 2)] + z * g[(1, 0)] - x * g[(1, 2)] - y * g[(2, 0)] + x * g[(2, 1)]);
    let gx = 2.0
        * (y * g[(0, 1)] + z * g[(0, 2)] + y * g[(1, 0)] - 2.0 * x * g[(1, 1)] - w * g[(1, 2)]
            + z * g[(2, 0)]
            + w * g[(2, 1)]
            - 2.0 * x * g[(2, 2)]);
    let gy = 2.0
        * (-2.0 * y * g[(0, 0)] + x * g[(0, 1)] + w * g[(0, 2)] + x * g[(1, 0)] + z * g[(1, 2)]
            - w * g[(2, 0)]
            + z * g[(2, 1)]
            - 2.0 * y * g[(2, 2)]);
    let gz = 2.0
        * (-2.0 * z * g[(0, 0)] - w * g[(0, 1)] + x * g[(0, 2)] + w * g[(1, 0)] - 2.0 * z * g[(1, 1)]
            + y * g[(1, 2)]
            + x * g[(2, 0)]
            + y * g[(2, 1)]);
    let dot = gw * w + gx * x + gy * y + gz * z;
    [
        (gw - dot * w) * inv_norm,
        (gx - dot * x) * inv_norm,
        (gy - dot * y) * inv_norm,
        (gz - dot * z) * inv_norm,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        Camera { width: 64, height: 48, fx: 60.0, fy: 55.0, cx: 31.0, cy: 25.0, near: 0.01, far: 1e10 }
    }

    fn identity() -> View {
        View { r: Matrix3::identity(), t: Vector3::zeros() }
    }

    #[test]
    fn zero_quaternion_is_identity_without_nan() {
        let params = Params {
            mean: &[0.1, 0.0, 2.0],
            log_scale: &[-2.0, -1.5, -2.5],
            quat: &[0.0; 4],
            opacity: 0.5,
            color: &[1.0],
        };
        let c = cam();
        let p = project(&params, &identity(), &c, &c.fov_limits()).unwrap();
        assert!(p.radius > 0 && p.splat.a.is_finite() && p.splat.b == 0.0);
        let up = SplatGrad { u: 1.0, v: -1.0, a: 0.5, b: 0.2, c: 0.3, opacity: 0.0, z: 1.0, color: [0.0; 3] };
        let g = project_backward(&params, &identity(), &c, &c.fov_limits(), &up);
        assert_eq!(g.quat, [0.0; 4]);
        assert!(g.mean.iter().chain(&g.log_scale).all(|v| v.is_finite()));
    }

    #[test]
    fn culls_behind_near_and_outside() {
        let c = cam();
        let lims = c.fov_limits();
        let at = |mean: &'static [f32]| {
            let p = Params {
                mean,
                log_scale: &[-3.0; 3],
                quat: &[1.0, 0.0, 0.0, 0.0],
                opacity: 0.9,
                color: &[1.0],
            };
            project(&p, &identity(), &c, &lims).is_some()
        };
        assert!(!at(&[0.0, 0.0, -1.0]));
        assert!(!at(&[0.0, 0.0, 0.005]));
        assert!(at(&[0.0, 0.0, 0.01]));
        assert!(!at(&[10.0, 0.0, 1.0]));
        assert!(at(&[0.0, 0.0, 1.0]));
    }

    /// The quaternion backward against central differences of `R(q/|q|)` contracted with a fixed matrix.
    #[test]
    fn quaternion_gradient_matches_finite_differences() {
        let q = [0.7f64, -0.3, 0.5, 0.2];
        let gmat = Matrix3::new(0.3f32, -1.0, 0.2, 0.5, 0.1, -0.7, 0.9, 0.4, -0.2);
        let f = |q: [f64; 4]| {
            let n = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
            let (w, x, y, z) = (q[0] / n, q[1] / n, q[2] / n, q[3] / n);
            let r = [
                [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
                [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
                [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
            ];
            (0..9).map(|k| r[k / 3][k % 3] * gmat[(k / 3, k % 3)] as f64).sum::<f64>()
        };
        let qf = q.map(|v| v as f32);
        let (qhat, inv) = normalise(&qf);
        let g = quat_backward(qhat, inv, &gmat);
        for i in 0..4 {
            let (mut qp, mut qm) = (q, q);
            qp[i] += 1e-6;
            qm[i] -= 1e-6;
            let fd = (f(qp) - f(qm)) / 2e-6;
            assert!((fd - g[i] as f64).abs() < 1e-4, "component {i}: fd {fd} vs {}", g[i]);
        }
    }
}

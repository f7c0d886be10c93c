//! Criterion benchmarks of the rasterizer: forward and backward of one 320×240 view of a
//! spacecraft-like cloud (the same construction as `benches/raster_bench.py`, which prints the full
//! table with thread counts and the torch reference). Thread count: `RAYON_NUM_THREADS`. Throughput is
//! in pixel–Gaussian evaluations in the standard (3DGS/gsplat) sense, the sense of the speed targets.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use evgs::raster::{backward, forward, forward_jvp, twist_tangents, Camera, GaussianBuffers};

/// splitmix64: a deterministic uniform stream in [0, 1) without a dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next()
    }
}

/// Gaussians on the surfaces of a 1.6×1.6×2.4 m body and two 4×1.2 m panels, sized to tile them.
fn spacecraft(n: usize) -> GaussianBuffers {
    let boxes = [
        ([0.0, 0.0, 0.0], [0.8, 0.8, 1.2]),
        ([-2.9, 0.0, 0.0], [2.0, 0.6, 0.02]),
        ([2.9, 0.0, 0.0], [2.0, 0.6, 0.02]),
    ];
    let area = |e: &[f32; 3]| 8.0 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2]);
    let total: f32 = boxes.iter().map(|(_, e)| area(e)).sum();
    let spacing = (total / n as f32).sqrt();
    let mut rng = Rng(7);
    let mut c = GaussianBuffers::new(1);
    for _ in 0..n {
        // A box with probability proportional to its surface area.
        let mut pick = rng.next() * total;
        let mut chosen = &boxes[boxes.len() - 1];
        for b in &boxes {
            if pick < area(&b.1) {
                chosen = b;
                break;
            }
            pick -= area(&b.1);
        }
        let (centre, ext) = chosen;
        let mut p: [f32; 3] = std::array::from_fn(|i| rng.range(-1.0, 1.0) * ext[i]);
        let face = (0..3).max_by(|&a, &b| (p[a] / ext[a]).abs().total_cmp(&(p[b] / ext[b]).abs())).unwrap();
        p[face] = ext[face].copysign(p[face]);
        c.means.extend((0..3).map(|i| p[i] + centre[i]));
        c.log_scales.extend((0..3).map(|_| (spacing * rng.range(0.4, 0.9)).ln()));
        c.quats.extend((0..4).map(|_| rng.range(-1.0, 1.0)));
        c.opacities.push(rng.range(0.5, 0.95));
        c.colors.push(rng.range(0.2, 0.9));
    }
    c
}

/// A 60° camera 9 m away, looking down at the spacecraft by 40° (row-major world-to-camera).
fn view(width: u32, height: u32) -> (Camera, Vec<f32>) {
    let f = 0.5 * width as f32 / 30f32.to_radians().tan();
    let cam = Camera {
        width,
        height,
        fx: f,
        fy: f,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
        near: 0.01,
        far: 1e10,
    };
    let (s, c) = 40f32.to_radians().sin_cos();
    (cam, vec![1.0, 0.0, 0.0, 0.0, 0.0, c, -s, 0.0, 0.0, s, c, 9.0, 0.0, 0.0, 0.0, 1.0])
}

fn bench(cr: &mut Criterion) {
    let (cam, vm) = view(320, 240);
    let mut group = cr.benchmark_group("raster_320x240");
    group.sample_size(10);
    for n in [10_000, 100_000] {
        let c = spacecraft(n);
        let gs = c.view();
        let out = forward(&gs, &vm, &cam, &[0.0]).unwrap();
        group.throughput(Throughput::Elements(out.state.forward_evaluations_standard));
        group.bench_with_input(BenchmarkId::new("forward", n), &gs, |b, gs| {
            b.iter(|| forward(gs, &vm, &cam, &[0.0]).unwrap())
        });
        let up: Vec<f32> = (0..cam.num_pixels()).map(|i| ((i * 7919) % 101) as f32 / 50.0 - 1.0).collect();
        group.throughput(Throughput::Elements(out.state.backward_evaluations_standard));
        group.bench_with_input(BenchmarkId::new("backward", n), &gs, |b, gs| {
            b.iter(|| backward(gs, &vm, &out.state, &up, &up, &up).unwrap())
        });
    }
    group.finish();
}

/// Tracking's pose Jacobian for one view: the forward-mode pass against the 13 renders of central
/// differences (the view and ±ε along each coordinate, one batched call), which it replaces.
fn pose_jacobian(cr: &mut Criterion) {
    let (cam, vm) = view(320, 240);
    let mut group = cr.benchmark_group("pose_jacobian_320x240");
    group.sample_size(10);
    let tangents = twist_tangents(&vm);
    // exp(±ε·ξ̂)·V ≈ V ± ε·ξ̂·V: the view and its twelve neighbours.
    let mut variants = vm.clone();
    for sign in [1.0f32, -1.0] {
        for t in tangents.chunks_exact(16) {
            variants.extend(vm.iter().zip(t).map(|(v, d)| v + sign * 1e-3 * d));
        }
    }
    for n in [10_000, 100_000] {
        let c = spacecraft(n);
        let gs = c.view();
        group.bench_with_input(BenchmarkId::new("forward_jvp", n), &gs, |b, gs| {
            b.iter(|| forward_jvp(gs, &vm, &tangents, &cam, &[0.0]).unwrap())
        });
        group.bench_with_input(BenchmarkId::new("central_differences_13_renders", n), &gs, |b, gs| {
            b.iter(|| forward(gs, &variants, &cam, &[0.0]).unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, bench, pose_jacobian);
criterion_main!(benches);

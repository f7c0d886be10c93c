//! Criterion bench for the loss kernels on what one mapping step evaluates: the SSIM term (11-px
//! window, σ = 1.5) of a window's two renders with its gradient, and the relief prior of both views'
//! depth with its gradient, at the coarse (320×240) and full (640×480) levels.
//! Run lean with `cargo bench --profile fast --bench loss`; `benches/loss_bench.py` puts torch beside it.

use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use evgs::loss::relief::depth_variation;
use evgs::loss::ssim::{ssim, SsimWindow};
use evgs::loss::Planes;

fn gaussian_taps(n: usize, sigma: f32) -> Vec<f32> {
    let half = (n - 1) as f32 / 2.0;
    let k: Vec<f32> = (0..n).map(|i| (-((i as f32 - half).powi(2)) / (2.0 * sigma * sigma)).exp()).collect();
    let sum: f32 = k.iter().sum();
    k.into_iter().map(|v| v / sum).collect()
}

fn image(len: usize, salt: usize) -> Vec<f32> {
    (0..len).map(|i| ((i * 7919 + salt * 104_729) % 1000) as f32 / 1000.0).collect()
}

fn losses(c: &mut Criterion) {
    let taps = gaussian_taps(11, 1.5);
    let window = SsimWindow { taps: &taps, c1: 1e-4, c2: 9e-4 };
    let mut g = c.benchmark_group("loss_kernels");
    g.sample_size(20).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(3));
    for (w, h) in [(320, 240), (640, 480)] {
        let pair = Planes { planes: 1, height: h, width: w };
        let (a, b) = (image(w * h, 1), image(w * h, 2));
        g.throughput(Throughput::Elements((w * h) as u64));
        g.bench_function(BenchmarkId::new("ssim_with_grad", format!("{w}x{h}")), |bench| {
            bench.iter(|| ssim(&a, &b, pair, &window, true).unwrap())
        });
        let views = Planes { planes: 2, height: h, width: w };
        let alpha: Vec<f32> = image(2 * w * h, 3).iter().map(|v| 0.3 + 0.7 * v).collect();
        let depth: Vec<f32> = image(2 * w * h, 4).iter().map(|v| 2.5 + v).collect();
        g.bench_function(BenchmarkId::new("depth_variation_with_grad", format!("2x{w}x{h}")), |bench| {
            bench.iter(|| depth_variation(&depth, &alpha, views, 0.5, true).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, losses);
criterion_main!(benches);

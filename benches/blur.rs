//! Criterion bench for the SSIM window's separable blur (11 taps, σ = 1.5) on the planes one SSIM call
//! filters: 5 statistics × a batch of 2 renders, at the coarse (160×120) and full (640×480) levels.
//! Run lean with `cargo bench --profile fast --bench blur`; `benches/loss_bench.py` puts torch beside it.

use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use evgs::loss::blur::correlate_valid;

fn gaussian_taps(n: usize, sigma: f32) -> Vec<f32> {
    let half = (n - 1) as f32 / 2.0;
    let k: Vec<f32> = (0..n).map(|i| (-((i as f32 - half).powi(2)) / (2.0 * sigma * sigma)).exp()).collect();
    let sum: f32 = k.iter().sum();
    k.into_iter().map(|v| v / sum).collect()
}

fn blur(c: &mut Criterion) {
    let taps = gaussian_taps(11, 1.5);
    let mut g = c.benchmark_group("ssim_blur_11taps");
    g.sample_size(20).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(3));
    for (w, h) in [(160, 120), (640, 480)] {
        let planes = 10;
        let x: Vec<f32> = (0..planes * w * h).map(|i| ((i * 7919) % 1000) as f32 / 1000.0).collect();
        g.throughput(Throughput::Elements((planes * w * h) as u64));
        g.bench_function(BenchmarkId::new("planes10", format!("{w}x{h}")), |b| {
            b.iter(|| correlate_valid(&x, planes, h, w, &taps).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, blur);
criterion_main!(benches);

//! Criterion benches for event frames and the window sampler (uniform random events on 640×480: the
//! cache-unfriendly worst case). Run lean with `cargo bench --profile fast --bench frames`.

use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use evgs::events::accumulate::{accumulate_into, frame_size, FrameParams};
use evgs::events::window::{SplitMix64, WindowMode, WindowSampler};
use evgs::events::Events;

const W: u32 = 640;
const H: u32 = 480;
const N: usize = 20_000_000;

fn uniform_events(seed: u64) -> Events {
    let mut r = SplitMix64::new(seed);
    let mut ev = Events::with_capacity(N, W, H);
    for i in 0..N {
        let bits = r.next_u64();
        let x = ((bits & 0xFFFF_FFFF) * u64::from(W)) >> 32;
        let y = ((bits >> 32) * u64::from(H)) >> 32;
        ev.push(i as i64, x as u16, y as u16, if bits & 1 == 0 { 1 } else { -1 });
    }
    ev
}

fn accumulate(c: &mut Criterion) {
    let ev = uniform_events(1);
    let mut g = c.benchmark_group("accumulate_640x480");
    g.sample_size(10).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(3));
    for (w, batch) in [(50_000, 32), (200_000, 16), (2_000_000, 4), (2_000_000, 1)] {
        let windows = WindowSampler::new(0..N, w, w, WindowMode::Paper, 1).unwrap().sample(batch).unwrap();
        g.throughput(Throughput::Elements((w * batch) as u64));
        for (name, c_off) in [("one_c", 0.1), ("two_c", 0.2)] {
            let params = FrameParams { c_on: 0.1, c_off, downsample_log2: 0 };
            let (fw, fh) = frame_size(W, H, params);
            let mut out = vec![0f32; batch * fw * fh];
            g.bench_function(BenchmarkId::new(name, format!("{}k_x{batch}", w / 1000)), |b| {
                b.iter(|| accumulate_into(ev.view(), &windows, params, None, &mut out).unwrap())
            });
        }
    }
    g.finish();
}

fn sample_windows(c: &mut Criterion) {
    let mut s = WindowSampler::new(0..N, 50_000, 2_000_000, WindowMode::Paper, 1).unwrap();
    let mut g = c.benchmark_group("window_sampler");
    g.throughput(Throughput::Elements(1024));
    g.bench_function("paper_1024", |b| b.iter(|| s.sample(1024).unwrap()));
    g.finish();
}

criterion_group!(benches, accumulate, sample_windows);
criterion_main!(benches);

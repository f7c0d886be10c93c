//! Decode rate of the camera formats (EVT 2.0, EVT 3.0, AEDAT 4.0) on 10 M synthetic events, fed in
//! 8 MiB pieces as the streaming reader does, into a reused output buffer (a converter reuses its
//! batch). Each runs on a 1-thread rayon pool and on the default pool (EVT 2.0 chunks and AEDAT 4
//! packets decode in parallel).
//! Run: `cargo bench --profile fast --bench decode_camera` (the `bench` profile is fat LTO: slow to build).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use evgs::events::aedat4::{encode_aedat4, parse_aedat4_header, Aedat4Compression, Aedat4Decoder};
use evgs::events::evt2::{encode_evt2, Evt2Decoder};
use evgs::events::evt3::{encode_evt3, Evt3Decoder};
use evgs::events::raw_header::parse_raw_header;
use evgs::events::{Decoder, Events};

const N: usize = 10_000_000;
const PIECE: usize = 8 << 20;
const W: u32 = 1280;
const H: u32 = 720;

/// Sensor-like events: ~10 events/µs in row bursts of 1–16 nearby pixels of one polarity.
fn events(n: usize) -> Events {
    let mut s = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    let mut ev = Events::with_capacity(n, W, H);
    let mut t = 1_000_000i64;
    while ev.len() < n {
        let r = next();
        t += i64::from(r % 10 == 0);
        let (y, p) = ((r >> 8) as u16 % H as u16, if (r >> 30) & 1 == 1 { 1 } else { -1 });
        let mut x = (r >> 32) as u16 % W as u16;
        for _ in 0..1 + (r >> 50) % 16 {
            if x >= W as u16 || ev.len() == n {
                break;
            }
            ev.push(t, x, y, p);
            x += 1 + (next() % 3) as u16;
        }
    }
    ev
}

/// Feed `payload` in `PIECE`-byte windows (growing a window that holds no complete record).
fn decode(dec: &mut impl Decoder, payload: &[u8], offset: usize, out: &mut Events) {
    out.t.clear();
    out.x.clear();
    out.y.clear();
    out.p.clear();
    let (mut pos, mut piece) = (0, PIECE);
    loop {
        let end = (pos + piece).min(payload.len());
        let used = dec.decode(&payload[pos..end], (offset + pos) as u64, out).unwrap();
        pos += used;
        if end == payload.len() {
            dec.finish(&payload[pos..], (offset + pos) as u64, out).unwrap();
            assert_eq!(out.len(), N);
            return;
        }
        piece = if used == 0 { piece * 2 } else { PIECE };
    }
}

/// CPU time of the calling thread (ns): on a shared machine this, unlike wall time, does not count
/// the time other processes hold the cores.
fn thread_cpu_ns() -> u64 {
    let stat = std::fs::read_to_string("/proc/thread-self/schedstat").unwrap_or_default();
    stat.split_whitespace().next().and_then(|v| v.parse().ok()).unwrap_or(0)
}

/// Best of three single-threaded runs, in millions of events per CPU-second.
fn cpu_rate(run: &mut dyn FnMut()) -> f64 {
    let best = (0..3)
        .map(|_| {
            let start = thread_cpu_ns();
            run();
            thread_cpu_ns() - start
        })
        .min()
        .unwrap();
    N as f64 / best.max(1) as f64 * 1e3
}

fn bench(c: &mut Criterion) {
    let ev = events(N);
    let mut out = Events::with_capacity(N, W, H);
    let mut group = c.benchmark_group("decode_camera");
    group.sample_size(10).throughput(Throughput::Elements(N as u64));

    // CPU rates are measured on a 1-thread pool: the calling thread's CPU time is all the work there.
    let single = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    for (name, file) in [("evt2", encode_evt2(ev.view()).unwrap()), ("evt3", encode_evt3(ev.view()).unwrap())]
    {
        let h = parse_raw_header(&file, name).unwrap();
        let payload = &file[h.data_offset..];
        let mut run = || {
            if name == "evt2" {
                decode(&mut Evt2Decoder::new(name, W, H, false), payload, h.data_offset, &mut out)
            } else {
                decode(&mut Evt3Decoder::new(name, W, H, false), payload, h.data_offset, &mut out)
            }
        };
        let rate = single.install(|| cpu_rate(&mut run));
        println!(
            "{name}: {:.2} bytes/event, {rate:.0} M events per CPU-second (1 thread)",
            payload.len() as f64 / N as f64
        );
        group.bench_function(format!("{name}_1thread"), |b| b.iter(|| single.install(&mut run)));
        group.bench_function(format!("{name}_rayon"), |b| b.iter(&mut run));
    }

    for (name, compression) in [
        ("none", Aedat4Compression::None),
        ("lz4", Aedat4Compression::Lz4),
        ("zstd", Aedat4Compression::Zstd),
    ] {
        let file = encode_aedat4(ev.view(), compression, 4096).unwrap();
        let h = parse_aedat4_header(&file, name).unwrap();
        let payload = &file[h.data_offset..];
        let mut run = || decode(&mut Aedat4Decoder::new(name, &h), payload, h.data_offset, &mut out);
        let rate = single.install(|| cpu_rate(&mut run));
        let size = payload.len() as f64 / N as f64;
        println!("aedat4 {name}: {size:.2} bytes/event, {rate:.0} M events per CPU-second (1 thread)");
        group.bench_function(format!("aedat4_{name}_1thread"), |b| b.iter(|| single.install(&mut run)));
        group.bench_function(format!("aedat4_{name}_rayon"), |b| b.iter(&mut run));
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

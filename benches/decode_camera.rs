//! Decode rate of the camera formats (EVT 2.0, EVT 3.0, AEDAT 4.0) on 10 M synthetic events, fed in
//! 8 MiB pieces as the streaming reader does. Run: `cargo bench --profile fast --bench decode_camera`.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion, Throughput};
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
fn decode(dec: &mut impl Decoder, payload: &[u8], offset: usize) -> Events {
    let mut out = Events::with_capacity(N, W, H);
    let (mut pos, mut piece) = (0, PIECE);
    loop {
        let end = (pos + piece).min(payload.len());
        let used = dec.decode(&payload[pos..end], (offset + pos) as u64, &mut out).unwrap();
        pos += used;
        if end == payload.len() {
            dec.finish(&payload[pos..], (offset + pos) as u64, &mut out).unwrap();
            return out;
        }
        piece = if used == 0 { piece * 2 } else { PIECE };
    }
}

fn bench(c: &mut Criterion) {
    let ev = events(N);
    let mut group = c.benchmark_group("decode_camera");
    group.sample_size(10).throughput(Throughput::Elements(N as u64));

    for (name, file) in [("evt2", encode_evt2(ev.view())), ("evt3", encode_evt3(ev.view()))] {
        let h = parse_raw_header(&file, name).unwrap();
        let payload = &file[h.data_offset..];
        println!("{name}: {} bytes per event", payload.len() as f64 / N as f64);
        group.bench_function(name, |b| {
            b.iter(|| {
                let got = if name == "evt2" {
                    decode(&mut Evt2Decoder::new(name, W, H, false), payload, h.data_offset)
                } else {
                    decode(&mut Evt3Decoder::new(name, W, H, false), payload, h.data_offset)
                };
                assert_eq!(got.len(), N);
            })
        });
    }

    let single = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    for (name, compression) in [
        ("none", Aedat4Compression::None),
        ("lz4", Aedat4Compression::Lz4),
        ("zstd", Aedat4Compression::Zstd),
    ] {
        let file = encode_aedat4(ev.view(), compression, 4096);
        let h = parse_aedat4_header(&file, name).unwrap();
        let payload = &file[h.data_offset..];
        println!("aedat4 {name}: {} bytes per event", payload.len() as f64 / N as f64);
        let run = || {
            let got = decode(&mut Aedat4Decoder::new(name, &h), payload, h.data_offset);
            assert_eq!(got.len(), N);
        };
        group.bench_function(format!("aedat4_{name}_1thread"), |b| {
            b.iter_batched(|| (), |()| single.install(run), BatchSize::PerIteration)
        });
        group.bench_function(format!("aedat4_{name}_rayon"), |b| b.iter(run));
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

//! Criterion benches for the text and NPY decoders (in-memory, so only the parsing is timed).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use evgs::events::npy::{encode_npy_rows, npy_header, parse_npy_header, NpyDecoder, NpyStyle};
use evgs::events::text::{encode_text, TextDecoder, TextOptions, TextStyle, TimeUnit};
use evgs::events::{Decoder, Events};

/// A deterministic, sorted, camera-like stream (LCG coordinates, ~2 M ev/s).
fn events(n: usize) -> Events {
    let mut ev = Events::with_capacity(n, 640, 480);
    let mut s = 0x2545_f491_4f6c_dd1du64;
    for i in 0..n {
        s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        ev.push(
            i as i64 / 2,
            ((s >> 33) % 640) as u16,
            ((s >> 17) % 480) as u16,
            if s >> 63 == 1 { 1 } else { -1 },
        );
    }
    ev
}

fn decode_all(dec: &mut impl Decoder, data: &[u8]) -> Events {
    let mut out = Events::default();
    let used = dec.decode(data, 0, &mut out).unwrap();
    dec.finish(&data[used..], used as u64, &mut out).unwrap();
    out
}

fn bench(c: &mut Criterion) {
    const N: usize = 1_000_000;
    let ev = events(N);
    let mut g = c.benchmark_group("decode");
    g.throughput(Throughput::Elements(N as u64));
    g.sample_size(10);
    for (name, unit, delimiter) in [("csv_us", TimeUnit::Us, b','), ("txt_s", TimeUnit::S, b' ')] {
        let text =
            encode_text(ev.view(), TextStyle { delimiter, time_unit: unit, header: true, zero_one: true });
        g.bench_function(name, |b| {
            b.iter(|| {
                let mut dec = TextDecoder::new(&text, "bench", &TextOptions::default()).unwrap();
                assert_eq!(decode_all(&mut dec, &text).len(), N);
            })
        });
    }
    let mut npy = npy_header(N as u64, NpyStyle::Structured);
    npy.extend(encode_npy_rows(ev.view(), NpyStyle::Structured));
    let layout = parse_npy_header(&npy, "bench", None, None).unwrap();
    g.bench_function("npy_structured", |b| {
        b.iter(|| {
            let mut dec = NpyDecoder::new("bench", layout.clone());
            assert_eq!(decode_all(&mut dec, &npy[layout.data_offset..]).len(), N);
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

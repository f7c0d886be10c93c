//! Prophesee EVT 2.0 decoder and encoder (32-bit words; see EVENT_FORMATS.md §2).
//!
//! A CD word carries the low 6 bits of time; EVT_TIME_HIGH words carry bits 33..6. The 34-bit
//! counter wraps every 2^34 µs, which is undone by comparing each new unwrapped base with the
//! previous unwrapped base (never the raw value with the unwrapped one).

use super::raw_header::{check_encodable, write_raw_header, DecodeStats, RawEncoding, MAX_COORD};
use super::{ColumnsMut, Decoder, Events, EventsView};
use crate::error::{Error, Result};
use rayon::prelude::*;

const CD_OFF: u32 = 0x0;
const CD_ON: u32 = 0x1;
const TIME_HIGH: u32 = 0x8;
const EXT_TRIGGER: u32 = 0xA;
/// Period of the 34-bit time counter in µs.
const WRAP: i64 = 1 << 34;
/// A TIME_HIGH that falls by at least `WRAP - 64 - WRAP_TOLERANCE` is a wrap (OpenEB HAL's tolerance).
const WRAP_TOLERANCE: i64 = 10_000;

/// Words per parallel chunk: big enough to amortise a chunk's setup, small enough to balance threads.
const CHUNK_WORDS: usize = 1 << 16;

/// Decoder registers between words.
#[derive(Debug, Clone, Copy, Default)]
struct State {
    /// Whether a TIME_HIGH has been seen; words before it have unknown time and are skipped.
    started: bool,
    /// Unwrapped time base (TIME_HIGH << 6 plus the wraps so far), µs.
    base: i64,
    /// Subtracted from every timestamp: the first base when `time_shift`, else 0.
    shift: i64,
}

impl State {
    /// Apply a TIME_HIGH word's 28-bit value.
    #[inline]
    fn time_high(&mut self, raw: u32, time_shift: bool) {
        let mut base = (i64::from(raw) << 6) + (self.base - self.base.rem_euclid(WRAP));
        if !self.started {
            self.started = true;
            self.shift = if time_shift { base } else { 0 };
        } else if is_wrap(self.base.rem_euclid(WRAP) >> 6, i64::from(raw)) {
            base += WRAP;
        }
        self.base = base;
    }
}

/// Whether TIME_HIGH going from `previous` to `raw` (28-bit values) is a wrap of the counter. It depends
/// on the raw values only, which is what lets a chunk be scanned without the state before it.
#[inline]
fn is_wrap(previous: i64, raw: i64) -> bool {
    (previous - raw) << 6 >= WRAP - 64 - WRAP_TOLERANCE
}

/// Word counts by kind: CD events, triggers, and anything else except TIME_HIGH.
#[derive(Debug, Clone, Copy, Default)]
struct Counts {
    cd: u64,
    triggers: u64,
    other: u64,
}

impl Counts {
    /// Count `words` (TIME_HIGH words are passed to `on_high` and not counted).
    fn of(words: &[u8], mut on_high: impl FnMut(u32)) -> Self {
        let (mut highs, mut triggers, mut other) = (0u64, 0u64, 0u64);
        for w in words.chunks_exact(4) {
            let w = u32::from_le_bytes(w.try_into().unwrap());
            match w >> 28 {
                CD_OFF | CD_ON => {}
                TIME_HIGH => {
                    highs += 1;
                    on_high(w & 0x0FFF_FFFF);
                }
                EXT_TRIGGER => triggers += 1,
                _ => other += 1,
            }
        }
        Counts { cd: (words.len() / 4) as u64 - highs - triggers - other, triggers, other }
    }
}

/// What the first pass learns about a chunk of words without knowing the state before it.
#[derive(Debug, Clone, Copy, Default)]
struct ChunkScan {
    /// Raw value of the chunk's first TIME_HIGH.
    first_high: Option<u32>,
    /// Raw value of the chunk's last TIME_HIGH.
    last_high: u32,
    /// Wraps between the chunk's own consecutive TIME_HIGHs.
    wraps: i64,
    /// Words before the first TIME_HIGH (all of them when there is none), and after it.
    before: Counts,
    after: Counts,
}

impl ChunkScan {
    fn of(words: &[u8]) -> Self {
        let first = words.chunks_exact(4).position(|w| w[3] >> 4 == TIME_HIGH as u8);
        let (head, tail) = words.split_at(first.map_or(words.len(), |i| 4 * i));
        let mut s = ChunkScan { before: Counts::of(head, |_| {}), ..Default::default() };
        if first.is_none() {
            return s;
        }
        let raw0 = u32::from_le_bytes(tail[..4].try_into().unwrap()) & 0x0FFF_FFFF;
        let (mut last, mut wraps) = (raw0, 0);
        s.after = Counts::of(&tail[4..], |raw| {
            wraps += i64::from(is_wrap(i64::from(last), i64::from(raw)));
            last = raw;
        });
        (s.first_high, s.last_high, s.wraps) = (Some(raw0), last, wraps);
        s
    }
}

/// Streaming EVT 2.0 decoder; fed the payload after the RAW header.
///
/// Decodes in two parallel passes over chunks of words: the first counts each chunk's events and
/// follows its TIME_HIGHs (a wrap depends only on consecutive raw values), a sequential prefix gives
/// every chunk its starting time base and output position, and the second writes the events straight
/// into their final place.
#[derive(Debug, Clone)]
pub struct Evt2Decoder {
    path: String,
    width: u32,
    height: u32,
    time_shift: bool,
    st: State,
    stats: DecodeStats,
    chunk_words: usize,
}

impl Evt2Decoder {
    /// `width`/`height` (0 = unknown) bound the coordinates; `time_shift` makes times relative to the
    /// first TIME_HIGH base as Metavision does by default (evgs keeps absolute times: `false`).
    pub fn new(path: &str, width: u32, height: u32, time_shift: bool) -> Self {
        Evt2Decoder {
            path: path.to_string(),
            width,
            height,
            time_shift,
            st: State::default(),
            stats: DecodeStats::default(),
            chunk_words: CHUNK_WORDS,
        }
    }

    /// What was skipped or dropped so far.
    pub fn stats(&self) -> DecodeStats {
        self.stats
    }

    /// Second pass over one chunk starting in state `st`: its CD events into `out` (sized by the first
    /// pass). On a coordinate outside the sensor returns the word index and the coordinates.
    fn fill(
        &self,
        words: &[u8],
        mut st: State,
        mut out: ColumnsMut<'_>,
    ) -> std::result::Result<(), (usize, u32, u32)> {
        let xlim = if self.width == 0 { MAX_COORD } else { self.width };
        let ylim = if self.height == 0 { MAX_COORD } else { self.height };
        let mut t0 = st.base - st.shift;
        let mut k = 0;
        for (i, word) in words.chunks_exact(4).enumerate() {
            let w = u32::from_le_bytes(word.try_into().unwrap());
            let kind = w >> 28;
            if kind <= CD_ON && st.started {
                let (x, y) = ((w >> 11) & 0x7FF, w & 0x7FF);
                if x >= xlim || y >= ylim {
                    return Err((i, x, y));
                }
                out.set(k, t0 + i64::from((w >> 22) & 0x3F), x as u16, y as u16, kind as i8 * 2 - 1);
                k += 1;
            } else if kind == TIME_HIGH {
                st.time_high(w & 0x0FFF_FFFF, self.time_shift);
                t0 = st.base - st.shift;
            }
        }
        // Every slot written: `Decoder::decode` relies on this to append them.
        assert_eq!(k, out.t.len(), "EVT 2.0 first and second pass disagree");
        Ok(())
    }
}

impl Decoder for Evt2Decoder {
    fn decode(&mut self, data: &[u8], offset: u64, out: &mut Events) -> Result<usize> {
        let n = data.len() / 4 * 4;
        if out.width == 0 && out.height == 0 {
            (out.width, out.height) = (self.width, self.height);
        }
        let chunks: Vec<&[u8]> = data[..n].chunks(4 * self.chunk_words).collect();
        let scans: Vec<ChunkScan> = chunks.par_iter().map(|c| ChunkScan::of(c)).collect();
        // Sequential prefix: each chunk's starting state and event count, and the skip statistics.
        let (mut st, mut stats) = (self.st, self.stats);
        let mut starts = Vec::with_capacity(scans.len());
        let mut counts = Vec::with_capacity(scans.len());
        for s in &scans {
            starts.push(st);
            let (b, a) = (s.before, s.after);
            if st.started {
                counts.push((b.cd + a.cd) as usize);
                stats.triggers += b.triggers;
                stats.skipped_words += b.other;
            } else {
                counts.push(a.cd as usize);
                stats.words_before_time_high += b.cd + b.triggers + b.other;
            }
            stats.triggers += a.triggers;
            stats.skipped_words += a.other;
            if let Some(raw0) = s.first_high {
                st.time_high(raw0, self.time_shift);
                st.base += s.wraps * WRAP + (i64::from(s.last_high) - i64::from(raw0)) * 64;
            }
        }
        let total = counts.iter().sum();
        let parts = out.spare_parts(counts);
        let filled: Vec<_> =
            chunks.par_iter().zip(starts).zip(parts).map(|((c, st), part)| self.fill(c, st, part)).collect();
        let first_error = filled.iter().enumerate().find_map(|(c, r)| r.err().map(|e| (c, e)));
        if let Some((c, (i, x, y))) = first_error {
            return Err(Error::format(
                &self.path,
                format!("byte offset {}", offset + 4 * (c * self.chunk_words + i) as u64),
                format!("event ({x}, {y}) outside the {}x{} sensor", self.width, self.height),
            ));
        }
        // SAFETY: every chunk filled its part whole (`fill` asserts it) and the parts are contiguous.
        unsafe { out.assume_filled(total) };
        (self.st, self.stats) = (st, stats);
        Ok(n)
    }

    /// A trailing partial word is dropped and counted in [`DecodeStats::dropped_partial_bytes`].
    fn finish(&mut self, tail: &[u8], offset: u64, out: &mut Events) -> Result<()> {
        let used = self.decode(tail, offset, out)?;
        self.stats.dropped_partial_bytes += (tail.len() - used) as u64;
        Ok(())
    }
}

/// Streaming EVT 2.0 encoder: the payload of a `.raw` file, batch by batch after [`write_raw_header`].
///
/// TIME_HIGH is written whenever bits 33..6 of time change; when the 34-bit counter wraps, TIME_HIGH
/// words at the last base before the wrap and at the wrap are inserted so the decoder sees the fall.
/// Times decode absolutely only within the first 2^34 µs of the first event's period (the format has
/// no higher bits).
#[derive(Debug, Clone)]
pub struct Evt2Encoder {
    path: String,
    xlim: u32,
    ylim: u32,
    /// The last TIME_HIGH base written.
    current: Option<i64>,
    last_t: Option<i64>,
    seen: u64,
}

impl Evt2Encoder {
    /// `path` names the output in errors; coordinates must fit the sensor (`width`/`height`, 0 =
    /// unknown) and the 11-bit address fields.
    pub fn new(path: &str, width: u32, height: u32) -> Self {
        let lim = |n: u32| if n == 0 { MAX_COORD } else { n.min(MAX_COORD) };
        Evt2Encoder {
            path: path.into(),
            xlim: lim(width),
            ylim: lim(height),
            current: None,
            last_t: None,
            seen: 0,
        }
    }

    /// Append the words of the stream's next events to `out`. Unsorted or negative times and
    /// coordinates that do not fit are errors naming the event's index in the stream (nothing of
    /// the batch is written then).
    pub fn encode(&mut self, ev: EventsView<'_>, out: &mut Vec<u8>) -> Result<()> {
        check_encodable(&self.path, "EVT 2.0", ev, self.last_t, self.seen, 0, self.xlim, self.ylim)?;
        out.reserve(ev.len() * 4 + ev.len() / 16 * 4);
        for i in 0..ev.len() {
            let (t, x, y) = (ev.t[i], ev.x[i], ev.y[i]);
            let high = t & !63;
            if self.current != Some(high) {
                if let Some(previous) = self.current {
                    for wrap in (previous / WRAP + 1..=high / WRAP).map(|k| k * WRAP) {
                        push_time_high(out, (wrap - 64).max(previous));
                        push_time_high(out, wrap);
                    }
                }
                push_time_high(out, high);
                self.current = Some(high);
            }
            let kind = if ev.p[i] > 0 { CD_ON } else { CD_OFF };
            let w = (kind << 28) | (((t & 63) as u32) << 22) | (u32::from(x) << 11) | u32::from(y);
            out.extend_from_slice(&w.to_le_bytes());
        }
        self.last_t = ev.t.last().copied().or(self.last_t);
        self.seen += ev.len() as u64;
        Ok(())
    }
}

/// A complete EVT 2.0 `.raw` file (header + payload) for sorted, non-negative-time events.
pub fn encode_evt2(ev: EventsView<'_>) -> Result<Vec<u8>> {
    let mut out = write_raw_header(RawEncoding::Evt2, ev.width, ev.height);
    Evt2Encoder::new("memory", ev.width, ev.height).encode(ev, &mut out)?;
    Ok(out)
}

fn push_time_high(out: &mut Vec<u8>, base: i64) {
    let w = (TIME_HIGH << 28) | ((base >> 6) as u32 & 0x0FFF_FFFF);
    out.extend_from_slice(&w.to_le_bytes());
}

#[cfg(test)]
mod tests {
    use super::super::raw_header::{feed, parse_raw_header};
    use super::*;

    fn cd(on: bool, t_low: u32, x: u32, y: u32) -> u32 {
        (u32::from(on) << 28) | (t_low << 22) | (x << 11) | y
    }
    fn th(v: u32) -> u32 {
        (TIME_HIGH << 28) | v
    }
    fn bytes(words: &[u32]) -> Vec<u8> {
        words.iter().flat_map(|w| w.to_le_bytes()).collect()
    }

    #[test]
    fn hand_built_words_with_wrap_triggers_and_mid_stream_start() {
        let max_high = (1 << 28) - 1;
        let words = [
            cd(true, 5, 1, 1),              // before the first TIME_HIGH: skipped
            (EXT_TRIGGER << 28) | 1,        // also before it
            th(max_high - 1),               // base 2^34 - 128
            cd(true, 63, 639, 479),         //
            (EXT_TRIGGER << 28) | (3 << 8), // trigger
            (0xE << 28) | 7,                // OTHERS
            (0xF << 28) | 7,                // CONTINUED
            0x3000_0000,                    // reserved type 3
            th(max_high),                   // 2^34 - 64
            cd(false, 1, 2, 3),             //
            th(0),                          // wrap: 2^34
            cd(true, 0, 4, 5),              //
            th(1),                          // 2^34 + 64
            cd(false, 2, 6, 7),             //
            th(0),                          // falls by 64 only: not a wrap, time goes back
            cd(true, 3, 8, 9),
        ];
        let mut data = bytes(&words);
        data.extend_from_slice(&[0xAB, 0xCD]); // truncated final word
        let mut dec = Evt2Decoder::new("f.raw", 640, 480, false);
        let ev = feed::whole(&mut dec, &data, 100).unwrap();
        let w = 1i64 << 34;
        assert_eq!(ev.t, vec![w - 128 + 63, w - 64 + 1, w, w + 64 + 2, w + 3]);
        assert_eq!(ev.x, vec![639, 2, 4, 6, 8]);
        assert_eq!(ev.y, vec![479, 3, 5, 7, 9]);
        assert_eq!(ev.p, vec![1, -1, 1, -1, 1]);
        let s = dec.stats();
        assert_eq!(
            (s.words_before_time_high, s.triggers, s.skipped_words, s.dropped_partial_bytes),
            (2, 1, 3, 2)
        );

        let mut dec = Evt2Decoder::new("f.raw", 640, 480, true);
        let shifted = feed::pieces(&mut dec, &data, 100, 7).unwrap();
        assert_eq!(shifted.t, ev.t.iter().map(|t| t - (w - 128)).collect::<Vec<_>>());
    }

    #[test]
    fn second_wrap_compares_unwrapped_bases() {
        // After one wrap, later TIME_HIGHs must not add 2^34 again (the evlib bug).
        let words = [th((1 << 28) - 1), th(0), cd(true, 0, 0, 0), th(5), cd(true, 0, 0, 0), th(5), th(6)];
        let mut dec = Evt2Decoder::new("f.raw", 0, 0, false);
        let mut words = words.to_vec();
        words.push(cd(true, 1, 0, 0));
        let ev = feed::whole(&mut dec, &bytes(&words), 0).unwrap();
        let w = 1i64 << 34;
        assert_eq!(ev.t, vec![w, w + 5 * 64, w + 6 * 64 + 1]);
    }

    #[test]
    fn coordinates_outside_the_sensor_name_the_byte_offset() {
        let data = bytes(&[th(0), cd(true, 0, 10, 0), cd(true, 0, 640, 0)]);
        let mut dec = Evt2Decoder::new("f.raw", 640, 480, false);
        let e = feed::whole(&mut dec, &data, 40).unwrap_err().to_string();
        assert!(e.contains("f.raw") && e.contains("byte offset 48") && e.contains("(640, 0)"), "{e}");
    }

    #[test]
    fn round_trip_across_wraps_whole_and_in_pieces() {
        let mut ev = feed::random_events(5000, 7, (1 << 34) - 20_000, 50, 640, 480);
        ev.extend(&feed::random_events(100, 9, 3 * (1 << 34) + 5, 100_000_000_000, 640, 480));
        let file = encode_evt2(ev.view()).unwrap();
        let header = parse_raw_header(&file, "f.raw").unwrap();
        assert_eq!((header.encoding, header.width, header.height), (RawEncoding::Evt2, 640, 480));
        let payload = &file[header.data_offset..];
        let mut dec = Evt2Decoder::new("f.raw", 640, 480, false);
        let whole = feed::whole(&mut dec, payload, header.data_offset as u64).unwrap();
        assert_eq!(whole, ev);
        for piece in [1, 3, 7, 4096] {
            let mut dec = Evt2Decoder::new("f.raw", 640, 480, false);
            assert_eq!(feed::pieces(&mut dec, payload, 0, piece).unwrap(), ev, "piece {piece}");
        }
    }

    /// Chunked (parallel) decoding equals one chunk (sequential) for any chunk size and thread count:
    /// chunk borders fall before the first TIME_HIGH, between wraps, and next to triggers.
    #[test]
    fn chunked_parallel_decode_equals_sequential() {
        let max_high = (1 << 28) - 1;
        let mut words = vec![cd(true, 5, 1, 1), (EXT_TRIGGER << 28) | 1, (0xE << 28) | 7, th(max_high - 1)];
        for (i, high) in [max_high - 1, max_high, 0, 1, 0, 2, max_high, 3].into_iter().enumerate() {
            words.push(th(high));
            words.extend((0..i as u32).map(|k| cd(k % 2 == 0, k, k, i as u32)));
            words.push((EXT_TRIGGER << 28) | 5);
            words.push((0xF << 28) | 2);
        }
        let mut data = bytes(&words);
        let payload = {
            let file =
                encode_evt2(feed::random_events(3000, 3, (1 << 34) - 9000, 40, 640, 480).view()).unwrap();
            let h = parse_raw_header(&file, "f.raw").unwrap();
            file[h.data_offset..].to_vec()
        };
        data.extend(payload);
        for time_shift in [false, true] {
            let decode = |chunk_words: usize| {
                let mut dec = Evt2Decoder::new("f.raw", 640, 480, time_shift);
                dec.chunk_words = chunk_words;
                let ev = feed::pieces(&mut dec, &data, 0, 4000).unwrap();
                (ev, dec.stats())
            };
            let (want, want_stats) = decode(usize::MAX / 4);
            assert_eq!(want_stats.words_before_time_high, 3);
            for chunk_words in [1, 2, 3, 7, 64] {
                for threads in [1, 3] {
                    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
                    let (got, stats) = pool.install(|| decode(chunk_words));
                    assert_eq!(got, want, "chunk {chunk_words}, {threads} threads");
                    assert_eq!(format!("{stats:?}"), format!("{want_stats:?}"));
                }
            }
        }
        let bad = bytes(&[th(0), cd(true, 0, 10, 0), th(1), cd(true, 0, 640, 0)]);
        let mut dec = Evt2Decoder::new("f.raw", 640, 480, false);
        dec.chunk_words = 1;
        let e = feed::whole(&mut dec, &bad, 40).unwrap_err().to_string();
        assert!(e.contains("byte offset 52") && e.contains("(640, 0)"), "{e}");
    }
}

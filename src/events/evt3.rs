//! Prophesee EVT 3.0 decoder and encoder (16-bit words, vectorised events; EVENT_FORMATS.md §3).
//!
//! State words (row, vector base, time) set registers that later event words use. Decoded word by
//! word, so a vector group may follow another without a new VECT_BASE_X and a truncated group never
//! swallows the next word. TIME_LOW overwrites the low time bits: it is not monotonic (sensor
//! glitches right after a TIME_HIGH re-send), so a decrease never implies an overflow; only TIME_HIGH
//! detects the 24-bit loop.

use super::raw_header::{write_raw_header, DecodeStats, RawEncoding, MAX_COORD};
use super::{Decoder, Events, EventsView};
use crate::error::{Error, Result};

const ADDR_Y: u16 = 0x0;
/// Row of a non-CD event (OpenEB HAL): CD output stops until the next ADDR_Y.
const ADDR_Y_OTHER: u16 = 0x1;
const ADDR_X: u16 = 0x2;
const VECT_BASE_X: u16 = 0x3;
const VECT_12: u16 = 0x4;
const VECT_8: u16 = 0x5;
const TIME_LOW: u16 = 0x6;
const TIME_HIGH: u16 = 0x8;
const EXT_TRIGGER: u16 = 0xA;
/// Period of the 24-bit time counter in µs.
const LOOP: i64 = 1 << 24;
/// A TIME_HIGH that falls by at least this much is a loop of the counter (OpenEB standalone's rule).
const LOOP_THRESHOLD: i64 = 0xFF_F000 - 40960;

/// Decoder registers, copied into a local for the hot loop.
#[derive(Debug, Clone, Copy, Default)]
struct State {
    started: bool,
    /// Unwrapped TIME_HIGH base, µs.
    base: i64,
    /// Current time: base + TIME_LOW, µs.
    t: i64,
    shift: i64,
    y: u32,
    y_valid: bool,
    base_x: u32,
    pol: i8,
    base_x_valid: bool,
}

/// Streaming EVT 3.0 decoder; fed the payload after the RAW header.
#[derive(Debug, Clone)]
pub struct Evt3Decoder {
    path: String,
    width: u32,
    height: u32,
    time_shift: bool,
    st: State,
    stats: DecodeStats,
}

impl Evt3Decoder {
    /// `width`/`height` (0 = unknown) bound the coordinates; `time_shift` subtracts Metavision's
    /// shift, `(first TIME_HIGH − 1)·4096` µs (evgs keeps absolute times: `false`).
    pub fn new(path: &str, width: u32, height: u32, time_shift: bool) -> Self {
        Evt3Decoder {
            path: path.to_string(),
            width,
            height,
            time_shift,
            st: State::default(),
            stats: DecodeStats::default(),
        }
    }

    /// What was skipped or dropped so far.
    pub fn stats(&self) -> DecodeStats {
        self.stats
    }

    fn outside(&self, offset: u64, x: u32, y: u32) -> Error {
        Error::format(
            &self.path,
            format!("byte offset {offset}"),
            format!("event ({x}, {y}) outside the {}x{} sensor", self.width, self.height),
        )
    }

    /// Decode whole words of `data` with the registers in `st`; on error returns the bad word's offset
    /// and coordinates.
    fn words(
        &mut self,
        st: &mut State,
        data: &[u8],
        out: &mut Events,
    ) -> std::result::Result<(), (usize, u32, u32)> {
        let xlim = if self.width == 0 { MAX_COORD } else { self.width };
        let ylim = if self.height == 0 { MAX_COORD } else { self.height };
        let stats = &mut self.stats;
        for (i, word) in data.chunks_exact(2).enumerate() {
            let w = u16::from_le_bytes([word[0], word[1]]);
            let v = u32::from(w & 0x7FF);
            let kind = w >> 12;
            if !st.started {
                if kind == TIME_HIGH {
                    st.started = true;
                    st.base = i64::from(w & 0xFFF) << 12;
                    st.t = st.base;
                    st.shift = if self.time_shift { (i64::from(w & 0xFFF) - 1) << 12 } else { 0 };
                } else {
                    stats.words_before_time_high += 1;
                }
                continue;
            }
            match kind {
                ADDR_X => {
                    if !st.y_valid {
                        stats.dropped_events += 1;
                    } else if v >= xlim || st.y >= ylim {
                        return Err((2 * i, v, st.y));
                    } else {
                        out.push(st.t - st.shift, v as u16, st.y as u16, if w & 0x800 != 0 { 1 } else { -1 });
                    }
                }
                VECT_12 | VECT_8 => {
                    let (mut mask, width) =
                        if kind == VECT_12 { (u32::from(w & 0xFFF), 12) } else { (u32::from(w & 0xFF), 8) };
                    if !(st.y_valid && st.base_x_valid) {
                        stats.dropped_events += u64::from(mask.count_ones());
                    } else if mask != 0 {
                        let last = st.base_x + 31 - mask.leading_zeros();
                        if last >= xlim || st.y >= ylim {
                            return Err((2 * i, last, st.y));
                        }
                        let t = st.t - st.shift;
                        while mask != 0 {
                            out.push(t, (st.base_x + mask.trailing_zeros()) as u16, st.y as u16, st.pol);
                            mask &= mask - 1;
                        }
                    }
                    st.base_x = st.base_x.saturating_add(width);
                }
                TIME_LOW => st.t = st.base + i64::from(w & 0xFFF),
                ADDR_Y => {
                    st.y = v;
                    st.y_valid = true;
                }
                VECT_BASE_X => {
                    st.base_x = v;
                    st.pol = if w & 0x800 != 0 { 1 } else { -1 };
                    st.base_x_valid = true;
                }
                TIME_HIGH => {
                    let mut base = (i64::from(w & 0xFFF) << 12) + (st.base - st.base.rem_euclid(LOOP));
                    if st.base - base >= LOOP_THRESHOLD {
                        base += LOOP;
                    }
                    st.base = base;
                    st.t = base;
                }
                ADDR_Y_OTHER => {
                    st.y_valid = false;
                    stats.skipped_words += 1;
                }
                EXT_TRIGGER => stats.triggers += 1,
                // CONTINUED_4, OTHERS, CONTINUED_12, IMU and reserved types (incl. 0x9999 padding).
                _ => stats.skipped_words += 1,
            }
        }
        Ok(())
    }
}

impl Decoder for Evt3Decoder {
    fn decode(&mut self, data: &[u8], offset: u64, out: &mut Events) -> Result<usize> {
        let n = data.len() / 2 * 2;
        // A hint, not a bound: a vector word holds up to 12 events.
        out.t.reserve(n / 2);
        out.x.reserve(n / 2);
        out.y.reserve(n / 2);
        out.p.reserve(n / 2);
        if out.width == 0 && out.height == 0 {
            (out.width, out.height) = (self.width, self.height);
        }
        let mut st = self.st;
        let result = self.words(&mut st, &data[..n], out);
        self.st = st;
        match result {
            Ok(()) => Ok(n),
            Err((at, x, y)) => Err(self.outside(offset + at as u64, x, y)),
        }
    }

    /// A trailing partial word is dropped and counted in [`DecodeStats::dropped_partial_bytes`].
    fn finish(&mut self, tail: &[u8], offset: u64, out: &mut Events) -> Result<()> {
        let used = self.decode(tail, offset, out)?;
        self.stats.dropped_partial_bytes += (tail.len() - used) as u64;
        Ok(())
    }
}

/// Encode sorted, non-negative-time events as a complete EVT 3.0 `.raw` file (header + payload).
///
/// Consecutive events with the same time, row and polarity and increasing x (gaps ≤ 12) become one
/// VECT_BASE_X followed by VECT_12, VECT_12, VECT_8 groups (repeated without a new base for long runs);
/// single events become ADDR_X. When the 24-bit counter loops, TIME_HIGH words at the last base before
/// the loop and at the loop are inserted so the decoder sees the fall. Times decode absolutely only
/// within the first 2^24 µs period of the first event (the format has no higher bits). Panics on
/// unsorted or negative times or coordinates above 2047.
pub fn encode_evt3(ev: EventsView<'_>) -> Vec<u8> {
    let mut out = write_raw_header(RawEncoding::Evt3, ev.width, ev.height);
    out.reserve(ev.len() * 2 + 64);
    let word = |out: &mut Vec<u8>, kind: u16, v: u32| {
        out.extend_from_slice(&((kind << 12) | v as u16).to_le_bytes())
    };
    let (mut high, mut time, mut row): (Option<i64>, Option<i64>, Option<u16>) = (None, None, None);
    let n = ev.len();
    let mut i = 0;
    while i < n {
        let (t, x, y, on) = (ev.t[i], ev.x[i], ev.y[i], ev.p[i] > 0);
        assert!(
            t >= 0 && time.is_none_or(|c| c <= t),
            "encode_evt3: event {i}: times must be sorted and >= 0"
        );
        assert!(x < 2048 && y < 2048, "encode_evt3: event {i}: ({x}, {y}) does not fit 11 bits");
        let h = t & !0xFFF;
        if high != Some(h) {
            if let Some(previous) = high {
                for lp in (previous / LOOP + 1..=h / LOOP).map(|k| k * LOOP) {
                    word(&mut out, TIME_HIGH, (((lp - 4096).max(previous) >> 12) & 0xFFF) as u32);
                    word(&mut out, TIME_HIGH, 0);
                }
            }
            word(&mut out, TIME_HIGH, ((h >> 12) & 0xFFF) as u32);
            (high, time) = (Some(h), None);
        }
        if time != Some(t) {
            word(&mut out, TIME_LOW, (t & 0xFFF) as u32);
            time = Some(t);
        }
        if row != Some(y) {
            word(&mut out, ADDR_Y, u32::from(y));
            row = Some(y);
        }
        let pol = u32::from(on) << 11;
        let mut j = i + 1;
        while j < n
            && ev.t[j] == t
            && ev.y[j] == y
            && (ev.p[j] > 0) == on
            && ev.x[j] > ev.x[j - 1]
            && ev.x[j] - ev.x[j - 1] <= 12
        {
            j += 1;
        }
        if j == i + 1 {
            word(&mut out, ADDR_X, pol | u32::from(x));
        } else {
            word(&mut out, VECT_BASE_X, pol | u32::from(x));
            let mut base = u32::from(x);
            for (k, group) in [12u32, 12, 8].into_iter().cycle().enumerate() {
                let mut mask = 0;
                while i < j && u32::from(ev.x[i]) < base + group {
                    mask |= 1 << (u32::from(ev.x[i]) - base);
                    i += 1;
                }
                word(&mut out, if k % 3 == 2 { VECT_8 } else { VECT_12 }, mask);
                base += group;
                if i == j {
                    break;
                }
            }
        }
        i = j;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::raw_header::{feed, parse_raw_header};
    use super::*;

    fn w(kind: u16, v: u16) -> u16 {
        (kind << 12) | v
    }
    fn bytes(words: &[u16]) -> Vec<u8> {
        words.iter().flat_map(|w| w.to_le_bytes()).collect()
    }
    fn triples(ev: &Events) -> Vec<(i64, u16, u16, i8)> {
        (0..ev.len()).map(|i| (ev.t[i], ev.x[i], ev.y[i], ev.p[i])).collect()
    }

    #[test]
    fn hand_built_vectors_time_loop_glitch_padding_and_mid_stream_start() {
        let words = [
            w(ADDR_Y, 3),                 // mid-stream start: everything before the first TIME_HIGH is skipped
            w(ADDR_X, 0x805),             //
            w(TIME_LOW, 7),               //
            w(TIME_HIGH, 0xFFE),          // base 0xFFE000
            w(ADDR_X, 9),                 // row unknown yet: dropped
            w(TIME_LOW, 0x10),            //
            w(ADDR_Y, 0x805),             // y = 5, system type bit 11 ignored
            w(ADDR_X, 0x800 | 100),       // (100, 5, +1) at 0xFFE010
            0x9999,                       // padding (reserved type 9)
            w(VECT_BASE_X, 200),          // base 200, negative polarity
            w(VECT_12, 0b1000_0000_0001), // 200, 211
            w(VECT_12, 0b1),              // 212
            w(VECT_8, 0b1000_0000),       // 224 + 7 = 231
            w(VECT_12, 0b10),             // group after group, no new base: 232 + 1 = 233
            w(EXT_TRIGGER, 0x301),        //
            w(0xE, 1),                    // OTHERS
            w(0xF, 2),                    // CONTINUED_12
            w(0x7, 3),                    // CONTINUED_4
            w(TIME_HIGH, 0xFFF),          // 0xFFF000
            w(TIME_LOW, 0xFFF),           //
            w(ADDR_X, 1),                 // (1, 5, −1) at 0xFFFFFF
            w(TIME_HIGH, 0x000),          // the 24-bit loop: 0x1000000
            w(TIME_LOW, 0x002),           //
            w(ADDR_X, 2),                 // (2, 5, −1) at 0x1000002
            w(TIME_HIGH, 0x000),          // re-sent TIME_HIGH ...
            w(TIME_LOW, 0x00C),           // ... a glitch 10 µs ahead with no events ...
            w(TIME_LOW, 0x003),           // ... then back: overwrite, no overflow inferred
            w(ADDR_X, 3),                 // (3, 5, −1) at 0x1000003
            w(ADDR_Y_OTHER, 7),           // non-CD row: CD output stops ...
            w(ADDR_X, 4),                 // ... so this one is dropped
            w(ADDR_Y, 6),
            w(ADDR_X, 0x800 | 4), // (4, 6, +1)
        ];
        let mut data = bytes(&words);
        data.push(0x42); // truncated final word
        let base = 0xFFE000;
        let expected = vec![
            (base + 0x10, 100, 5, 1),
            (base + 0x10, 200, 5, -1),
            (base + 0x10, 211, 5, -1),
            (base + 0x10, 212, 5, -1),
            (base + 0x10, 231, 5, -1),
            (base + 0x10, 233, 5, -1),
            (0xFFFFFF, 1, 5, -1),
            (0x1000002, 2, 5, -1),
            (0x1000003, 3, 5, -1),
            (0x1000003, 4, 6, 1),
        ];
        let mut dec = Evt3Decoder::new("f.raw", 640, 480, false);
        let ev = feed::whole(&mut dec, &data, 0).unwrap();
        assert_eq!(triples(&ev), expected);
        let s = dec.stats();
        assert_eq!(s.words_before_time_high, 3);
        assert_eq!(s.dropped_events, 2);
        assert_eq!(s.triggers, 1);
        assert_eq!(s.skipped_words, 5); // 0x9999, OTHERS, CONTINUED_12, CONTINUED_4, ADDR_Y_OTHER
        assert_eq!(s.dropped_partial_bytes, 1);

        // Piecewise feeding gives the same; Metavision's shift is (first TIME_HIGH − 1)·4096.
        let mut dec = Evt3Decoder::new("f.raw", 640, 480, true);
        let shifted = feed::pieces(&mut dec, &data, 0, 7).unwrap();
        let shift = (0xFFE - 1) * 4096;
        let want: Vec<_> = expected.iter().map(|&(t, x, y, p)| (t - shift, x, y, p)).collect();
        assert_eq!(triples(&shifted), want);
    }

    #[test]
    fn vector_outside_the_sensor_names_the_byte_offset() {
        let data =
            bytes(&[w(TIME_HIGH, 0), w(ADDR_Y, 1), w(VECT_BASE_X, 630), w(VECT_12, 1), w(VECT_12, 1 << 11)]);
        let mut dec = Evt3Decoder::new("g.raw", 640, 480, false);
        let e = feed::whole(&mut dec, &data, 1000).unwrap_err().to_string();
        assert!(e.contains("g.raw") && e.contains("byte offset 1008") && e.contains("(653, 1)"), "{e}");
    }

    #[test]
    fn unknown_geometry_still_bounds_vectors_to_11_bits() {
        let data = bytes(&[
            w(TIME_HIGH, 0),
            w(ADDR_Y, 1),
            w(VECT_BASE_X, 2040),
            w(VECT_12, 1 << 7),
            w(VECT_12, 1 << 2),
        ]);
        let mut dec = Evt3Decoder::new("g.raw", 0, 0, false);
        let e = feed::whole(&mut dec, &data, 0).unwrap_err().to_string();
        assert!(e.contains("byte offset 8") && e.contains("(2054, 1)"), "{e}");
    }

    /// Random row bursts (what vector groups are for), with time gaps that loop the 24-bit counter.
    fn bursts(n: usize, seed: u64) -> Events {
        let mut s = seed;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        let mut ev = Events::with_capacity(n, 1280, 720);
        let mut t = (1 << 24) - 30_000;
        while ev.len() < n {
            t += (next() % 8) as i64;
            // Bursts along a row (vectorisable), sometimes a single event, sometimes a big time gap.
            let r = next();
            let (y, p) = ((r % 720) as u16, if r >> 20 & 1 == 1 { 1 } else { -1 });
            let mut x = ((r >> 32) % 1200) as u16;
            for _ in 0..(r >> 50) % 40 {
                ev.push(t, x, y, p);
                x += 1 + (next() % 14) as u16;
                if x >= 1280 {
                    break;
                }
            }
            if r % 97 == 0 {
                t += 40_000_000;
            }
        }
        ev
    }

    #[test]
    fn encoder_uses_vector_groups_for_runs() {
        let mut ev = Events::with_capacity(3, 64, 8);
        for x in [3, 5, 17, 26, 35, 38, 47, 60] {
            ev.push(4096 * 3 + 1, x, 2, 1);
        }
        let file = encode_evt3(ev.view());
        let h = parse_raw_header(&file, "f.raw").unwrap();
        let payload: Vec<u16> =
            file[h.data_offset..].chunks(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect();
        // Offsets from base 3: 0 2 | 14 23 | – | 32 35 | 44 (a second group without a new base); 60 is
        // 13 px after 47, so it ends the run and becomes a single ADDR_X.
        let mut want = vec![w(TIME_HIGH, 3), w(TIME_LOW, 1), w(ADDR_Y, 2), w(VECT_BASE_X, 0x800 | 3)];
        want.extend([w(VECT_12, 0b101), w(VECT_12, 1 << 2 | 1 << 11), w(VECT_8, 0)]);
        want.extend([w(VECT_12, 0b1001), w(VECT_12, 1), w(ADDR_X, 0x800 | 60)]);
        assert_eq!(payload, want);
    }

    #[test]
    fn round_trip_across_loops_whole_and_in_pieces() {
        let ev = bursts(20_000, 11);
        let file = encode_evt3(ev.view());
        let h = parse_raw_header(&file, "f.raw").unwrap();
        assert_eq!((h.encoding, h.width, h.height), (RawEncoding::Evt3, 1280, 720));
        let payload = &file[h.data_offset..];
        assert!(payload.len() < ev.len() * 2, "vector groups should make it smaller than one word per event");
        let mut dec = Evt3Decoder::new("f.raw", 1280, 720, false);
        assert_eq!(feed::whole(&mut dec, payload, 0).unwrap(), ev);
        for piece in [1, 7, 1000] {
            let mut dec = Evt3Decoder::new("f.raw", 1280, 720, false);
            assert_eq!(feed::pieces(&mut dec, payload, 0, piece).unwrap(), ev, "piece {piece}");
        }
    }
}

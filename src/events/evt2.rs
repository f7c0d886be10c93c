//! Prophesee EVT 2.0 decoder and encoder (32-bit words; see EVENT_FORMATS.md §2).
//!
//! A CD word carries the low 6 bits of time; EVT_TIME_HIGH words carry bits 33..6. The 34-bit
//! counter wraps every 2^34 µs, which is undone by comparing each new unwrapped base with the
//! previous unwrapped base (never the raw value with the unwrapped one).

use super::raw_header::{write_raw_header, DecodeStats, RawEncoding};
use super::{Decoder, Events, EventsView};
use crate::error::{Error, Result};

const CD_OFF: u32 = 0x0;
const CD_ON: u32 = 0x1;
const TIME_HIGH: u32 = 0x8;
const EXT_TRIGGER: u32 = 0xA;
/// Period of the 34-bit time counter in µs.
const WRAP: i64 = 1 << 34;
/// A TIME_HIGH that falls by at least `WRAP - 64 - WRAP_TOLERANCE` is a wrap (OpenEB HAL's tolerance).
const WRAP_TOLERANCE: i64 = 10_000;

/// Streaming EVT 2.0 decoder; fed the payload after the RAW header.
#[derive(Debug, Clone)]
pub struct Evt2Decoder {
    path: String,
    width: u32,
    height: u32,
    time_shift: bool,
    /// Whether a TIME_HIGH has been seen; words before it have unknown time and are skipped.
    started: bool,
    /// Unwrapped time base (TIME_HIGH << 6 plus the wraps so far), µs.
    base: i64,
    /// Subtracted from every timestamp: the first base when `time_shift`, else 0.
    shift: i64,
    stats: DecodeStats,
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
            started: false,
            base: 0,
            shift: 0,
            stats: DecodeStats::default(),
        }
    }

    /// What was skipped or dropped so far.
    pub fn stats(&self) -> DecodeStats {
        self.stats
    }

    /// Every word except a CD event after the first TIME_HIGH (the rare path).
    #[cold]
    fn other_word(&mut self, w: u32) {
        let kind = w >> 28;
        if kind == TIME_HIGH {
            let mut base = (i64::from(w & 0x0FFF_FFFF) << 6) + (self.base - self.base.rem_euclid(WRAP));
            if !self.started {
                self.started = true;
                self.shift = if self.time_shift { base } else { 0 };
            } else if self.base - base >= WRAP - 64 - WRAP_TOLERANCE {
                base += WRAP;
            }
            self.base = base;
        } else if !self.started {
            self.stats.words_before_time_high += 1;
        } else if kind == EXT_TRIGGER {
            self.stats.triggers += 1;
        } else {
            self.stats.skipped_words += 1;
        }
    }
}

impl Decoder for Evt2Decoder {
    fn decode(&mut self, data: &[u8], offset: u64, out: &mut Events) -> Result<usize> {
        let n = data.len() / 4 * 4;
        reserve(out, n / 4);
        if out.width == 0 && out.height == 0 {
            (out.width, out.height) = (self.width, self.height);
        }
        let xlim = if self.width == 0 { u32::MAX } else { self.width };
        let ylim = if self.height == 0 { u32::MAX } else { self.height };
        let mut t0 = self.base - self.shift;
        for (i, word) in data[..n].chunks_exact(4).enumerate() {
            let w = u32::from_le_bytes(word.try_into().unwrap());
            let kind = w >> 28;
            if kind <= CD_ON && self.started {
                let (x, y) = ((w >> 11) & 0x7FF, w & 0x7FF);
                if x >= xlim || y >= ylim {
                    return Err(Error::format(
                        &self.path,
                        format!("byte offset {}", offset + 4 * i as u64),
                        format!("event ({x}, {y}) outside the {}x{} sensor", self.width, self.height),
                    ));
                }
                out.push(t0 + i64::from((w >> 22) & 0x3F), x as u16, y as u16, kind as i8 * 2 - 1);
            } else {
                self.other_word(w);
                t0 = self.base - self.shift;
            }
        }
        Ok(n)
    }

    /// A trailing partial word is dropped and counted in [`DecodeStats::dropped_partial_bytes`].
    fn finish(&mut self, tail: &[u8], offset: u64, out: &mut Events) -> Result<()> {
        let used = self.decode(tail, offset, out)?;
        self.stats.dropped_partial_bytes += (tail.len() - used) as u64;
        Ok(())
    }
}

pub(crate) fn reserve(out: &mut Events, n: usize) {
    out.t.reserve(n);
    out.x.reserve(n);
    out.y.reserve(n);
    out.p.reserve(n);
}

/// Encode sorted, non-negative-time events as a complete EVT 2.0 `.raw` file (header + payload).
///
/// TIME_HIGH is written whenever bits 33..6 of time change; when the 34-bit counter wraps, TIME_HIGH
/// words at the last base before the wrap and at the wrap are inserted so the decoder sees the fall.
/// Times decode absolutely only within the first 2^34 µs of the first event's period (the format has
/// no higher bits). Panics on unsorted or negative times or coordinates above 2047.
pub fn encode_evt2(ev: EventsView<'_>) -> Vec<u8> {
    let mut out = write_raw_header(RawEncoding::Evt2, ev.width, ev.height);
    out.reserve(ev.len() * 4 + ev.len() / 16 * 4);
    let mut current: Option<i64> = None;
    for i in 0..ev.len() {
        let (t, x, y) = (ev.t[i], ev.x[i], ev.y[i]);
        assert!(
            t >= 0 && current.is_none_or(|c| c <= t),
            "encode_evt2: event {i}: times must be sorted and >= 0"
        );
        assert!(x < 2048 && y < 2048, "encode_evt2: event {i}: ({x}, {y}) does not fit 11 bits");
        let high = t & !63;
        if current != Some(high) {
            if let Some(previous) = current {
                for wrap in (previous / WRAP + 1..=high / WRAP).map(|k| k * WRAP) {
                    push_time_high(&mut out, (wrap - 64).max(previous));
                    push_time_high(&mut out, wrap);
                }
            }
            push_time_high(&mut out, high);
            current = Some(high);
        }
        let kind = if ev.p[i] > 0 { CD_ON } else { CD_OFF };
        let w = (kind << 28) | (((t & 63) as u32) << 22) | (u32::from(x) << 11) | u32::from(y);
        out.extend_from_slice(&w.to_le_bytes());
    }
    out
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
        let file = encode_evt2(ev.view());
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
}

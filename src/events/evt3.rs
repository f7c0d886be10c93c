//! Prophesee EVT 3.0 decoder and encoder (16-bit words, vectorised events; EVENT_FORMATS.md §3).
//!
//! State words (row, vector base, time) set registers that later event words use. TIME_LOW
//! overwrites the low time bits: it is not monotonic (sensor glitches right after a TIME_HIGH
//! re-send), so a decrease never implies an overflow; only TIME_HIGH detects the 24-bit loop.
//!
//! Decoding is parallel over chunks of words. A chunk's *sync point* is the word after its first row
//! word (and after its first VECT_BASE_X if a vector word comes before it): from there on, which
//! words emit events no longer depends on the state before the chunk. A parallel first pass counts
//! each chunk's events after its sync point and summarises how the chunk changes the registers; a
//! sequential pass decodes the (short) parts before the sync points with the reference word-by-word
//! decoder, which gives every chunk its exact state and output position; a parallel second pass
//! writes the rest with a branch-light loop straight into place. The result equals the sequential
//! decode bit for bit (tested).

use rayon::prelude::*;

use super::raw_header::{check_encodable, write_raw_header, DecodeStats, RawEncoding, MAX_COORD};
use super::{ColumnsMut, Decoder, Events, EventsView};
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
/// Word types counted as skipped: ADDR_Y_OTHER, CONTINUED_4, reserved, OTHERS, CONTINUED_12, IMU.
const SKIPPED_KINDS: u16 = !((1 << ADDR_Y)
    | (1 << ADDR_X)
    | (1 << VECT_BASE_X)
    | (1 << VECT_12)
    | (1 << VECT_8)
    | (1 << TIME_LOW)
    | (1 << TIME_HIGH)
    | (1 << EXT_TRIGGER));
/// Word types the branch-free part of [`Evt3Decoder::fill`] does not handle.
const STATEFUL_KINDS: u16 = (1 << VECT_BASE_X) | (1 << VECT_12) | (1 << VECT_8) | (1 << TIME_HIGH);
/// Period of the 24-bit time counter in µs.
const LOOP: i64 = 1 << 24;
/// A TIME_HIGH that falls by at least this much is a loop of the counter (OpenEB standalone's rule).
const LOOP_THRESHOLD: i64 = 0xFF_F000 - 40960;
/// Words per parallel chunk: big enough to amortise a chunk's setup, small enough to balance threads.
const CHUNK_WORDS: usize = 1 << 16;

/// Decoder registers.
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

impl State {
    /// Apply a TIME_HIGH word's 12-bit value (the stream has started).
    #[inline]
    fn time_high(&mut self, raw: u32) {
        let mut base = (i64::from(raw) << 12) + (self.base - self.base.rem_euclid(LOOP));
        if is_loop(self.base.rem_euclid(LOOP) >> 12, i64::from(raw)) {
            base += LOOP;
        }
        self.base = base;
        self.t = base;
    }
}

/// Whether TIME_HIGH going from `previous` to `raw` (12-bit values) is a loop of the counter: it
/// depends on the raw values only, so a chunk's loops are counted without the state before it.
#[inline]
fn is_loop(previous: i64, raw: i64) -> bool {
    (previous - raw) << 12 >= LOOP_THRESHOLD
}

#[inline]
fn word(data: &[u8], i: usize) -> u16 {
    u16::from_le_bytes([data[2 * i], data[2 * i + 1]])
}

/// Event mask and group width of a vector word.
#[inline]
fn vector(w: u16) -> (u32, u32) {
    if w >> 12 == VECT_12 {
        (u32::from(w & 0xFFF), 12)
    } else {
        (u32::from(w & 0xFF), 8)
    }
}

/// What the first pass learns about a chunk: its sync point, and from there on its event count,
/// skip statistics and register changes (given that the stream has started).
#[derive(Debug, Clone, Copy, Default)]
struct ChunkScan {
    /// Word index of the sync point; the chunk's length when it has none.
    sync: usize,
    events: usize,
    stats: DecodeStats,
    /// Last row word: (row, whether CD).
    row: Option<(u32, bool)>,
    /// Last VECT_BASE_X: (base, polarity).
    vect_base: Option<(u32, i8)>,
    /// Vector widths after the last VECT_BASE_X (or after the sync point when there is none).
    base_advance: u32,
    /// Raw values of the first and last TIME_HIGH, and the loops between them.
    first_high: Option<u32>,
    last_high: u32,
    loops: i64,
    /// Last TIME_LOW after the last TIME_HIGH.
    low: Option<u32>,
}

impl ChunkScan {
    fn of(data: &[u8]) -> Self {
        let n = data.len() / 2;
        let mut s = ChunkScan { sync: n, ..Default::default() };
        let (mut row, mut vector_base, mut vector_first) = (None, None, false);
        for i in 0..n {
            let kind = word(data, i) >> 12;
            match kind {
                ADDR_Y | ADDR_Y_OTHER if row.is_none() => row = Some(i),
                VECT_BASE_X if vector_base.is_none() => vector_base = Some(i),
                VECT_12 | VECT_8 if vector_base.is_none() => vector_first = true,
                _ => {}
            }
            if let Some(r) = row {
                if !vector_first || vector_base.is_some() {
                    s.sync = r.max(vector_base.filter(|_| vector_first).unwrap_or(0)) + 1;
                    break;
                }
            }
        }
        let Some(r) = row.filter(|_| s.sync < n) else { return s };
        // Registers between the chunk start and the sync point come from the sequential pass; only
        // the row's validity matters for counting.
        let mut y_valid = word(data, r) >> 12 == ADDR_Y;
        for i in r + 1..s.sync {
            let kind = word(data, i) >> 12;
            y_valid = (kind == ADDR_Y) | (y_valid & (kind != ADDR_Y_OTHER));
        }
        // One branch-free counting pass (it vectorises); the last row, VECT_BASE_X, TIME_LOW and
        // TIME_HIGH words are then found from the end. Rare cases are redone exactly below.
        let rest = &data[2 * s.sync..];
        let kinds = || rest.chunks_exact(2).map(|w| u16::from_le_bytes([w[0], w[1]]));
        let mut n = [0u32; 7]; // emitted, other rows, highs, skipped, triggers, vectors, bases
        for w in kinds() {
            let kind = w >> 12;
            let is_vector = (kind == VECT_12) | (kind == VECT_8);
            let mask = w & if kind == VECT_12 { 0xFFF } else { 0xFF };
            n[0] += u32::from(kind == ADDR_X) + if is_vector { mask.count_ones() } else { 0 };
            n[1] += u32::from(kind == ADDR_Y_OTHER);
            n[2] += u32::from(kind == TIME_HIGH);
            n[3] += u32::from((SKIPPED_KINDS >> kind) & 1);
            n[4] += u32::from(kind == EXT_TRIGGER);
            n[5] += u32::from(is_vector);
            n[6] += u32::from(kind == VECT_BASE_X);
        }
        let [emitted, other_rows, highs, skipped, triggers, vectors, bases] = n;
        let last = |pred: fn(u16) -> bool| kinds().rposition(|w| pred(w >> 12));
        let last_row = last(|k| k <= ADDR_Y_OTHER);
        let last_base = if bases > 0 { last(|k| k == VECT_BASE_X) } else { None };
        let last_low = last(|k| k == TIME_LOW);
        let last_high = if highs > 0 { last(|k| k == TIME_HIGH) } else { None };
        let advance = if vectors > 0 {
            let from = last_base.map_or(0, |b| b + 1);
            kinds().skip(from).filter(|w| matches!(w >> 12, VECT_12 | VECT_8)).map(|w| vector(w).1).sum()
        } else {
            0
        };
        let at = |pos: usize| word(rest, pos);
        let (mut events, mut dropped) = (u64::from(emitted), 0);
        if other_rows > 0 || !y_valid {
            // Rows that stop CD output: follow the row's validity word by word.
            (events, dropped) = (0, 0);
            for w in kinds() {
                let kind = w >> 12;
                let count = if matches!(kind, VECT_12 | VECT_8) {
                    u64::from(vector(w).0.count_ones())
                } else {
                    u64::from(kind == ADDR_X)
                };
                events += if y_valid { count } else { 0 };
                dropped += if y_valid { 0 } else { count };
                y_valid = (kind == ADDR_Y) | (y_valid & (kind != ADDR_Y_OTHER));
            }
        }
        if highs > 0 {
            for w in kinds() {
                if w >> 12 == TIME_HIGH {
                    let raw = u32::from(w & 0xFFF);
                    match s.first_high {
                        None => s.first_high = Some(raw),
                        Some(_) => s.loops += i64::from(is_loop(i64::from(s.last_high), i64::from(raw))),
                    }
                    s.last_high = raw;
                }
            }
        }
        s.events = events as usize;
        s.stats = DecodeStats {
            triggers: u64::from(triggers),
            skipped_words: u64::from(skipped),
            dropped_events: dropped,
            ..Default::default()
        };
        s.row = last_row.map(|r| (u32::from(at(r) & 0x7FF), at(r) >> 12 == ADDR_Y));
        s.vect_base = last_base.map(|b| (u32::from(at(b) & 0x7FF), if at(b) & 0x800 != 0 { 1 } else { -1 }));
        s.base_advance = advance;
        s.low = last_low.filter(|&l| last_high.is_none_or(|h| l > h)).map(|l| u32::from(at(l) & 0xFFF));
        s
    }

    /// The registers after the chunk, given those at its sync point.
    fn apply(&self, mut st: State) -> State {
        if let Some((y, valid)) = self.row {
            (st.y, st.y_valid) = (y, valid);
        }
        if let Some((x, pol)) = self.vect_base {
            (st.base_x, st.pol, st.base_x_valid) = (x, pol, true);
        }
        st.base_x = st.base_x.saturating_add(self.base_advance);
        if let Some(raw0) = self.first_high {
            st.time_high(raw0);
            st.base += self.loops * LOOP + ((i64::from(self.last_high) - i64::from(raw0)) << 12);
            st.t = st.base;
        }
        if let Some(low) = self.low {
            st.t = st.base + i64::from(low);
        }
        st
    }
}

fn add_stats(a: &mut DecodeStats, b: &DecodeStats) {
    a.triggers += b.triggers;
    a.words_before_time_high += b.words_before_time_high;
    a.skipped_words += b.skipped_words;
    a.dropped_events += b.dropped_events;
    a.dropped_partial_bytes += b.dropped_partial_bytes;
    a.skipped_packets += b.skipped_packets;
}

/// How one chunk is decoded: its events before the sync point (decoded sequentially into a shared
/// buffer) and the state and event count from the sync point on.
struct Plan {
    head: std::ops::Range<usize>,
    sync: usize,
    state: State,
    events: usize,
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
    chunk_words: usize,
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
            chunk_words: CHUNK_WORDS,
        }
    }

    /// What was skipped or dropped so far.
    pub fn stats(&self) -> DecodeStats {
        self.stats
    }

    fn limits(&self) -> (u32, u32) {
        (
            if self.width == 0 { MAX_COORD } else { self.width },
            if self.height == 0 { MAX_COORD } else { self.height },
        )
    }

    /// The reference decoder: whole words of `data`, one at a time, from the registers in `st`. On a
    /// coordinate outside the sensor returns the bad word's index and the coordinates.
    fn words(
        &self,
        st: &mut State,
        stats: &mut DecodeStats,
        data: &[u8],
        out: &mut Events,
    ) -> std::result::Result<(), (usize, u32, u32)> {
        let (xlim, ylim) = self.limits();
        for i in 0..data.len() / 2 {
            let w = word(data, i);
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
                        return Err((i, v, st.y));
                    } else {
                        out.push(st.t - st.shift, v as u16, st.y as u16, if w & 0x800 != 0 { 1 } else { -1 });
                    }
                }
                VECT_12 | VECT_8 => {
                    let (mut mask, width) = vector(w);
                    if !(st.y_valid && st.base_x_valid) {
                        stats.dropped_events += u64::from(mask.count_ones());
                    } else if mask != 0 {
                        let last = st.base_x + 31 - mask.leading_zeros();
                        if last >= xlim || st.y >= ylim {
                            return Err((i, last, st.y));
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
                TIME_HIGH => st.time_high(u32::from(w & 0xFFF)),
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

    /// Second pass: the words of `data` from a sync point in state `st` into `out`, which the first
    /// pass sized. Row, column and time words are handled without branches (every word stores a
    /// candidate event that only an ADDR_X with a valid row keeps); once `out` is full no later word
    /// can emit an event, so the loop stops. Returns whether a coordinate was outside the sensor.
    fn fill(&self, data: &[u8], mut st: State, out: ColumnsMut<'_>) -> bool {
        let (xlim, ylim) = self.limits();
        let ColumnsMut { t, x, y, p } = out;
        let len = t.len();
        assert!(x.len() == len && y.len() == len && p.len() == len);
        let (mut k, mut bad) = (0, false);
        let mut tt = st.t - st.shift;
        for w in data.chunks_exact(2) {
            if k == len {
                break;
            }
            let w = u16::from_le_bytes([w[0], w[1]]);
            let kind = w >> 12;
            let v = u32::from(w & 0x7FF);
            // Every word stores a candidate event; only an ADDR_X on a valid row keeps it.
            let keep = (kind == ADDR_X) & st.y_valid;
            t[k].write(tt);
            x[k].write(v as u16);
            y[k].write(st.y as u16);
            p[k].write(if w & 0x800 != 0 { 1 } else { -1 });
            bad |= keep & ((v >= xlim) | (st.y >= ylim));
            k += usize::from(keep);
            let is_row = kind == ADDR_Y;
            st.y = if is_row { v } else { st.y };
            st.y_valid = is_row | (st.y_valid & (kind != ADDR_Y_OTHER));
            tt = if kind == TIME_LOW { st.base + i64::from(w & 0xFFF) - st.shift } else { tt };
            if (STATEFUL_KINDS >> kind) & 1 == 0 {
                continue;
            }
            match kind {
                VECT_12 | VECT_8 => {
                    let (mut mask, width) = vector(w);
                    if st.y_valid && mask != 0 {
                        bad |= (st.base_x + 31 - mask.leading_zeros() >= xlim) | (st.y >= ylim);
                        while mask != 0 {
                            t[k].write(tt);
                            x[k].write((st.base_x + mask.trailing_zeros()) as u16);
                            y[k].write(st.y as u16);
                            p[k].write(st.pol);
                            k += 1;
                            mask &= mask - 1;
                        }
                    }
                    st.base_x = st.base_x.saturating_add(width);
                }
                VECT_BASE_X => {
                    st.base_x = v;
                    st.pol = if w & 0x800 != 0 { 1 } else { -1 };
                }
                TIME_HIGH => {
                    st.time_high(u32::from(w & 0xFFF));
                    tt = st.t - st.shift;
                }
                _ => {}
            }
        }
        // Every slot written: `Decoder::decode` relies on this to append them.
        assert_eq!(k, len, "EVT 3.0 first and second pass disagree");
        bad
    }
}

impl Decoder for Evt3Decoder {
    fn decode(&mut self, data: &[u8], offset: u64, out: &mut Events) -> Result<usize> {
        let n = data.len() / 2 * 2;
        if out.width == 0 && out.height == 0 {
            (out.width, out.height) = (self.width, self.height);
        }
        let chunks: Vec<&[u8]> = data[..n].chunks(2 * self.chunk_words).collect();
        let scans: Vec<ChunkScan> = chunks.par_iter().map(|c| ChunkScan::of(c)).collect();
        // Sequential pass: the parts before the sync points (a whole chunk until the stream starts).
        let (mut st, mut stats) = (self.st, self.stats);
        let mut heads = Events::default();
        let mut plans = Vec::with_capacity(chunks.len());
        let mut head_error = None;
        for (c, (chunk, scan)) in chunks.iter().zip(&scans).enumerate() {
            let sync = if st.started { scan.sync } else { chunk.len() / 2 };
            let from = heads.len();
            if let Err((i, x, y)) = self.words(&mut st, &mut stats, &chunk[..2 * sync], &mut heads) {
                head_error = Some((c, i, x, y));
                break;
            }
            let state = st;
            let events = if sync < chunk.len() / 2 {
                add_stats(&mut stats, &scan.stats);
                st = scan.apply(st);
                scan.events
            } else {
                0
            };
            plans.push(Plan { head: from..heads.len(), sync, state, events });
        }
        let sizes: Vec<usize> = plans.iter().flat_map(|p| [p.head.len(), p.events]).collect();
        let total = sizes.iter().sum();
        let mut parts = out.spare_parts(sizes).into_iter();
        let jobs: Vec<_> = plans
            .iter()
            .zip(&chunks)
            .map(|(p, c)| (p, c, parts.next().unwrap(), parts.next().unwrap()))
            .collect();
        let bad: Vec<bool> = jobs
            .into_par_iter()
            .map(|(plan, chunk, head, rest)| {
                head.copy_from(heads.view(), plan.head.clone());
                self.fill(&chunk[2 * plan.sync..], plan.state, rest)
            })
            .collect();
        // The first bad coordinate in file order: re-decode that chunk's rest with the reference.
        let error = bad.iter().position(|&b| b).map_or(head_error, |c| {
            let plan = &plans[c];
            let (mut st, mut scratch) = (plan.state, DecodeStats::default());
            let rest = &chunks[c][2 * plan.sync..];
            let (i, x, y) = self.words(&mut st, &mut scratch, rest, &mut Events::default()).unwrap_err();
            Some((c, plan.sync + i, x, y))
        });
        if let Some((c, i, x, y)) = error {
            return Err(Error::format(
                &self.path,
                format!("byte offset {}", offset + 2 * (c * self.chunk_words + i) as u64),
                format!("event ({x}, {y}) outside the {}x{} sensor", self.width, self.height),
            ));
        }
        // SAFETY: each head part is a whole copy and each rest part is filled whole (`fill` asserts
        // it); together they are contiguous.
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

/// Streaming EVT 3.0 encoder: the payload of a `.raw` file, batch by batch after [`write_raw_header`].
///
/// Consecutive events with the same time, row and polarity and increasing x (gaps ≤ 12) become one
/// VECT_BASE_X followed by VECT_12, VECT_12, VECT_8 groups (repeated without a new base for long runs);
/// single events become ADDR_X. Runs do not cross batches (the file stays valid, a word or two larger).
/// When the 24-bit counter loops, TIME_HIGH words at the last base before the loop and at the loop are
/// inserted so the decoder sees the fall. Times decode absolutely only within the first 2^24 µs period
/// of the first event (the format has no higher bits).
#[derive(Debug, Clone)]
pub struct Evt3Encoder {
    path: String,
    xlim: u32,
    ylim: u32,
    /// The registers written so far: TIME_HIGH base, full time, row.
    high: Option<i64>,
    time: Option<i64>,
    row: Option<u16>,
    seen: u64,
}

impl Evt3Encoder {
    /// `path` names the output in errors; coordinates must fit the sensor (`width`/`height`, 0 =
    /// unknown) and the 11-bit address fields.
    pub fn new(path: &str, width: u32, height: u32) -> Self {
        let lim = |n: u32| if n == 0 { MAX_COORD } else { n.min(MAX_COORD) };
        Evt3Encoder {
            path: path.into(),
            xlim: lim(width),
            ylim: lim(height),
            high: None,
            time: None,
            row: None,
            seen: 0,
        }
    }

    /// Append the words of the stream's next events to `out`. Unsorted or negative times and
    /// coordinates that do not fit are errors naming the event's index in the stream (nothing of
    /// the batch is written then).
    pub fn encode(&mut self, ev: EventsView<'_>, out: &mut Vec<u8>) -> Result<()> {
        check_encodable(&self.path, "EVT 3.0", ev, self.time, self.seen, 0, self.xlim, self.ylim)?;
        out.reserve(ev.len() * 2 + 64);
        let word = |out: &mut Vec<u8>, kind: u16, v: u32| {
            out.extend_from_slice(&((kind << 12) | v as u16).to_le_bytes())
        };
        let n = ev.len();
        let mut i = 0;
        while i < n {
            let (t, x, y, on) = (ev.t[i], ev.x[i], ev.y[i], ev.p[i] > 0);
            let h = t & !0xFFF;
            if self.high != Some(h) {
                if let Some(previous) = self.high {
                    for lp in (previous / LOOP + 1..=h / LOOP).map(|k| k * LOOP) {
                        word(out, TIME_HIGH, (((lp - 4096).max(previous) >> 12) & 0xFFF) as u32);
                        word(out, TIME_HIGH, 0);
                    }
                }
                word(out, TIME_HIGH, ((h >> 12) & 0xFFF) as u32);
                (self.high, self.time) = (Some(h), None);
            }
            if self.time != Some(t) {
                word(out, TIME_LOW, (t & 0xFFF) as u32);
                self.time = Some(t);
            }
            if self.row != Some(y) {
                word(out, ADDR_Y, u32::from(y));
                self.row = Some(y);
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
                word(out, ADDR_X, pol | u32::from(x));
            } else {
                word(out, VECT_BASE_X, pol | u32::from(x));
                let mut base = u32::from(x);
                for (k, group) in [12u32, 12, 8].into_iter().cycle().enumerate() {
                    let mut mask = 0;
                    while i < j && u32::from(ev.x[i]) < base + group {
                        mask |= 1 << (u32::from(ev.x[i]) - base);
                        i += 1;
                    }
                    word(out, if k % 3 == 2 { VECT_8 } else { VECT_12 }, mask);
                    base += group;
                    if i == j {
                        break;
                    }
                }
            }
            i = j;
        }
        self.seen += n as u64;
        Ok(())
    }
}

/// A complete EVT 3.0 `.raw` file (header + payload) for sorted, non-negative-time events.
pub fn encode_evt3(ev: EventsView<'_>) -> Result<Vec<u8>> {
    let mut out = write_raw_header(RawEncoding::Evt3, ev.width, ev.height);
    Evt3Encoder::new("memory", ev.width, ev.height).encode(ev, &mut out)?;
    Ok(out)
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
        let file = encode_evt3(ev.view()).unwrap();
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
        let file = encode_evt3(ev.view()).unwrap();
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

    /// Decode with the reference word-by-word decoder only (no chunks, no sync points).
    fn reference(data: &[u8], time_shift: bool) -> (Events, DecodeStats) {
        let dec = Evt3Decoder::new("f.raw", 1280, 720, time_shift);
        let (mut st, mut stats, mut out) = (State::default(), DecodeStats::default(), Events::default());
        dec.words(&mut st, &mut stats, data, &mut out).unwrap();
        out.width = 1280;
        out.height = 720;
        (out, stats)
    }

    /// Chunked (parallel) decoding equals the reference for any chunk size and thread count: chunk
    /// borders fall before the first TIME_HIGH, inside vector groups (groups continuing without a new
    /// VECT_BASE_X), between a row word and its events, around ADDR_Y_OTHER and across counter loops.
    #[test]
    fn chunked_parallel_decode_equals_reference() {
        let mut words = vec![w(ADDR_Y, 3), w(VECT_12, 5), w(ADDR_X, 1), w(TIME_HIGH, 0xFFE), w(VECT_12, 3)];
        words.extend([w(ADDR_X, 9), w(VECT_BASE_X, 0x800 | 10), w(ADDR_Y, 4), w(VECT_12, 0xFFF)]);
        words.extend([w(VECT_8, 0x81), w(VECT_12, 0x801), 0x9999, w(ADDR_Y_OTHER, 2), w(ADDR_X, 3)]);
        words.extend([w(VECT_12, 7), w(EXT_TRIGGER, 1), w(ADDR_Y, 5), w(TIME_LOW, 0xFFF), w(ADDR_X, 7)]);
        words.extend([w(TIME_HIGH, 0xFFF), w(VECT_12, 1), w(TIME_HIGH, 0), w(TIME_LOW, 3), w(ADDR_X, 8)]);
        words.extend([w(TIME_HIGH, 0), w(TIME_LOW, 0xC), w(TIME_LOW, 1), w(VECT_BASE_X, 20), w(ADDR_Y, 6)]);
        words.extend([w(VECT_8, 0xFF), w(ADDR_X, 0x800 | 1), w(0xE, 1), w(TIME_HIGH, 5)]);
        let mut data = bytes(&words);
        let file = encode_evt3(bursts(5000, 3).view()).unwrap();
        data.extend_from_slice(&file[parse_raw_header(&file, "f.raw").unwrap().data_offset..]);
        for time_shift in [false, true] {
            let (want, want_stats) = reference(&data, time_shift);
            assert!(want.len() > 5000 && want_stats.dropped_events > 0 && want_stats.skipped_words > 0);
            for chunk_words in [1, 2, 3, 5, 7, 64, 1000, usize::MAX / 4] {
                for threads in [1, 3] {
                    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
                    let mut dec = Evt3Decoder::new("f.raw", 1280, 720, time_shift);
                    dec.chunk_words = chunk_words;
                    let got = pool.install(|| feed::pieces(&mut dec, &data, 0, 3001).unwrap());
                    assert_eq!(got, want, "chunk {chunk_words}, {threads} threads");
                    assert_eq!(dec.stats(), want_stats, "chunk {chunk_words}");
                }
            }
        }
        // The first bad coordinate in file order is reported, in a head or after a sync point.
        let bad = bytes(&[w(TIME_HIGH, 0), w(ADDR_Y, 1), w(ADDR_X, 5), w(ADDR_X, 1300), w(ADDR_Y, 800)]);
        let mut bad = [bad.clone(), bad].concat();
        bad.extend(bytes(&[w(ADDR_X, 1)]));
        for chunk_words in [1, 2, 3, 4, 100] {
            let mut dec = Evt3Decoder::new("f.raw", 1280, 720, false);
            dec.chunk_words = chunk_words;
            let e = feed::whole(&mut dec, &bad, 40).unwrap_err().to_string();
            assert!(e.contains("byte offset 46") && e.contains("(1300, 1)"), "chunk {chunk_words}: {e}");
        }
    }
}

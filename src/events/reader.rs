//! Streaming event reader: open any Rust-decoded format, then pull batches in bounded memory.
//!
//! The file is read in blocks; the format's [`Decoder`] consumes what it can and the unconsumed tail
//! is carried into the next block. Sortedness and sensor bounds are checked here for every format
//! (text files check them line by line instead, so their errors name the line).

use std::fs::File;
use std::io::Read;

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::events::aedat4::{parse_aedat4_header, Aedat4Decoder};
use crate::events::detect::{detect, read_head, Format};
use crate::events::evt2::Evt2Decoder;
use crate::events::evt3::Evt3Decoder;
use crate::events::npy::{parse_npy_header, NpyDecoder};
use crate::events::raw_header::{parse_raw_header, DecodeStats};
use crate::events::text::{TextDecoder, TextLayout, TextOptions};
use crate::events::{reserve_huge, Decoder, Events, EventsView};

/// Bytes read per block. The two block buffers are reused, so reads land in memory that is already
/// mapped; decoders write straight into reserved output columns ([`Events::spare_parts`]), so blocks
/// cost no serial copies, and the next block is read while the current one decodes.
const BLOCK: usize = 16 << 20;
/// The first block of [`EventReader::read_all`], which estimates the output size.
const PROBE_BLOCK: usize = 1 << 20;
/// Room kept in front of each block for the previous block's unconsumed tail (a partial line, word
/// or packet), so the two become contiguous without moving the block. Larger tails are copied.
const GAP: usize = 1 << 20;

/// Read up to `want` bytes into `block` after a `gap`-byte front gap; returns the bytes read.
fn read_block(file: &mut File, block: &mut Vec<u8>, gap: usize, want: usize) -> std::io::Result<usize> {
    // The gap's contents are irrelevant: only resize (zero) it the first time.
    block.truncate(gap);
    block.resize(gap, 0);
    reserve_huge(block, want);
    // read_to_end fills spare capacity without zeroing it first.
    file.take(want as u64).read_to_end(block)
}

/// Reader options. `text.width/height` give the sensor size for formats that do not store one
/// (they override a header's); `text.columns` and `text.time_unit` also apply to NPY.
#[derive(Debug, Clone, Default)]
pub struct ReadOptions {
    pub text: TextOptions,
    /// Drop (and count) events outside the sensor instead of failing.
    pub drop_outside: bool,
    /// EVT 2.0/3.0: make times relative to the first TIME_HIGH (Metavision's default; evgs's is off).
    pub time_shift: bool,
}

/// Per-batch checks shared by every reader (Rust-decoded here, Python-decoded through the binding):
/// coordinates inside the sensor (or dropped and counted), and optionally non-decreasing time.
#[derive(Debug, Clone, Default)]
pub struct BatchCheck {
    /// Names the data in errors.
    pub path: String,
    /// Sensor size; 0 = unknown (no bounds check).
    pub width: u32,
    pub height: u32,
    pub drop_outside: bool,
    pub require_sorted: bool,
    /// Events examined so far (kept and dropped): the file position of the next one.
    pub seen: u64,
    /// Events dropped as outside the sensor.
    pub dropped: u64,
    last_t: Option<i64>,
}

impl BatchCheck {
    pub fn new(path: &str, width: u32, height: u32, drop_outside: bool, require_sorted: bool) -> Self {
        BatchCheck {
            path: path.to_owned(),
            width,
            height,
            drop_outside,
            require_sorted,
            ..Default::default()
        }
    }

    /// Check the next batch. Returns the indices to keep when some events were dropped.
    pub fn check(&mut self, v: EventsView<'_>) -> Result<Option<Vec<usize>>> {
        let (w, h) = (self.width, self.height);
        let outside = |i: usize| (w > 0 && u32::from(v.x[i]) >= w) || (h > 0 && u32::from(v.y[i]) >= h);
        let first_out = if w > 0 || h > 0 { first_where(v.len(), outside) } else { None };
        let keep = match first_out {
            None => None,
            Some(i) if !self.drop_outside => {
                return Err(Error::format(
                    &self.path,
                    format!("event {}", self.seen + i as u64),
                    format!(
                        "({}, {}) outside the {w}x{h} sensor (drop_outside drops such events)",
                        v.x[i], v.y[i]
                    ),
                ))
            }
            Some(_) => Some((0..v.len()).filter(|&i| !outside(i)).collect::<Vec<_>>()),
        };
        if self.require_sorted {
            let t = v.t;
            let bad = match &keep {
                Some(k) => {
                    let mut prev = self.last_t;
                    k.iter().find_map(|&i| {
                        let back = prev.filter(|&q| t[i] < q).map(|q| (i, q));
                        prev = Some(t[i]);
                        back
                    })
                }
                None => match (self.last_t, t.first()) {
                    (Some(q), Some(&t0)) if t0 < q => Some((0, q)),
                    _ => first_where(t.len().saturating_sub(1), |i| t[i + 1] < t[i]).map(|i| (i + 1, t[i])),
                },
            };
            if let Some((i, q)) = bad {
                return Err(Error::format(
                    &self.path,
                    format!("event {}", self.seen + i as u64),
                    format!("time goes backwards ({} < previous {q})", v.t[i]),
                ));
            }
        }
        let last = match &keep {
            Some(k) => k.last().map(|&i| v.t[i]),
            None => v.t.last().copied(),
        };
        self.last_t = last.or(self.last_t);
        self.seen += v.len() as u64;
        self.dropped += keep.as_ref().map_or(0, |k| (v.len() - k.len()) as u64);
        Ok(keep)
    }
}

/// The first `i < n` with `pred(i)`, scanning blocks in parallel with a branch-free (vectorisable)
/// test per block and only then locating the index.
fn first_where(n: usize, pred: impl Fn(usize) -> bool + Sync) -> Option<usize> {
    const B: usize = 1 << 14;
    let block = (0..n.div_ceil(B))
        .into_par_iter()
        .position_first(|b| (b * B..n.min(b * B + B)).fold(false, |any, i| any | pred(i)))?;
    (block * B..n.min(block * B + B)).find(|&i| pred(i))
}

enum AnyDecoder {
    Text(TextDecoder),
    Npy(NpyDecoder),
    Evt2(Evt2Decoder),
    Evt3(Evt3Decoder),
    Aedat4(Aedat4Decoder),
}

impl AnyDecoder {
    fn get(&mut self) -> &mut dyn Decoder {
        match self {
            AnyDecoder::Text(d) => d,
            AnyDecoder::Npy(d) => d,
            AnyDecoder::Evt2(d) => d,
            AnyDecoder::Evt3(d) => d,
            AnyDecoder::Aedat4(d) => d,
        }
    }
}

/// An open event file, decoded batch by batch.
pub struct EventReader {
    path: String,
    file: File,
    format: Format,
    decoder: AnyDecoder,
    /// Unconsumed bytes are `buf[start..]`; `buf[start]` is at absolute file offset `buf_offset`.
    buf: Vec<u8>,
    start: usize,
    buf_offset: u64,
    /// The next block (buffer, bytes read), read while the current one decoded.
    ahead: Option<std::io::Result<(Vec<u8>, usize)>>,
    /// The block buffer not in use.
    spare: Vec<u8>,
    /// [`BLOCK`] and [`GAP`] (smaller in tests).
    block: usize,
    gap: usize,
    file_size: u64,
    finished: bool,
    pending: Events,
    width: u32,
    height: u32,
    check: BatchCheck,
}

impl EventReader {
    /// Open `path`, detect its format from content unless `format` is given, parse its header.
    pub fn open(path: &str, format: Option<Format>, opts: &ReadOptions) -> Result<Self> {
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        let file_size = file.metadata().map_err(|e| Error::io(path, e))?.len();
        let mut head = read_head(&mut file, path)?;
        let format = match format {
            Some(f) => f,
            None => detect(&head, path)?,
        };
        let t = &opts.text;
        let (decoder, data_offset, width, height) = match format {
            Format::Text => {
                // With drop_outside the reader filters; otherwise the text decoder names the bad line.
                let mut text = t.clone();
                if opts.drop_outside {
                    (text.width, text.height) = (0, 0);
                }
                (AnyDecoder::Text(TextDecoder::new(&head, path, &text)?), 0, t.width, t.height)
            }
            Format::Npy => {
                let layout = parse_npy_header(&head, path, t.columns.as_deref(), t.time_unit)?;
                let off = layout.data_offset;
                (AnyDecoder::Npy(NpyDecoder::new(path, layout)), off, t.width, t.height)
            }
            // With drop_outside the camera decoders do not bound coordinates (the reader drops and
            // counts); otherwise they fail naming the byte offset.
            Format::Evt2 | Format::Evt3 => {
                let h = parse_raw_header(&head, path)?;
                let (w, hh) = if t.width > 0 { (t.width, t.height) } else { (h.width, h.height) };
                let (dw, dh) = if opts.drop_outside { (0, 0) } else { (w, hh) };
                let d = if format == Format::Evt2 {
                    AnyDecoder::Evt2(Evt2Decoder::new(path, dw, dh, opts.time_shift))
                } else {
                    AnyDecoder::Evt3(Evt3Decoder::new(path, dw, dh, opts.time_shift))
                };
                (d, h.data_offset, w, hh)
            }
            Format::Aedat4 => {
                let mut h = parse_aedat4_header(&head, path)?;
                let (w, hh) = if t.width > 0 { (t.width, t.height) } else { (h.width, h.height) };
                if opts.drop_outside {
                    (h.width, h.height) = (0, 0);
                }
                (AnyDecoder::Aedat4(Aedat4Decoder::new(path, &h)), h.data_offset, w, hh)
            }
            Format::Npz | Format::Hdf5 | Format::Parquet => {
                return Err(Error::Invalid(format!(
                    "{path}: {} files are read by the Python layer (evgs.events.io)",
                    format.name()
                )))
            }
        };
        let start = data_offset.min(head.len());
        head.drain(..start);
        Ok(EventReader {
            path: path.to_owned(),
            file,
            format,
            decoder,
            buf: head,
            start: 0,
            buf_offset: start as u64,
            ahead: None,
            spare: Vec::new(),
            block: BLOCK,
            gap: GAP,
            file_size,
            finished: false,
            pending: Events::with_capacity(0, width, height),
            width,
            height,
            // Text files check bounds and order line by line (unless dropping), naming the line.
            check: if format == Format::Text {
                let (w, h) = if opts.drop_outside { (width, height) } else { (0, 0) };
                BatchCheck::new(path, w, h, opts.drop_outside, false)
            } else {
                BatchCheck::new(path, width, height, opts.drop_outside, t.require_sorted)
            },
        })
    }

    pub fn format(&self) -> Format {
        self.format
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    pub fn file_size(&self) -> u64 {
        self.file_size
    }

    /// File bytes decoded so far (for progress bars).
    pub fn bytes_done(&self) -> u64 {
        self.buf_offset
    }

    /// Events dropped because they were outside the sensor (only with `drop_outside`).
    pub fn dropped_outside(&self) -> u64 {
        self.check.dropped
    }

    /// The sniffed layout of a text file.
    pub fn text_layout(&self) -> Option<&TextLayout> {
        match &self.decoder {
            AnyDecoder::Text(d) => Some(d.layout()),
            _ => None,
        }
    }

    /// What the camera decoder skipped (triggers, words before the first time base, ...).
    pub fn decode_stats(&self) -> Option<DecodeStats> {
        match &self.decoder {
            AnyDecoder::Evt2(d) => Some(d.stats()),
            AnyDecoder::Evt3(d) => Some(d.stats()),
            AnyDecoder::Aedat4(d) => Some(d.stats()),
            AnyDecoder::Text(_) | AnyDecoder::Npy(_) => None,
        }
    }

    /// Decode one more block into `pending` (or finish at end of file), reading the block after it
    /// at the same time.
    fn fill(&mut self) -> Result<()> {
        let path = self.path.clone();
        let io = |e| Error::io(&path, e);
        let (mut block, got) = match self.ahead.take() {
            Some(read) => read.map_err(io)?,
            None => {
                let mut b = std::mem::take(&mut self.spare);
                let got = read_block(&mut self.file, &mut b, self.gap, self.block).map_err(io)?;
                (b, got)
            }
        };
        // The unconsumed tail goes right before the new bytes.
        let (tail, gap) = (&self.buf[self.start..], self.gap);
        let (current, start) = if tail.len() <= gap {
            block[gap - tail.len()..gap].copy_from_slice(tail);
            (block, gap - tail.len())
        } else {
            let mut joined = tail.to_vec();
            joined.extend_from_slice(&block[gap..]);
            self.spare = block;
            (joined, 0)
        };
        let old = std::mem::replace(&mut self.buf, current);
        if self.spare.capacity() < old.capacity() {
            self.spare = old;
        }
        self.start = start;
        let before = self.pending.len();
        if got == 0 {
            let data = &self.buf[self.start..];
            let used = self.decoder.get().decode(data, self.buf_offset, &mut self.pending)?;
            let tail = &data[used..];
            self.decoder.get().finish(tail, self.buf_offset + used as u64, &mut self.pending)?;
            self.buf_offset += data.len() as u64;
            self.start = self.buf.len();
            self.finished = true;
        } else {
            let mut spare = std::mem::take(&mut self.spare);
            let EventReader { file, decoder, buf, start, buf_offset, pending, gap, block, .. } = self;
            let data = &buf[*start..];
            let (read, used) = rayon::join(
                || read_block(file, &mut spare, *gap, *block).map(|got| (spare, got)),
                || decoder.get().decode(data, *buf_offset, pending),
            );
            self.ahead = Some(read);
            let used = used?;
            self.start += used;
            self.buf_offset += used as u64;
        }
        self.check_new(before)
    }

    /// Sortedness and sensor bounds of the events appended since `from`.
    fn check_new(&mut self, from: usize) -> Result<()> {
        let p = &mut self.pending;
        let v = EventsView {
            t: &p.t[from..],
            x: &p.x[from..],
            y: &p.y[from..],
            p: &p.p[from..],
            width: 0,
            height: 0,
        };
        if let Some(keep) = self.check.check(v)? {
            for (k, &j) in keep.iter().enumerate() {
                let j = from + j;
                (p.t[from + k], p.x[from + k], p.y[from + k], p.p[from + k]) =
                    (p.t[j], p.x[j], p.y[j], p.p[j]);
            }
            let n = from + keep.len();
            p.t.truncate(n);
            p.x.truncate(n);
            p.y.truncate(n);
            p.p.truncate(n);
        }
        Ok(())
    }

    /// The next batch of at most `max_events` events, or `None` at the end of the file.
    pub fn next_batch(&mut self, max_events: usize) -> Result<Option<Events>> {
        let max = max_events.max(1);
        while self.pending.len() < max && !self.finished {
            self.fill()?;
        }
        if self.pending.is_empty() {
            return Ok(None);
        }
        let batch = if self.pending.len() <= max {
            std::mem::replace(&mut self.pending, Events::with_capacity(0, self.width, self.height))
        } else {
            let p = &mut self.pending;
            let rest = Events {
                t: p.t.split_off(max),
                x: p.x.split_off(max),
                y: p.y.split_off(max),
                p: p.p.split_off(max),
                width: self.width,
                height: self.height,
            };
            std::mem::replace(p, rest)
        };
        Ok(Some(batch))
    }

    /// Every remaining event.
    pub fn read_all(&mut self) -> Result<Events> {
        if !self.finished {
            // Decode a small first block to learn the events per byte, then reserve the whole output
            // once (plus 1/8): growing block by block would let `realloc` copy the columns into fresh
            // pages again and again.
            let probe = self.block.min(PROBE_BLOCK);
            let block = std::mem::replace(&mut self.block, probe);
            let first = self.fill();
            self.block = block;
            first?;
            let done = self.bytes_done().max(1);
            let rest = self.file_size.saturating_sub(done);
            let est = u64::try_from(self.pending.len() as u128 * u128::from(rest) / u128::from(done));
            let est = usize::try_from(est.unwrap_or(u64::MAX)).unwrap_or(usize::MAX);
            self.pending.reserve(est.saturating_add(est / 8));
        }
        while !self.finished {
            self.fill()?;
        }
        let all = std::mem::take(&mut self.pending);
        Ok(Events { width: self.width, height: self.height, ..all })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::events::npy::{encode_npy_rows, npy_header, NpyStyle};
    use crate::test_util::TempDir;

    fn sample(n: usize) -> Events {
        let mut ev = Events::with_capacity(n, 64, 48);
        for i in 0..n {
            ev.push(i as i64 * 3, (i % 64) as u16, (i % 48) as u16, if i % 3 == 0 { 1 } else { -1 });
        }
        ev
    }

    #[test]
    fn batches_equal_whole_read_for_every_rust_format() {
        let dir = TempDir::new("reader");
        let ev = sample(100_003);
        let mut npy = npy_header(ev.len() as u64, NpyStyle::Structured);
        npy.extend(encode_npy_rows(ev.view(), NpyStyle::Structured));
        let files = [
            (dir.write("a.npy", &npy), Format::Npy),
            (dir.write("a.raw", &crate::events::evt2::encode_evt2(ev.view()).unwrap()), Format::Evt2),
            (dir.write("b.raw", &crate::events::evt3::encode_evt3(ev.view()).unwrap()), Format::Evt3),
        ];
        let opts = ReadOptions {
            text: TextOptions { width: 64, height: 48, ..Default::default() },
            ..Default::default()
        };
        for (path, fmt) in files {
            let mut r = EventReader::open(&path, None, &opts).unwrap();
            assert_eq!(r.format(), fmt);
            let mut got = Events::with_capacity(0, 64, 48);
            while let Some(b) = r.next_batch(7777).unwrap() {
                assert!(b.len() <= 7777);
                got.extend(&b);
            }
            assert_eq!(got, ev, "{fmt:?}");
            assert_eq!(EventReader::open(&path, None, &opts).unwrap().read_all().unwrap(), ev);
        }
    }

    /// Tiny blocks and gaps: tails longer than the gap (AEDAT 4 packets, partial lines) are joined by
    /// copying, shorter ones placed in the gap; the result is the same for every format.
    #[test]
    fn small_blocks_and_gaps_read_the_same() {
        let dir = TempDir::new("reader");
        use crate::events::aedat4::{encode_aedat4, Aedat4Compression};
        use crate::events::text::{encode_text, TextStyle, TimeUnit};
        // Larger than the 1 MiB head read at open, so blocks are read.
        let ev = sample(300_000);
        let style = TextStyle { delimiter: b',', time_unit: TimeUnit::Us, header: true, zero_one: true };
        let files = [
            dir.write("s.csv", &encode_text(ev.view(), style)),
            dir.write("s2.raw", &crate::events::evt2::encode_evt2(ev.view()).unwrap()),
            dir.write("s3.raw", &crate::events::evt3::encode_evt3(ev.view()).unwrap()),
            dir.write("s.aedat4", &encode_aedat4(ev.view(), Aedat4Compression::None, 300).unwrap()),
        ];
        let opts = ReadOptions {
            text: TextOptions { width: 64, height: 48, ..Default::default() },
            ..Default::default()
        };
        for path in files {
            assert!(std::fs::metadata(&path).unwrap().len() > 1 << 20);
            for (block, gap) in [(4093, 3), (65_536, 100), (1 << 20, 1 << 20)] {
                let mut r = EventReader::open(&path, None, &opts).unwrap();
                (r.block, r.gap) = (block, gap);
                assert_eq!(r.read_all().unwrap(), ev, "{path} block {block} gap {gap}");
            }
        }
    }

    #[test]
    fn outside_and_unsorted_are_errors_or_counted() {
        let dir = TempDir::new("reader");
        let mut ev = sample(10);
        ev.x[4] = 70;
        let mut npy = npy_header(10, NpyStyle::Structured);
        npy.extend(encode_npy_rows(ev.view(), NpyStyle::Structured));
        let path = dir.write("o.npy", &npy);
        let mut opts = ReadOptions {
            text: TextOptions { width: 64, height: 48, ..Default::default() },
            ..Default::default()
        };
        let e = EventReader::open(&path, None, &opts).unwrap().read_all().unwrap_err().to_string();
        assert!(e.contains("event 4: (70, 4) outside the 64x48 sensor"), "{e}");
        opts.drop_outside = true;
        let mut r = EventReader::open(&path, None, &opts).unwrap();
        assert_eq!(r.read_all().unwrap().len(), 9);
        assert_eq!(r.dropped_outside(), 1);
        ev.x[4] = 0;
        ev.t[6] = 0;
        let mut npy = npy_header(10, NpyStyle::Structured);
        npy.extend(encode_npy_rows(ev.view(), NpyStyle::Structured));
        let path = dir.write("u.npy", &npy);
        opts.text.require_sorted = true;
        let e = EventReader::open(&path, None, &opts).unwrap().read_all().unwrap_err().to_string();
        assert!(e.contains("event 6: time goes backwards"), "{e}");
    }

    /// The block-parallel scans find the first bad event, also past the first block and at the
    /// border between batches.
    #[test]
    fn batch_check_finds_the_first_bad_event_in_long_batches() {
        let ev = sample(50_000);
        let check = |ev: &Events, require_sorted| {
            let mut c = BatchCheck::new("f", 64, 48, false, require_sorted);
            c.check(ev.view()).map(|_| ()).unwrap_err().to_string()
        };
        let mut bad = ev.clone();
        bad.t[40_000] = 0;
        bad.t[45_000] = 0;
        assert!(check(&bad, true).contains("event 40000: time goes backwards"));
        bad.x[30_001] = 64;
        assert!(check(&bad, false).contains("event 30001: (64, 1) outside"));
        let mut c = BatchCheck::new("f", 64, 48, false, true);
        c.check(ev.view()).unwrap();
        assert!(c.check(ev.view()).unwrap_err().to_string().contains("event 50000: time goes backwards"));
        let mut c = BatchCheck::new("f", 64, 48, true, true);
        let e = c.check(bad.view()).unwrap_err().to_string();
        assert!(e.contains("event 40000: time goes backwards"), "{e}");
    }

    /// drop_outside applies to the camera formats too (their decoders would otherwise fail first).
    #[test]
    fn camera_formats_drop_and_count_outside_events() {
        let dir = TempDir::new("reader");
        use crate::events::aedat4::{encode_aedat4, Aedat4Compression};
        let mut ev = sample(10);
        ev.x[4] = 70;
        // Written without a sensor size (the encoders refuse events outside it); read with one.
        let ev = EventsView { width: 0, height: 0, ..ev.view() };
        let files = [
            dir.write("d2.raw", &crate::events::evt2::encode_evt2(ev).unwrap()),
            dir.write("d3.raw", &crate::events::evt3::encode_evt3(ev).unwrap()),
            dir.write("d.aedat4", &encode_aedat4(ev, Aedat4Compression::Lz4, 4).unwrap()),
        ];
        for path in files {
            let mut opts = ReadOptions {
                text: TextOptions { width: 64, height: 48, ..Default::default() },
                ..Default::default()
            };
            let e = EventReader::open(&path, None, &opts).unwrap().read_all().unwrap_err().to_string();
            assert!(e.contains("(70, 4) outside"), "{path}: {e}");
            opts.drop_outside = true;
            let mut r = EventReader::open(&path, None, &opts).unwrap();
            assert_eq!(r.read_all().unwrap().len(), 9, "{path}");
            assert_eq!(r.dropped_outside(), 1);
        }
    }
}

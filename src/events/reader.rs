//! Streaming event reader: open any Rust-decoded format, then pull batches in bounded memory.
//!
//! The file is read in blocks; the format's [`Decoder`] consumes what it can and the unconsumed tail
//! is carried into the next block. Sortedness and sensor bounds are checked here for every format
//! (text files check them line by line instead, so their errors name the line).

use std::fs::File;
use std::io::Read;

use crate::error::{Error, Result};
use crate::events::aedat4::{parse_aedat4_header, Aedat4Decoder};
use crate::events::detect::{detect, Format};
use crate::events::evt2::Evt2Decoder;
use crate::events::evt3::Evt3Decoder;
use crate::events::npy::{parse_npy_header, NpyDecoder};
use crate::events::raw_header::{parse_raw_header, DecodeStats};
use crate::events::text::{TextDecoder, TextOptions};
use crate::events::{Decoder, Events};

/// Bytes read for detection and headers (RAW/AEDAT 4 headers and text sniffing fit easily).
const HEAD: usize = 1 << 20;
/// Bytes read per block.
const BLOCK: usize = 16 << 20;

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
    /// Unconsumed bytes; `buf[0]` is at absolute file offset `buf_offset`.
    buf: Vec<u8>,
    buf_offset: u64,
    file_size: u64,
    finished: bool,
    pending: Events,
    width: u32,
    height: u32,
    drop_outside: bool,
    require_sorted: bool,
    /// Events handed out so far (and dropped), for positions in error messages.
    emitted: u64,
    dropped_outside: u64,
    last_t: Option<i64>,
}

impl EventReader {
    /// Open `path`, detect its format from content unless `format` is given, parse its header.
    pub fn open(path: &str, format: Option<Format>, opts: &ReadOptions) -> Result<Self> {
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        let file_size = file.metadata().map_err(|e| Error::io(path, e))?.len();
        let mut head = Vec::with_capacity(HEAD);
        (&mut file).take(HEAD as u64).read_to_end(&mut head).map_err(|e| Error::io(path, e))?;
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
            Format::Evt2 | Format::Evt3 => {
                let h = parse_raw_header(&head, path)?;
                let (w, hh) = if t.width > 0 { (t.width, t.height) } else { (h.width, h.height) };
                let d = if format == Format::Evt2 {
                    AnyDecoder::Evt2(Evt2Decoder::new(path, w, hh, opts.time_shift))
                } else {
                    AnyDecoder::Evt3(Evt3Decoder::new(path, w, hh, opts.time_shift))
                };
                (d, h.data_offset, w, hh)
            }
            Format::Aedat4 => {
                let h = parse_aedat4_header(&head, path)?;
                let (w, hh) = if t.width > 0 { (t.width, t.height) } else { (h.width, h.height) };
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
            buf_offset: start as u64,
            file_size,
            finished: false,
            pending: Events::with_capacity(0, width, height),
            width,
            height,
            drop_outside: opts.drop_outside,
            require_sorted: t.require_sorted,
            emitted: 0,
            dropped_outside: 0,
            last_t: None,
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
        self.dropped_outside
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

    /// Read one more block and decode it into `pending` (or finish at end of file).
    fn fill(&mut self) -> Result<()> {
        let have = self.buf.len();
        let want = BLOCK.max(have);
        self.buf.resize(have + want, 0);
        let mut got = 0;
        while got < want {
            match self.file.read(&mut self.buf[have + got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(Error::io(&self.path, e)),
            }
        }
        self.buf.truncate(have + got);
        let before = self.pending.len();
        let used = self.decoder.get().decode(&self.buf, self.buf_offset, &mut self.pending)?;
        self.buf.drain(..used);
        self.buf_offset += used as u64;
        if got == 0 {
            self.decoder.get().finish(&self.buf, self.buf_offset, &mut self.pending)?;
            self.buf_offset += self.buf.len() as u64;
            self.buf.clear();
            self.finished = true;
        }
        self.check_new(before)
    }

    /// Sortedness and sensor bounds of the events appended since `from`.
    fn check_new(&mut self, from: usize) -> Result<()> {
        let p = &mut self.pending;
        // File position of pending[i] (exact unless events were dropped inside this batch).
        let base = self.emitted + self.dropped_outside;
        let (w, h) = (self.width, self.height);
        if (w > 0 || h > 0) && self.format != Format::Text || self.drop_outside {
            let outside = |x: u16, y: u16| (w > 0 && u32::from(x) >= w) || (h > 0 && u32::from(y) >= h);
            if let Some(i) = (from..p.len()).find(|&i| outside(p.x[i], p.y[i])) {
                if !self.drop_outside {
                    return Err(Error::format(
                        &self.path,
                        format!("event {}", base + i as u64),
                        format!(
                            "({}, {}) outside the {w}x{h} sensor (use drop_outside to drop such events)",
                            p.x[i], p.y[i]
                        ),
                    ));
                }
                let mut k = i;
                for j in i..p.len() {
                    if !outside(p.x[j], p.y[j]) {
                        (p.t[k], p.x[k], p.y[k], p.p[k]) = (p.t[j], p.x[j], p.y[j], p.p[j]);
                        k += 1;
                    }
                }
                self.dropped_outside += (p.len() - k) as u64;
                p.t.truncate(k);
                p.x.truncate(k);
                p.y.truncate(k);
                p.p.truncate(k);
            }
        }
        if self.require_sorted && self.format != Format::Text {
            let mut prev = if from > 0 { Some(p.t[from - 1]) } else { self.last_t };
            for i in from..p.len() {
                if prev.is_some_and(|q| p.t[i] < q) {
                    return Err(Error::format(
                        &self.path,
                        format!("event {}", base + i as u64),
                        format!("time goes backwards ({} < previous {})", p.t[i], prev.unwrap()),
                    ));
                }
                prev = Some(p.t[i]);
            }
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
        self.last_t = batch.t.last().copied();
        self.emitted += batch.len() as u64;
        Ok(Some(batch))
    }

    /// Every remaining event.
    pub fn read_all(&mut self) -> Result<Events> {
        while !self.finished {
            self.fill()?;
        }
        let all = std::mem::take(&mut self.pending);
        self.emitted += all.len() as u64;
        Ok(Events { width: self.width, height: self.height, ..all })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::events::npy::{encode_npy_rows, npy_header, NpyStyle};

    fn tmp(name: &str, bytes: &[u8]) -> String {
        let dir = std::env::temp_dir().join(format!("evgs-reader-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        p.to_string_lossy().into_owned()
    }

    fn sample(n: usize) -> Events {
        let mut ev = Events::with_capacity(n, 64, 48);
        for i in 0..n {
            ev.push(i as i64 * 3, (i % 64) as u16, (i % 48) as u16, if i % 3 == 0 { 1 } else { -1 });
        }
        ev
    }

    #[test]
    fn batches_equal_whole_read_for_every_rust_format() {
        let ev = sample(100_003);
        let mut npy = npy_header(ev.len() as u64, NpyStyle::Structured);
        npy.extend(encode_npy_rows(ev.view(), NpyStyle::Structured));
        let files = [
            (tmp("a.npy", &npy), Format::Npy),
            (tmp("a.raw", &crate::events::evt2::encode_evt2(ev.view())), Format::Evt2),
            (tmp("b.raw", &crate::events::evt3::encode_evt3(ev.view())), Format::Evt3),
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

    #[test]
    fn outside_and_unsorted_are_errors_or_counted() {
        let mut ev = sample(10);
        ev.x[4] = 70;
        let mut npy = npy_header(10, NpyStyle::Structured);
        npy.extend(encode_npy_rows(ev.view(), NpyStyle::Structured));
        let path = tmp("o.npy", &npy);
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
        let path = tmp("u.npy", &npy);
        opts.text.require_sorted = true;
        let e = EventReader::open(&path, None, &opts).unwrap().read_all().unwrap_err().to_string();
        assert!(e.contains("event 6: time goes backwards"), "{e}");
    }
}

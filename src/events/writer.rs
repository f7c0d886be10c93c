//! Camera-format files (EVT 2.0, EVT 3.0, AEDAT 4) written batch by batch in bounded memory.
//!
//! Each batch is encoded into a reused buffer and written out; only AEDAT 4's packet table (a few
//! bytes per packet) and the events of one partial packet are kept. The caller writes to a temporary
//! path and renames it into place after [`CameraWriter::finish`] (atomic output).

use std::fs::File;
use std::io::{Seek, SeekFrom, Write};

use crate::error::{Error, Result};
use crate::events::aedat4::{Aedat4Compression, Aedat4Encoder, DATA_TABLE_FIELD};
use crate::events::evt2::Evt2Encoder;
use crate::events::evt3::Evt3Encoder;
use crate::events::raw_header::{write_raw_header, RawEncoding};
use crate::events::EventsView;

/// Events per AEDAT 4 packet (a few ms of a busy sensor, as DV writes).
pub const AEDAT4_PACKET_EVENTS: usize = 4096;

enum Encoder {
    Evt2(Evt2Encoder),
    Evt3(Evt3Encoder),
    Aedat4(Aedat4Encoder),
}

/// An open camera-format output file.
pub struct CameraWriter {
    path: String,
    /// Unbuffered: every write is a whole encoded batch.
    file: File,
    encoder: Encoder,
    buf: Vec<u8>,
}

impl CameraWriter {
    /// Create `path` and write the header. `name` is what errors call the output (the final path
    /// when `path` is a temporary). `format` is `evt2`, `evt3`, `aedat4` (LZ4), `aedat4-lz4`,
    /// `aedat4-zstd` or `aedat4-none`; `width`/`height` (0 = unknown) go into the header and bound
    /// the coordinates.
    pub fn create(path: &str, name: &str, format: &str, width: u32, height: u32) -> Result<Self> {
        let aedat4 =
            |c| Aedat4Encoder::new(name, width, height, c, AEDAT4_PACKET_EVENTS).map(Encoder::Aedat4);
        let encoder = match format {
            "evt2" => Encoder::Evt2(Evt2Encoder::new(name, width, height)),
            "evt3" => Encoder::Evt3(Evt3Encoder::new(name, width, height)),
            "aedat4" | "aedat4-lz4" => aedat4(Aedat4Compression::Lz4)?,
            "aedat4-zstd" => aedat4(Aedat4Compression::Zstd)?,
            "aedat4-none" => aedat4(Aedat4Compression::None)?,
            _ => {
                return Err(Error::Invalid(format!(
                    "{name}: no camera-format writer for {format:?} (evt2, evt3, aedat4, aedat4-lz4, \
                     aedat4-zstd, aedat4-none)"
                )))
            }
        };
        let header = match &encoder {
            Encoder::Evt2(_) => write_raw_header(RawEncoding::Evt2, width, height),
            Encoder::Evt3(_) => write_raw_header(RawEncoding::Evt3, width, height),
            Encoder::Aedat4(e) => e.header().to_vec(),
        };
        let file = File::create(path).map_err(|e| Error::io(path, e))?;
        let mut w = CameraWriter { path: path.into(), file, encoder, buf: header };
        w.flush_buf()?;
        Ok(w)
    }

    fn flush_buf(&mut self) -> Result<()> {
        self.file.write_all(&self.buf).map_err(|e| Error::io(&self.path, e))?;
        self.buf.clear();
        Ok(())
    }

    /// Encode and write the stream's next events (errors name the event's index in the stream).
    pub fn write(&mut self, ev: EventsView<'_>) -> Result<()> {
        let buf = &mut self.buf;
        match &mut self.encoder {
            Encoder::Evt2(e) => e.encode(ev, buf)?,
            Encoder::Evt3(e) => e.encode(ev, buf)?,
            Encoder::Aedat4(e) => e.encode(ev, buf)?,
        }
        self.flush_buf()
    }

    /// Write what is still pending (AEDAT 4: the last packet, the table, its position in the
    /// header) and flush the file to disk.
    pub fn finish(mut self) -> Result<()> {
        if let Encoder::Aedat4(e) = &mut self.encoder {
            let position = e.finish(&mut self.buf);
            self.flush_buf()?;
            let io = |e| Error::io(&self.path, e);
            self.file.seek(SeekFrom::Start(DATA_TABLE_FIELD)).map_err(io)?;
            self.file.write_all(&(position as i64).to_le_bytes()).map_err(io)?;
        }
        self.file.sync_all().map_err(|e| Error::io(&self.path, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::events::raw_header::feed::random_events;
    use crate::events::reader::{EventReader, ReadOptions};
    use crate::test_util::TempDir;

    /// Batches of any size (also smaller than a packet, and empty) give a file that reads back as
    /// the whole stream, for every camera format.
    #[test]
    fn batch_by_batch_round_trips() {
        let dir = TempDir::new("writer");
        let ev = random_events(30_000, 5, 1_000, 3, 640, 480);
        for format in ["evt2", "evt3", "aedat4", "aedat4-zstd", "aedat4-none"] {
            let path = dir.path(&format!("rt-{format}"));
            let mut w = CameraWriter::create(&path, "out", format, 640, 480).unwrap();
            let mut from = 0;
            for size in [0, 1, 4095, 4097, 7, 10_000].into_iter().cycle() {
                let to = (from + size).min(ev.len());
                let v = ev.view();
                w.write(EventsView {
                    t: &v.t[from..to],
                    x: &v.x[from..to],
                    y: &v.y[from..to],
                    p: &v.p[from..to],
                    ..v
                })
                .unwrap();
                from = to;
                if from == ev.len() {
                    break;
                }
            }
            w.finish().unwrap();
            let got = EventReader::open(&path, None, &ReadOptions::default()).unwrap().read_all().unwrap();
            assert_eq!(got, ev, "{format}");
        }
    }

    #[test]
    fn unsorted_negative_and_outside_events_are_errors_naming_the_event() {
        let dir = TempDir::new("writer");
        let ev = random_events(100, 7, 0, 3, 640, 480);
        for format in ["evt2", "evt3", "aedat4"] {
            let mut w =
                CameraWriter::create(&dir.path(&format!("bad-{format}")), "out", format, 640, 480).unwrap();
            w.write(ev.view()).unwrap();
            let mut next = ev.clone();
            next.t.iter_mut().for_each(|t| *t += 1000);
            next.t[10] = next.t[9] - 1;
            let e = w.write(next.view()).unwrap_err().to_string();
            assert!(e.contains("event 110") && e.contains("time-sorted"), "{format}: {e}");
            let mut w =
                CameraWriter::create(&dir.path(&format!("bad2-{format}")), "out", format, 640, 480).unwrap();
            w.write(ev.view()).unwrap();
            let e = w.write(ev.view()).unwrap_err().to_string();
            assert!(e.contains("event 100") && e.contains("before the previous"), "{format}: {e}");
            let mut outside = ev.clone();
            outside.x[42] = 640;
            let e =
                CameraWriter::create(&dir.path("o"), "out", format, 640, 480).unwrap().write(outside.view());
            assert!(e.unwrap_err().to_string().contains("event 42: (640, "), "{format}");
        }
        let mut negative = ev.clone();
        negative.t[0] = -1;
        let e = CameraWriter::create(&dir.path("n"), "out", "evt3", 0, 0).unwrap().write(negative.view());
        assert!(e.unwrap_err().to_string().contains("event 0: time -1 µs is negative"));
        assert!(CameraWriter::create(&dir.path("x"), "out", "evt4", 0, 0).is_err());
    }
}

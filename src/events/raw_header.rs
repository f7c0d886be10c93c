//! The Prophesee RAW container header (`% key value` lines) shared by EVT 2.0 and 3.0, and the
//! counters every camera decoder reports (so the CLI can say what was skipped instead of hiding it).

use crate::error::{Error, Result};
use crate::events::EventsView;

/// The payload encoding named by the header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RawEncoding {
    Evt2,
    Evt3,
}

/// What the header says about the recording. `width`/`height` are 0 when the header names no geometry.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawHeader {
    pub encoding: RawEncoding,
    pub width: u32,
    pub height: u32,
    /// Absolute file offset of the first payload byte.
    pub data_offset: usize,
    /// Every header line in file order, as (key, value).
    pub fields: Vec<(String, String)>,
}

/// Words and events a camera decoder skipped or dropped, by reason. Nothing is dropped silently.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecodeStats {
    /// External-trigger words (EVT 2.0 / 3.0); they carry no pixel event.
    pub triggers: u64,
    /// Words before the first TIME_HIGH: their time is unknown (a recording started mid-stream).
    pub words_before_time_high: u64,
    /// Non-CD words: OTHERS, CONTINUED, IMU and reserved types (incl. 0x9999 padding).
    pub skipped_words: u64,
    /// EVT 3.0 CD events whose row or vector base is not yet known (mid-stream start) — dropped.
    pub dropped_events: u64,
    /// Bytes of a trailing partial RAW word at end of file — dropped.
    pub dropped_partial_bytes: u64,
    /// AEDAT 4 packets of other streams (frames, IMU, triggers) — skipped by size.
    pub skipped_packets: u64,
}

/// Coordinate bound when the header names no geometry: EVT 2.0 / 3.0 addresses are 11-bit fields.
pub(crate) const MAX_COORD: u32 = 1 << 11;

/// The (encoding, width, height) of the OpenEB `system_ID` table, for headers without geometry.
fn system_id_geometry(id: &str) -> Option<(RawEncoding, u32, u32)> {
    match id.trim() {
        "21" => Some((RawEncoding::Evt2, 640, 480)),
        "48" | "49" => Some((RawEncoding::Evt3, 1280, 720)),
        _ => None,
    }
}

/// Parse the header at the start of `data` (the file's first bytes, at least the whole header).
///
/// The payload starts after the line `% end` or at the first line not starting with the two bytes
/// `% ` (older files have no `% end`). The encoding comes from `format` (else `evt`, else the
/// `system_ID` table), the geometry from the `format` options (else `geometry`, else `system_ID`).
pub fn parse_raw_header(data: &[u8], path: &str) -> Result<RawHeader> {
    let mut fields = Vec::new();
    let mut pos = 0;
    while data[pos..].starts_with(b"% ") {
        let Some(len) = data[pos..].iter().position(|&b| b == b'\n') else {
            return Err(Error::format(path, format!("byte offset {pos}"), "header line has no line feed"));
        };
        let line = &data[pos + 2..pos + len];
        let line = line.strip_suffix(b"\r").unwrap_or(line);
        let line = std::str::from_utf8(line)
            .map_err(|_| Error::format(path, format!("byte offset {pos}"), "header line is not UTF-8"))?;
        let (key, value) = line.split_once(' ').unwrap_or((line, ""));
        pos += len + 1;
        if key == "end" {
            break;
        }
        fields.push((key.to_string(), value.to_string()));
    }
    let field = |name: &str| fields.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str());
    let bad = |message: String| Error::format(path, "header", message);
    let system = field("system_ID").and_then(system_id_geometry);

    let encoding = if let Some(format) = field("format") {
        let name = format.split(';').next().unwrap_or("").trim();
        match name {
            "EVT2" => RawEncoding::Evt2,
            "EVT3" => RawEncoding::Evt3,
            _ => return Err(bad(format!("unsupported format `{name}` (EVT2 and EVT3 are supported)"))),
        }
    } else if let Some(evt) = field("evt") {
        match evt.trim() {
            "2.0" => RawEncoding::Evt2,
            "3.0" => RawEncoding::Evt3,
            other => {
                return Err(bad(format!("unsupported evt version `{other}` (2.0 and 3.0 are supported)")))
            }
        }
    } else if let Some((encoding, _, _)) = system {
        encoding
    } else {
        return Err(bad("no `format`, `evt` or known `system_ID` line names the encoding".into()));
    };

    let (width, height) = if let Some(g) = field("format").and_then(|f| format_geometry(f, path).transpose())
    {
        g?
    } else if let Some(g) = field("geometry") {
        parse_geometry(g).ok_or_else(|| bad(format!("geometry `{g}` is not WIDTHxHEIGHT")))?
    } else {
        system.map_or((0, 0), |(_, w, h)| (w, h))
    };
    Ok(RawHeader { encoding, width, height, data_offset: pos, fields })
}

/// `width=`/`height=` options of a `format` value such as `EVT3;height=720;width=1280`.
fn format_geometry(format: &str, path: &str) -> Result<Option<(u32, u32)>> {
    let (mut width, mut height) = (None, None);
    for option in format.split(';').skip(1) {
        let (key, value) = option.split_once('=').unwrap_or((option, ""));
        let slot = match key.trim() {
            "width" => &mut width,
            "height" => &mut height,
            _ => continue,
        };
        let v = value.trim().parse::<u32>().map_err(|_| {
            Error::format(path, "header", format!("format option `{option}` is not a number"))
        })?;
        *slot = Some(v);
    }
    Ok(width.zip(height))
}

fn parse_geometry(value: &str) -> Option<(u32, u32)> {
    let (w, h) = value.trim().split_once('x')?;
    Some((w.trim().parse().ok()?, h.trim().parse().ok()?))
}

/// Check the next `ev` of a stream before an encoder writes it: times non-decreasing (from `previous`,
/// the last time written) and at least `min_t`, coordinates below `xlim` × `ylim`. `seen` events came
/// before, so the error names the event's index in the whole stream.
#[allow(clippy::too_many_arguments)]
pub(crate) fn check_encodable(
    path: &str,
    format: &str,
    ev: EventsView<'_>,
    previous: Option<i64>,
    seen: u64,
    min_t: i64,
    xlim: u32,
    ylim: u32,
) -> Result<()> {
    let mut last = previous.unwrap_or(i64::MIN);
    let bad = (0..ev.len()).find(|&i| {
        let t = ev.t[i];
        let ok = t >= last && t >= min_t && u32::from(ev.x[i]) < xlim && u32::from(ev.y[i]) < ylim;
        last = t;
        !ok
    });
    let Some(i) = bad else { return Ok(()) };
    let (t, x, y) = (ev.t[i], ev.x[i], ev.y[i]);
    let message = if i > 0 && t < ev.t[i - 1] || i == 0 && previous.is_some_and(|q| t < q) {
        let q = if i > 0 { ev.t[i - 1] } else { previous.unwrap_or_default() };
        format!("time {t} µs is before the previous event's {q} µs: {format} needs time-sorted events (sort first)")
    } else if t < min_t {
        format!("time {t} µs is negative: {format} cannot store it (shift the times first)")
    } else {
        format!("({x}, {y}) does not fit {format}'s {xlim}x{ylim} coordinate range")
    };
    Err(Error::format(path, format!("event {}", seen + i as u64), message))
}

/// The header the encoders write: legacy `evt` line (old readers), `format` with geometry, `% end`.
pub(crate) fn write_raw_header(encoding: RawEncoding, width: u32, height: u32) -> Vec<u8> {
    let (evt, name) = match encoding {
        RawEncoding::Evt2 => ("2.0", "EVT2"),
        RawEncoding::Evt3 => ("3.0", "EVT3"),
    };
    format!(
        "% evt {evt}\n% format {name};height={height};width={width}\n% geometry {width}x{height}\n% end\n"
    )
    .into_bytes()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_without_end_stops_at_first_binary_line() {
        let mut data = b"% date 2021-01-01 10:00:00\r\n% evt 3.0\n% system_ID 49\n".to_vec();
        let offset = data.len();
        data.extend_from_slice(&[0x00, 0x80, 0x25, 0x20]);
        let h = parse_raw_header(&data, "f.raw").unwrap();
        assert_eq!(h.encoding, RawEncoding::Evt3);
        assert_eq!((h.width, h.height), (1280, 720));
        assert_eq!(h.data_offset, offset);
        assert_eq!(h.fields[0], ("date".to_string(), "2021-01-01 10:00:00".to_string()));
    }

    #[test]
    fn format_options_take_precedence_over_geometry() {
        let data = b"% evt 2.0\n% geometry 640x480\n% format EVT3;height=720;width=1280\n% end\n% x\n";
        let h = parse_raw_header(data, "f.raw").unwrap();
        assert_eq!(h.encoding, RawEncoding::Evt3);
        assert_eq!((h.width, h.height), (1280, 720));
        // `% end` ends the header even if the payload happens to start with "% ".
        assert_eq!(h.data_offset, data.len() - 4);
    }

    #[test]
    fn geometry_line_and_unknown_geometry() {
        let h = parse_raw_header(b"% evt 2.0\n% geometry 304x240\n", "f.raw").unwrap();
        assert_eq!((h.encoding, h.width, h.height), (RawEncoding::Evt2, 304, 240));
        let h = parse_raw_header(b"% evt 2.0\n", "f.raw").unwrap();
        assert_eq!((h.width, h.height), (0, 0));
    }

    #[test]
    fn bad_headers_name_the_file() {
        let e = parse_raw_header(b"% format EVT21;width=1\n", "a.raw").unwrap_err().to_string();
        assert!(e.contains("a.raw") && e.contains("EVT21"), "{e}");
        let e = parse_raw_header(b"% date x\n", "a.raw").unwrap_err().to_string();
        assert!(e.contains("encoding"), "{e}");
        let e = parse_raw_header(b"% evt 3.0\n% geom", "a.raw").unwrap_err().to_string();
        assert!(e.contains("byte offset 10"), "{e}");
        let e = parse_raw_header(b"% evt 3.0\n% geometry 3x\n", "a.raw").unwrap_err().to_string();
        assert!(e.contains("geometry"), "{e}");
    }

    #[test]
    fn written_header_parses_back() {
        let bytes = write_raw_header(RawEncoding::Evt2, 640, 480);
        let h = parse_raw_header(&bytes, "f.raw").unwrap();
        assert_eq!(
            (h.encoding, h.width, h.height, h.data_offset),
            (RawEncoding::Evt2, 640, 480, bytes.len())
        );
    }
}

/// Feeding helpers shared by the decoder tests: whole, and in pieces of `piece` bytes the way a
/// streaming reader does (keep the unconsumed tail, prepend it to the next piece).
#[cfg(test)]
pub(crate) mod feed {
    use crate::error::Result;
    use crate::events::{Decoder, Events};

    pub fn whole(dec: &mut impl Decoder, data: &[u8], offset: u64) -> Result<Events> {
        pieces(dec, data, offset, data.len().max(1))
    }

    pub fn pieces(dec: &mut impl Decoder, data: &[u8], offset: u64, piece: usize) -> Result<Events> {
        let mut out = Events::default();
        let mut pending = Vec::new();
        let mut pending_offset = offset;
        for chunk in data.chunks(piece) {
            pending.extend_from_slice(chunk);
            let used = dec.decode(&pending, pending_offset, &mut out)?;
            pending.drain(..used);
            pending_offset += used as u64;
        }
        dec.finish(&pending, pending_offset, &mut out)?;
        Ok(out)
    }

    /// `n` random events (xorshift, seeded) on a `width`×`height` sensor, times from `t_start` with
    /// steps uniform in `0..=max_step` µs.
    pub fn random_events(
        n: usize,
        seed: u64,
        t_start: i64,
        max_step: u64,
        width: u32,
        height: u32,
    ) -> Events {
        let mut s = seed.max(1);
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        let mut ev = Events::with_capacity(n, width, height);
        let mut t = t_start;
        for _ in 0..n {
            t += (next() % (max_step + 1)) as i64;
            let r = next();
            let p = if (r >> 40) & 1 == 1 { 1 } else { -1 };
            ev.push(t, (r % u64::from(width)) as u16, ((r >> 16) % u64::from(height)) as u16, p);
        }
        ev
    }
}

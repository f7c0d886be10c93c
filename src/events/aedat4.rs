//! iniVation AEDAT 4.0 decoder and encoder (LZ4 and ZSTD packets; EVENT_FORMATS.md §4).
//!
//! A file is a magic line, a size-prefixed IOHeader FlatBuffer (compression, where the packet area
//! ends, an XML description of the streams), then packets `(i32 stream id, i32 size, payload)` of
//! interleaved streams up to the FileDataTable. Event packets decompress to an `EventPacket`
//! FlatBuffer holding a vector of 16-byte structs. Buffers are only byte-aligned, so every field is
//! read with `from_le_bytes` through bounds-checked slices; packets decompress in parallel and are
//! appended in file order.

use std::io::Read;

use rayon::prelude::*;

use super::raw_header::{check_encodable, DecodeStats};
use super::{ColumnsMut, Decoder, Events, EventsView};
use crate::error::{Error, Result};

const MAGIC: &[u8; 14] = b"#!AER-DAT4.0\r\n";
const LZ4_MAGIC: [u8; 4] = [0x04, 0x22, 0x4D, 0x18];
/// Bytes of one `Event` struct: i64 t, i16 x, i16 y, bool on, 3 padding.
const EVENT_SIZE: usize = 16;

/// Packet payload compression named by the IOHeader.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Aedat4Compression {
    None,
    Lz4,
    Zstd,
}

/// What the IOHeader says: compression, where the packets end, and the event stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Aedat4Header {
    pub compression: Aedat4Compression,
    /// Absolute offset of the FileDataTable (where packets end), or −1 (read to end of file).
    pub data_table_position: i64,
    /// Sensor size from the event stream's `sizeX`/`sizeY`; 0 when the XML has none.
    pub width: u32,
    pub height: u32,
    pub event_stream_id: i32,
    /// Absolute offset of the first packet.
    pub data_offset: usize,
}

// ---- FlatBuffer walk (bounds-checked; errors are messages the caller places in the file) ----

type Walk<T> = std::result::Result<T, String>;

fn bytes<const N: usize>(b: &[u8], at: usize) -> Walk<[u8; N]> {
    at.checked_add(N)
        .and_then(|end| b.get(at..end))
        .map(|s| s.try_into().unwrap())
        .ok_or_else(|| format!("FlatBuffer offset {at} is outside the {}-byte buffer", b.len()))
}

fn u16_at(b: &[u8], at: usize) -> Walk<usize> {
    Ok(u16::from_le_bytes(bytes(b, at)?) as usize)
}

fn u32_at(b: &[u8], at: usize) -> Walk<usize> {
    Ok(u32::from_le_bytes(bytes(b, at)?) as usize)
}

/// Follow the uoffset stored at `at` (vector, string or table reference).
fn follow(b: &[u8], at: usize) -> Walk<usize> {
    Ok(at + u32_at(b, at)?)
}

/// The root table of a buffer (after its size prefix), checking the 4-byte file identifier.
fn root(b: &[u8], identifier: &[u8; 4]) -> Walk<usize> {
    let found: [u8; 4] = bytes(b, 4)?;
    if &found != identifier {
        return Err(format!(
            "FlatBuffer identifier is {:?}, expected {:?}",
            String::from_utf8_lossy(&found),
            String::from_utf8_lossy(identifier)
        ));
    }
    follow(b, 0)
}

/// Position of field `k` of the table at `table`, or `None` when the vtable marks it absent.
fn field(b: &[u8], table: usize, k: usize) -> Walk<Option<usize>> {
    // The soffset is signed and subtracted: the vtable may sit before or after its table.
    let soffset = i32::from_le_bytes(bytes(b, table)?);
    let vt = usize::try_from(table as i64 - i64::from(soffset))
        .map_err(|_| format!("vtable before buffer start (soffset {soffset})"))?;
    let slot = 4 + 2 * k;
    if slot >= u16_at(b, vt)? {
        return Ok(None);
    }
    let off = u16_at(b, vt + slot)?;
    Ok((off != 0).then_some(table + off))
}

/// A vector field as (position of the first element, count); an absent vector is empty.
fn vector(b: &[u8], table: usize, k: usize) -> Walk<(usize, usize)> {
    match field(b, table, k)? {
        None => Ok((0, 0)),
        Some(f) => {
            let v = follow(b, f)?;
            Ok((v + 4, u32_at(b, v)?))
        }
    }
}

// ---- IOHeader ----

/// Parse the magic and IOHeader at the start of `data` (the file's first bytes).
pub fn parse_aedat4_header(data: &[u8], path: &str) -> Result<Aedat4Header> {
    if !data.starts_with(MAGIC) {
        return Err(Error::format(path, "byte offset 0", "not an AEDAT 4.0 file (no `#!AER-DAT4.0` magic)"));
    }
    let err = |m: String| Error::format(path, "IOHeader at byte offset 18", m);
    let size = u32_at(data, 14)
        .map_err(|_| Error::format(path, "byte offset 14", "file ends inside the IOHeader size"))?;
    let Some(b) = data.get(18..18 + size) else {
        return Err(err(format!("file ends inside the {size}-byte IOHeader")));
    };
    let t = root(b, b"IOHE").map_err(err)?;
    let compression = match field(b, t, 0).map_err(err)? {
        None => 0,
        Some(f) => i32::from_le_bytes(bytes(b, f).map_err(err)?),
    };
    let compression = match compression {
        0 => Aedat4Compression::None,
        1 | 2 => Aedat4Compression::Lz4,
        3 | 4 => Aedat4Compression::Zstd,
        c => return Err(err(format!("unknown compression {c} (0 to 4 are defined)"))),
    };
    let data_table_position = match field(b, t, 1).map_err(err)? {
        None => -1,
        Some(f) => i64::from_le_bytes(bytes(b, f).map_err(err)?),
    };
    let Some(info) = field(b, t, 2).map_err(err)? else {
        return Err(err("no infoNode (stream description)".into()));
    };
    let s = follow(b, info).map_err(err)?;
    let len = u32_at(b, s).map_err(err)?;
    let xml =
        b.get(s + 4..s + 4 + len).ok_or_else(|| err("infoNode string runs past the IOHeader".into()))?;
    let xml = std::str::from_utf8(xml).map_err(|_| err("infoNode is not UTF-8".into()))?;
    let (event_stream_id, width, height) = event_stream(xml).map_err(|m| err(format!("infoNode: {m}")))?;
    Ok(Aedat4Header {
        compression,
        data_table_position,
        width,
        height,
        event_stream_id,
        data_offset: 18 + size,
    })
}

/// The value of `name="…"` inside a tag.
fn xml_attr<'a>(tag: &'a str, name: &str) -> Option<&'a str> {
    let start = tag.find(&format!(" {name}=\""))? + name.len() + 3;
    Some(&tag[start..start + tag[start..].find('"')?])
}

/// (ID, sizeX, sizeY) of the first stream whose `typeIdentifier` is `EVTS`.
///
/// The XML is `<dv><node name="outInfo"><node name="ID">` with `<attr key=…>` entries and a child
/// `<node name="info">` holding `sizeX`/`sizeY`; a small tag scanner is enough for it.
fn event_stream(xml: &str) -> Walk<(i32, u32, u32)> {
    // Per stream ID in document order: [typeIdentifier, sizeX, sizeY].
    let mut streams: Vec<(&str, [Option<&str>; 3])> = Vec::new();
    let mut path: Vec<&str> = Vec::new();
    let mut pos = 0;
    while let Some(lt) = xml[pos..].find('<') {
        let start = pos + lt;
        if xml[start..].starts_with("<!--") {
            pos = start + xml[start..].find("-->").ok_or("unterminated comment")? + 3;
            continue;
        }
        let end = start + xml[start..].find('>').ok_or("unterminated tag")?;
        let tag = &xml[start + 1..end];
        pos = end + 1;
        if tag.starts_with("/node") {
            path.pop();
        } else if tag.starts_with("node") && !tag.ends_with('/') {
            path.push(xml_attr(tag, "name").unwrap_or(""));
        } else if tag.starts_with("attr") {
            let key = xml_attr(tag, "key").unwrap_or("");
            let value =
                if tag.ends_with('/') { "" } else { xml[pos..].split('<').next().unwrap_or("").trim() };
            let n = path.len();
            let (id, in_info) = match path.iter().rposition(|&p| p == "outInfo") {
                Some(i) if i + 2 == n => (path[n - 1], false),
                Some(i) if i + 3 == n && path[n - 1] == "info" => (path[n - 2], true),
                _ => continue,
            };
            let slot = match (in_info, key) {
                (false, "typeIdentifier") => 0,
                (true, "sizeX") => 1,
                (true, "sizeY") => 2,
                _ => continue,
            };
            let k = streams.iter().position(|s| s.0 == id).unwrap_or_else(|| {
                streams.push((id, [None; 3]));
                streams.len() - 1
            });
            streams[k].1[slot] = Some(value);
        }
    }
    let (id, [_, sx, sy]) =
        streams.iter().find(|s| s.1[0] == Some("EVTS")).ok_or("no stream with typeIdentifier EVTS")?;
    let id = id.parse::<i32>().map_err(|_| format!("stream ID `{id}` is not a number"))?;
    let size = |v: &Option<&str>, name: &str| -> Walk<u32> {
        v.map_or(Ok(0), |s| s.parse().map_err(|_| format!("{name} `{s}` is not a number")))
    };
    Ok((id, size(sx, "sizeX")?, size(sy, "sizeY")?))
}

// ---- Packets ----

/// Streaming AEDAT 4.0 decoder; fed the bytes from `data_offset` on.
#[derive(Debug, Clone)]
pub struct Aedat4Decoder {
    path: String,
    compression: Aedat4Compression,
    data_table_position: i64,
    stream: i32,
    width: u32,
    height: u32,
    /// Reached the FileDataTable: everything after it is ignored.
    done: bool,
    stats: DecodeStats,
}

/// Offset of the first `Event` struct in a size-prefixed packet laid out as DV (and evgs) write it:
/// size prefix, root offset, identifier, vtable, table, vector length.
const DV_EVENTS_START: usize = 32;

/// Per-worker decompression state, reused across packets so that decoding a packet allocates
/// nothing and its output stays in cache until it is copied into the columns.
#[derive(Default)]
struct Scratch {
    buf: Vec<u8>,
    zstd: Option<zstd::bulk::Decompressor<'static>>,
}

impl Aedat4Decoder {
    pub fn new(path: &str, header: &Aedat4Header) -> Self {
        Aedat4Decoder {
            path: path.to_string(),
            compression: header.compression,
            data_table_position: header.data_table_position,
            stream: header.event_stream_id,
            width: header.width,
            height: header.height,
            done: false,
            stats: DecodeStats::default(),
        }
    }

    /// What was skipped so far (packets of other streams).
    pub fn stats(&self) -> DecodeStats {
        self.stats
    }

    fn packet_error(&self, offset: u64, message: impl Into<String>) -> Error {
        Error::format(&self.path, format!("byte offset {offset} (event packet)"), message)
    }

    /// Decompress one event packet payload (into `scratch` unless stored uncompressed) and return
    /// the bytes of its `Event` structs.
    fn unpack<'a>(&self, offset: u64, payload: &'a [u8], scratch: &'a mut Scratch) -> Result<&'a [u8]> {
        let err = |m| self.packet_error(offset, m);
        let buf: &[u8] = match self.compression {
            Aedat4Compression::None => payload,
            Aedat4Compression::Lz4 => {
                let n = lz4_decompress(payload, &mut scratch.buf).map_err(err)?;
                &scratch.buf[..n]
            }
            Aedat4Compression::Zstd => {
                zstd_decompress(payload, &mut scratch.zstd, &mut scratch.buf).map_err(err)?;
                &scratch.buf
            }
        };
        let (start, count) = event_structs(buf).map_err(err)?;
        Ok(&buf[start..start + EVENT_SIZE * count])
    }

    /// The event count of a packet as told by its compressed frame's content size, assuming DV's
    /// packet layout; `None` when the frame does not say (the count is then known only after
    /// decompressing).
    fn expected_count(&self, payload: &[u8]) -> Option<usize> {
        let size = match self.compression {
            Aedat4Compression::None => return event_structs(payload).ok().map(|(_, n)| n),
            Aedat4Compression::Lz4 => {
                let has_size =
                    payload.starts_with(&LZ4_MAGIC) && payload.get(4).is_some_and(|f| f & 0x08 != 0);
                u64::from_le_bytes(bytes(payload, 6).ok().filter(|_| has_size)?)
            }
            Aedat4Compression::Zstd => zstd::zstd_safe::get_frame_content_size(payload).ok()??,
        };
        let body = usize::try_from(size).ok()?.checked_sub(DV_EVENTS_START)?;
        (body % EVENT_SIZE == 0).then_some(body / EVENT_SIZE)
    }

    /// Copy a packet's `Event` structs into the column slices, checking coordinates. The loop is
    /// branch-free (a bad coordinate only sets a flag); the offending event is looked up afterwards.
    fn fill(&self, offset: u64, structs: &[u8], out: ColumnsMut<'_>) -> Result<()> {
        let ColumnsMut { t, x, y, p: pol } = out;
        // Every slot is written: `unpack_all` relies on this to append them.
        assert_eq!(structs.len(), EVENT_SIZE * t.len(), "AEDAT 4 packet and slots disagree");
        // Coordinates are i16; seen as u16 a negative one is ≥ 2^15, so one unsigned compare suffices.
        let xlim = if self.width == 0 { 1 << 15 } else { self.width };
        let ylim = if self.height == 0 { 1 << 15 } else { self.height };
        let coords = |e: &[u8]| (u16::from_le_bytes([e[8], e[9]]), u16::from_le_bytes([e[10], e[11]]));
        let mut bad = false;
        for ((e, t), ((x, y), pol)) in
            structs.chunks_exact(EVENT_SIZE).zip(t).zip(x.iter_mut().zip(y.iter_mut()).zip(pol.iter_mut()))
        {
            let (ex, ey) = coords(e);
            bad |= (u32::from(ex) >= xlim) | (u32::from(ey) >= ylim);
            t.write(i64::from_le_bytes(e[0..8].try_into().unwrap()));
            x.write(ex);
            y.write(ey);
            pol.write(if e[12] != 0 { 1 } else { -1 });
        }
        if !bad {
            return Ok(());
        }
        let (j, (ex, ey)) = structs
            .chunks_exact(EVENT_SIZE)
            .map(coords)
            .map(|(ex, ey)| (ex as i16, ey as i16))
            .enumerate()
            .find(|&(_, (ex, ey))| ex < 0 || ey < 0 || ex as u32 >= xlim || ey as u32 >= ylim)
            .expect("a flagged coordinate exists");
        Err(self.packet_error(
            offset,
            format!("event {j}: ({ex}, {ey}) outside the {}x{} sensor", self.width, self.height),
        ))
    }
}

/// Check the size prefix and identifier of a decompressed `EventPacket` and find its elements.
fn event_structs(buf: &[u8]) -> Walk<(usize, usize)> {
    let prefix = u32_at(buf, 0)?;
    if prefix + 4 != buf.len() {
        return Err(format!(
            "size prefix {prefix} does not match the {}-byte decompressed packet",
            buf.len()
        ));
    }
    let b = &buf[4..];
    let table = root(b, b"EVTS")?;
    let (start, count) = vector(b, table, 0)?;
    if count.checked_mul(EVENT_SIZE).and_then(|n| n.checked_add(start)).is_none_or(|end| end > b.len()) {
        return Err(format!("{count} events do not fit the {}-byte packet", buf.len()));
    }
    Ok((start + 4, count))
}

/// Decompress one LZ4 frame (LZ4 Frame Format 1.6.x), each block straight into the output: linked
/// blocks (DV's default) see the previous 64 KiB of output as their dictionary. Checksums are not
/// verified (DV writes none); corrupt block data still fails the bounds-checked block decoder.
/// Returns the decompressed length: the frame is `out[..length]` (`out` only grows, so a reused
/// buffer is zeroed once, not per packet).
fn lz4_decompress(p: &[u8], out: &mut Vec<u8>) -> Walk<usize> {
    let bad = |m: &str| format!("bad LZ4 frame: {m}");
    if !p.starts_with(&LZ4_MAGIC) {
        return Err(bad("no frame magic"));
    }
    let [flg, bd] = bytes::<2>(p, 4).map_err(|_| bad("truncated header"))?;
    if flg >> 6 != 1 {
        return Err(bad("unsupported version"));
    }
    let max_block = match (bd >> 4) & 7 {
        4 => 64 << 10,
        5 => 256 << 10,
        6 => 1 << 20,
        7 => 4 << 20,
        _ => return Err(bad("invalid block maximum size")),
    };
    let (linked, block_checksum) = (flg & 0x20 == 0, flg & 0x10 != 0);
    let mut pos = 6;
    let content_size = if flg & 0x08 != 0 {
        pos += 8;
        Some(u64::from_le_bytes(bytes(p, 6).map_err(|_| bad("truncated header"))?) as usize)
    } else {
        None
    };
    pos += 1 + if flg & 0x01 != 0 { 4 } else { 0 }; // dictionary id, header checksum
                                                    // `out` is a reused buffer: it only grows (zeroed once), and `filled` bytes of it are this frame's.
    let mut filled = 0;
    let room = |out: &mut Vec<u8>, need: usize| {
        if out.len() < need {
            out.resize(need, 0);
        }
    };
    loop {
        let word = u32::from_le_bytes(bytes(p, pos).map_err(|_| bad("truncated block"))?);
        pos += 4;
        if word == 0 {
            break;
        }
        let len = (word & 0x7FFF_FFFF) as usize;
        let block = p.get(pos..pos + len).ok_or_else(|| bad("truncated block"))?;
        pos += len + if block_checksum { 4 } else { 0 };
        if word & 0x8000_0000 != 0 {
            room(out, filled + block.len());
            out[filled..filled + block.len()].copy_from_slice(block);
            filled += block.len();
            continue;
        }
        // A block decodes to at most `max_block` bytes (and no more than the content size says).
        let limit = content_size.map_or(max_block, |n| n.saturating_sub(filled).min(max_block));
        room(out, filled + limit);
        let (previous, rest) = out.split_at_mut(filled);
        let rest = &mut rest[..limit];
        let written = if linked {
            let dict = &previous[filled.saturating_sub(64 << 10)..];
            lz4_flex::block::decompress_into_with_dict(block, rest, dict)
        } else {
            lz4_flex::block::decompress_into(block, rest)
        };
        filled += written.map_err(|e| bad(&e.to_string()))?;
    }
    if content_size.is_some_and(|n| n != filled) {
        return Err(bad("content size does not match the data"));
    }
    Ok(filled)
}

/// Decompress one zstd frame. With a plausible content size in the frame header (DV always writes it)
/// the frame decodes straight into an exactly sized buffer; otherwise it streams, so a corrupt size
/// field cannot request a huge allocation.
fn zstd_decompress(
    payload: &[u8],
    context: &mut Option<zstd::bulk::Decompressor<'static>>,
    out: &mut Vec<u8>,
) -> Walk<()> {
    let bad = |e: &dyn std::fmt::Display| format!("bad ZSTD frame: {e}");
    let plausible = (payload.len() as u64).saturating_mul(256).max(1 << 20);
    out.clear();
    match zstd::zstd_safe::get_frame_content_size(payload) {
        Ok(Some(size)) if size <= plausible => {
            let context = match context {
                Some(c) => c,
                None => context.insert(zstd::bulk::Decompressor::new().map_err(|e| bad(&e))?),
            };
            out.reserve(size as usize);
            context.decompress_to_buffer(payload, out).map_err(|e| bad(&e))?;
        }
        _ => {
            zstd::stream::read::Decoder::with_buffer(payload)
                .and_then(|mut d| d.read_to_end(out))
                .map_err(|e| bad(&e))?;
        }
    }
    Ok(())
}

impl Aedat4Decoder {
    /// Decode `packets` (file offset, payload) in parallel, appending their events in file order;
    /// the error is the first in file order.
    ///
    /// When every frame header gives the event count (DV's layout), each packet decompresses into
    /// its worker's scratch buffer and is copied straight to its final place. Otherwise (or if a
    /// count turns out different) the packets decompress into buffers of their own first.
    fn unpack_all(&self, packets: &[(u64, &[u8])], out: &mut Events) -> Result<()> {
        let counts: Option<Vec<usize>> = packets.iter().map(|&(_, p)| self.expected_count(p)).collect();
        if let Some(counts) = counts {
            let total = counts.iter().sum();
            let parts = out.spare_parts(counts);
            let done: Vec<Result<bool>> = packets
                .par_iter()
                .zip(parts)
                .map_init(Scratch::default, |scratch, (&(at, payload), part)| {
                    let structs = self.unpack(at, payload, scratch)?;
                    if structs.len() != EVENT_SIZE * part.t.len() {
                        return Ok(false);
                    }
                    self.fill(at, structs, part).map(|()| true)
                })
                .collect();
            match done.into_iter().find(|r| !matches!(r, Ok(true))) {
                None => {
                    // SAFETY: every packet filled its part whole (`fill` asserts it).
                    unsafe { out.assume_filled(total) };
                    return Ok(());
                }
                Some(Err(e)) => return Err(e),
                Some(Ok(_)) => {}
            }
        }
        let unpacked: Vec<Result<Vec<u8>>> = packets
            .par_iter()
            .map_init(Scratch::default, |scratch, &(at, payload)| {
                self.unpack(at, payload, scratch).map(<[u8]>::to_vec)
            })
            .collect();
        let ok = unpacked.iter().take_while(|r| r.is_ok()).count();
        let structs: Vec<&[u8]> = unpacked[..ok].iter().flatten().map(Vec::as_slice).collect();
        let total = structs.iter().map(|s| s.len() / EVENT_SIZE).sum();
        let parts = out.spare_parts(structs.iter().map(|s| s.len() / EVENT_SIZE));
        let filled: Vec<Result<()>> = structs
            .par_iter()
            .zip(packets)
            .zip(parts)
            .map(|((s, &(at, _)), part)| self.fill(at, s, part))
            .collect();
        let first_error = filled.into_iter().find_map(|r| r.err());
        if let Some(e) = first_error.or_else(|| unpacked.into_iter().nth(ok).and_then(|r| r.err())) {
            return Err(e);
        }
        // SAFETY: every packet filled its part whole (`fill` asserts it).
        unsafe { out.assume_filled(total) };
        Ok(())
    }
}

impl Decoder for Aedat4Decoder {
    /// Consumes whole packets only; a packet larger than `data` consumes nothing, so the caller must
    /// feed a bigger piece. Once at `data_table_position`, everything is consumed and ignored.
    fn decode(&mut self, data: &[u8], offset: u64, out: &mut Events) -> Result<usize> {
        if out.width == 0 && out.height == 0 {
            (out.width, out.height) = (self.width, self.height);
        }
        let table = u64::try_from(self.data_table_position).ok();
        let mut pos = 0;
        let mut packets = Vec::new();
        while !self.done {
            let at = offset + pos as u64;
            if table.is_some_and(|table| at >= table) {
                self.done = true;
                break;
            }
            let Ok(head) = bytes::<8>(&data[pos..], 0) else { break };
            let id = i32::from_le_bytes(head[0..4].try_into().unwrap());
            let size = i32::from_le_bytes(head[4..8].try_into().unwrap());
            let end = at
                + 8
                + u64::try_from(size).map_err(|_| {
                    Error::format(
                        &self.path,
                        format!("byte offset {at}"),
                        format!("negative packet size {size}"),
                    )
                })?;
            if let Some(table) = table.filter(|&table| end > table) {
                return Err(Error::format(
                    &self.path,
                    format!("byte offset {at}"),
                    format!("packet of {size} bytes runs past the FileDataTable at byte offset {table}"),
                ));
            }
            let end = (end - offset) as usize;
            if end > data.len() {
                break;
            }
            if id == self.stream {
                packets.push((at, &data[pos + 8..end]));
            } else {
                self.stats.skipped_packets += 1;
            }
            pos = end;
        }
        self.unpack_all(&packets, out)?;
        Ok(if self.done { data.len() } else { pos })
    }

    /// A partial packet at end of file, or a file ending before `data_table_position`, is an error.
    fn finish(&mut self, tail: &[u8], offset: u64, out: &mut Events) -> Result<()> {
        let used = self.decode(tail, offset, out)?;
        let end = offset + tail.len() as u64;
        if used < tail.len() {
            let at = offset + used as u64;
            return Err(Error::format(
                &self.path,
                format!("byte offset {at}"),
                format!("truncated packet: the file ends {} bytes later", end - at),
            ));
        }
        if !self.done && self.data_table_position >= 0 && end < self.data_table_position as u64 {
            return Err(Error::format(
                &self.path,
                format!("byte offset {end}"),
                format!("file ends before its data table at byte offset {}", self.data_table_position),
            ));
        }
        Ok(())
    }
}

// ---- Encoder ----

/// Byte offset of the `dataTablePosition` field in the header [`Aedat4Encoder`] writes: the writer
/// patches it once the table's position is known.
pub const DATA_TABLE_FIELD: u64 = 18 + 32;

/// Streaming AEDAT 4.0 encoder: one event stream (ID 0), `events_per_packet` events per packet, each
/// compressed (in parallel) as one LZ4 frame (linked blocks, as DV writes) or one ZSTD frame (with
/// its content size, which DV requires), then a FileDataTable. The file is [`Aedat4Encoder::header`],
/// the bytes of every [`Aedat4Encoder::encode`], those of [`Aedat4Encoder::finish`], and the table
/// position it returns written at [`DATA_TABLE_FIELD`].
#[derive(Debug, Clone)]
pub struct Aedat4Encoder {
    path: String,
    compression: Aedat4Compression,
    events_per_packet: usize,
    xlim: u32,
    ylim: u32,
    header: Vec<u8>,
    /// Events of a partial packet, carried into the next batch.
    carry: Events,
    table: Vec<TableEntry>,
    /// Bytes produced so far (header included): the file offset of the next byte.
    written: u64,
    last_t: Option<i64>,
    seen: u64,
}

impl Aedat4Encoder {
    /// `path` names the output in errors; coordinates must fit the sensor (`width`/`height`, 0 =
    /// unknown) and i16. Errors if `events_per_packet` is 0.
    pub fn new(
        path: &str,
        width: u32,
        height: u32,
        compression: Aedat4Compression,
        events_per_packet: usize,
    ) -> Result<Self> {
        if events_per_packet == 0 {
            return Err(Error::Invalid(format!("{path}: AEDAT 4 events_per_packet must be positive")));
        }
        let io = io_header(compression, &info_xml(width, height, compression));
        let mut header = MAGIC.to_vec();
        header.extend_from_slice(&(io.len() as u32).to_le_bytes());
        header.extend_from_slice(&io);
        let lim = |n: u32| if n == 0 { 1 << 15 } else { n.min(1 << 15) };
        Ok(Aedat4Encoder {
            path: path.into(),
            compression,
            events_per_packet,
            xlim: lim(width),
            ylim: lim(height),
            written: header.len() as u64,
            header,
            carry: Events::default(),
            table: Vec::new(),
            last_t: None,
            seen: 0,
        })
    }

    /// The magic and IOHeader, with `dataTablePosition` −1 until patched.
    pub fn header(&self) -> &[u8] {
        &self.header
    }

    /// Append the packets completed by the stream's next events to `out` (a partial packet waits for
    /// the next batch). Unsorted times and coordinates that do not fit are errors naming the event's
    /// index in the stream (nothing of the batch is written then).
    pub fn encode(&mut self, ev: EventsView<'_>, out: &mut Vec<u8>) -> Result<()> {
        check_encodable(&self.path, "AEDAT 4", ev, self.last_t, self.seen, i64::MIN, self.xlim, self.ylim)?;
        self.last_t = ev.t.last().copied().or(self.last_t);
        self.seen += ev.len() as u64;
        // Packets are cut from the carried events followed by this batch.
        let mut joined = std::mem::take(&mut self.carry);
        let all = if joined.is_empty() {
            ev
        } else {
            extend_from_view(&mut joined, ev);
            joined.view()
        };
        let full = all.len() / self.events_per_packet * self.events_per_packet;
        self.write_packets(all, full, out);
        extend_from_view(&mut self.carry, slice_view(all, full, all.len()));
        Ok(())
    }

    /// Append the last partial packet and the FileDataTable to `out`; returns the table's file
    /// offset, to be written at [`DATA_TABLE_FIELD`].
    pub fn finish(&mut self, out: &mut Vec<u8>) -> u64 {
        let carry = std::mem::take(&mut self.carry);
        self.write_packets(carry.view(), carry.len(), out);
        let position = self.written;
        let table = compress(&data_table(&self.table), self.compression);
        self.written += table.len() as u64;
        out.extend_from_slice(&table);
        position
    }

    /// Compress events `0..n` of `ev` as packets (in parallel) and append them to `out`.
    fn write_packets(&mut self, ev: EventsView<'_>, n: usize, out: &mut Vec<u8>) {
        let per = self.events_per_packet;
        let starts: Vec<usize> = (0..n).step_by(per).collect();
        let payloads: Vec<Vec<u8>> = starts
            .par_iter()
            .map(|&s| compress(&event_packet(ev, s, (s + per).min(n)), self.compression))
            .collect();
        for (&s, payload) in starts.iter().zip(&payloads) {
            let e = (s + per).min(n);
            self.table.push(TableEntry {
                offset: self.written + 8,
                size: payload.len(),
                count: e - s,
                t0: ev.t[s],
                t1: ev.t[e - 1],
            });
            out.extend_from_slice(&0i32.to_le_bytes());
            out.extend_from_slice(&(payload.len() as i32).to_le_bytes());
            out.extend_from_slice(payload);
            self.written += 8 + payload.len() as u64;
        }
    }
}

fn slice_view<'a>(ev: EventsView<'a>, from: usize, to: usize) -> EventsView<'a> {
    EventsView { t: &ev.t[from..to], x: &ev.x[from..to], y: &ev.y[from..to], p: &ev.p[from..to], ..ev }
}

fn extend_from_view(e: &mut Events, v: EventsView<'_>) {
    e.t.extend_from_slice(v.t);
    e.x.extend_from_slice(v.x);
    e.y.extend_from_slice(v.y);
    e.p.extend_from_slice(v.p);
}

/// A complete AEDAT 4.0 file for the events (see [`Aedat4Encoder`]).
pub fn encode_aedat4(
    ev: EventsView<'_>,
    compression: Aedat4Compression,
    events_per_packet: usize,
) -> Result<Vec<u8>> {
    let mut enc = Aedat4Encoder::new("memory", ev.width, ev.height, compression, events_per_packet)?;
    let mut out = enc.header().to_vec();
    enc.encode(ev, &mut out)?;
    let position = enc.finish(&mut out);
    let field = DATA_TABLE_FIELD as usize;
    out[field..field + 8].copy_from_slice(&(position as i64).to_le_bytes());
    Ok(out)
}

fn info_xml(width: u32, height: u32, compression: Aedat4Compression) -> String {
    let compression = match compression {
        Aedat4Compression::None => "NONE",
        Aedat4Compression::Lz4 => "LZ4",
        Aedat4Compression::Zstd => "ZSTD",
    };
    format!(
        r#"<dv version="2.0">
    <node name="outInfo" path="/outInfo/">
        <node name="0" path="/outInfo/0/">
            <attr key="compression" type="string">{compression}</attr>
            <attr key="originalModuleName" type="string">evgs</attr>
            <attr key="originalOutputName" type="string">events</attr>
            <attr key="typeDescription" type="string">Array of events (polarity ON/OFF).</attr>
            <attr key="typeIdentifier" type="string">EVTS</attr>
            <node name="info" path="/outInfo/0/info/">
                <attr key="sizeX" type="int">{width}</attr>
                <attr key="sizeY" type="int">{height}</attr>
                <attr key="source" type="string">evgs</attr>
                <attr key="tsOffset" type="long">0</attr>
            </node>
        </node>
    </node>
</dv>
"#
    )
}

/// IOHeader FlatBuffer (without size prefix): vtable at 8, table at 24 with compression (i32) at 28,
/// dataTablePosition (i64, −1 until patched) at 32 and the infoNode string reference at 40.
fn io_header(compression: Aedat4Compression, xml: &str) -> Vec<u8> {
    let code: i32 = match compression {
        Aedat4Compression::None => 0,
        Aedat4Compression::Lz4 => 1,
        Aedat4Compression::Zstd => 3,
    };
    let mut b = Vec::with_capacity(48 + xml.len());
    b.extend_from_slice(&24u32.to_le_bytes());
    b.extend_from_slice(b"IOHE");
    for v in [10u16, 20, 4, 8, 16] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b.resize(24, 0);
    b.extend_from_slice(&16i32.to_le_bytes());
    b.extend_from_slice(&code.to_le_bytes());
    b.extend_from_slice(&(-1i64).to_le_bytes());
    b.extend_from_slice(&4u32.to_le_bytes());
    b.extend_from_slice(&(xml.len() as u32).to_le_bytes());
    b.extend_from_slice(xml.as_bytes());
    b.push(0);
    b.resize(b.len().next_multiple_of(4), 0);
    b
}

/// Size-prefixed `EventPacket` for events `s..e`, laid out as DV does: root table at 16, vtable at 10,
/// the element vector at 24 and the 16-byte structs from 28.
fn event_packet(ev: EventsView<'_>, s: usize, e: usize) -> Vec<u8> {
    let n = e - s;
    let mut b = Vec::with_capacity(32 + EVENT_SIZE * n);
    b.extend_from_slice(&((28 + EVENT_SIZE * n) as u32).to_le_bytes());
    b.extend_from_slice(&16u32.to_le_bytes());
    b.extend_from_slice(b"EVTS");
    b.extend_from_slice(&[0, 0, 6, 0, 8, 0, 4, 0]);
    b.extend_from_slice(&6i32.to_le_bytes());
    b.extend_from_slice(&4u32.to_le_bytes());
    b.extend_from_slice(&(n as u32).to_le_bytes());
    for i in s..e {
        // Checked by the encoder: coordinates are below 2^15.
        let (x, y) = (ev.x[i] as i16, ev.y[i] as i16);
        b.extend_from_slice(&ev.t[i].to_le_bytes());
        b.extend_from_slice(&x.to_le_bytes());
        b.extend_from_slice(&y.to_le_bytes());
        b.extend_from_slice(&[u8::from(ev.p[i] > 0), 0, 0, 0]);
    }
    b
}

/// One FileDataTable row: where a packet's payload is and what it holds.
#[derive(Debug, Clone)]
struct TableEntry {
    offset: u64,
    size: usize,
    count: usize,
    t0: i64,
    t1: i64,
}

/// Size-prefixed `FileDataTable` (identifier `FTAB`): a vector of tables sharing one vtable, each
/// ByteOffset, PacketInfo{StreamID, Size}, NumElements, TimestampStart, TimestampEnd.
fn data_table(entries: &[TableEntry]) -> Vec<u8> {
    let n = entries.len();
    let vtable = 28 + 4 * n;
    let first = (vtable + 14).next_multiple_of(8);
    let mut b = Vec::with_capacity(first + 48 * n + 4);
    b.extend_from_slice(&16u32.to_le_bytes());
    b.extend_from_slice(b"FTAB");
    b.extend_from_slice(&[0, 0, 6, 0, 8, 0, 4, 0]);
    b.extend_from_slice(&6i32.to_le_bytes());
    b.extend_from_slice(&4u32.to_le_bytes());
    b.extend_from_slice(&(n as u32).to_le_bytes());
    for k in 0..n {
        b.extend_from_slice(&((first + 48 * k - (28 + 4 * k)) as u32).to_le_bytes());
    }
    for v in [14u16, 48, 8, 16, 24, 32, 40] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b.resize(first, 0);
    for (k, e) in entries.iter().enumerate() {
        b.extend_from_slice(&((first + 48 * k - vtable) as i32).to_le_bytes());
        b.extend_from_slice(&[0; 4]);
        b.extend_from_slice(&(e.offset as i64).to_le_bytes());
        b.extend_from_slice(&0i32.to_le_bytes());
        b.extend_from_slice(&(e.size as i32).to_le_bytes());
        b.extend_from_slice(&(e.count as i64).to_le_bytes());
        b.extend_from_slice(&e.t0.to_le_bytes());
        b.extend_from_slice(&e.t1.to_le_bytes());
    }
    let mut out = (b.len() as u32).to_le_bytes().to_vec();
    out.extend_from_slice(&b);
    out
}

fn compress(buf: &[u8], compression: Aedat4Compression) -> Vec<u8> {
    match compression {
        Aedat4Compression::None => buf.to_vec(),
        Aedat4Compression::Lz4 => {
            use lz4_flex::frame::{BlockMode, FrameEncoder, FrameInfo};
            use std::io::Write;
            let info = FrameInfo::new().content_size(Some(buf.len() as u64)).block_mode(BlockMode::Linked);
            let mut enc = FrameEncoder::with_frame_info(info, Vec::with_capacity(buf.len() / 2));
            enc.write_all(buf).expect("writing to a Vec cannot fail");
            enc.finish().expect("writing to a Vec cannot fail")
        }
        // libzstd writes the content size into the frame header, which DV requires.
        Aedat4Compression::Zstd => zstd::bulk::compress(buf, 1).expect("compressing into a Vec cannot fail"),
    }
}

#[cfg(test)]
mod tests {
    use super::super::raw_header::feed;
    use super::*;

    type Ev = (i64, i16, i16, bool);

    const XML: &str = r#"<dv version="2.0">
 <node name="outInfo" path="/outInfo/">
  <node name="0" path="/outInfo/0/">
   <attr key="typeIdentifier" type="string">IMUS</attr>
  </node>
  <node name="2" path="/outInfo/2/">
   <attr key="typeIdentifier" type="string">FRME</attr>
   <node name="info" path="/outInfo/2/info/"><attr key="sizeX" type="int">99</attr></node>
  </node>
  <!-- a <node> inside a comment -->
  <node name="3" path="/outInfo/3/">
   <attr key="compression" type="string">LZ4</attr>
   <attr key="typeIdentifier" type="string">EVTS</attr>
   <node name="info" path="/outInfo/3/info/">
    <attr key="sizeX" type="int">64</attr>
    <attr key="sizeY" type="int">48</attr>
    <attr key="source" type="string">DVXplorer_DXA00093</attr>
    <attr key="tsOffset" type="long">1633000000000000</attr>
   </node>
  </node>
 </node>
</dv>"#;

    /// IOHeader laid out differently from the encoder's: table at 8, vtable *after* it (negative
    /// soffset), absent fields marked by a zero vtable entry.
    fn io_header(compression: Option<i32>, table_position: Option<i64>, xml: &str) -> Vec<u8> {
        let mut b = vec![8, 0, 0, 0, b'I', b'O', b'H', b'E'];
        b.extend_from_slice(&(8i32 - 28).to_le_bytes()); // soffset: vtable at 28
        b.extend_from_slice(&compression.unwrap_or(0).to_le_bytes()); // 12
        b.extend_from_slice(&table_position.unwrap_or(0).to_le_bytes()); // 16
        b.extend_from_slice(&(40u32 - 24).to_le_bytes()); // 24: string at 40
        let c = if compression.is_some() { 4 } else { 0 };
        let d = if table_position.is_some() { 8 } else { 0 };
        for v in [10u16, 20, c, d, 16] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&[0, 0]);
        b.extend_from_slice(&(xml.len() as u32).to_le_bytes());
        b.extend_from_slice(xml.as_bytes());
        b.push(0);
        let mut file = MAGIC.to_vec();
        file.extend_from_slice(&(b.len() as u32).to_le_bytes());
        file.extend(b);
        file
    }

    /// Size-prefixed EventPacket: table at 8, vtable after it at 16, vector at 24.
    fn events_packet(events: &[Ev]) -> Vec<u8> {
        let mut b = vec![8, 0, 0, 0, b'E', b'V', b'T', b'S'];
        b.extend_from_slice(&(8i32 - 16).to_le_bytes());
        b.extend_from_slice(&(24u32 - 12).to_le_bytes());
        b.extend_from_slice(&[6, 0, 8, 0, 4, 0, 0, 0]);
        b.extend_from_slice(&(events.len() as u32).to_le_bytes());
        for &(t, x, y, on) in events {
            b.extend_from_slice(&t.to_le_bytes());
            b.extend_from_slice(&x.to_le_bytes());
            b.extend_from_slice(&y.to_le_bytes());
            b.extend_from_slice(&[u8::from(on), 0, 0, 0]);
        }
        let mut out = (b.len() as u32).to_le_bytes().to_vec();
        out.extend(b);
        out
    }

    /// An EventPacket whose vtable has no slots: `elements` absent, i.e. empty.
    fn empty_packet() -> Vec<u8> {
        let b = [8, 0, 0, 0, b'E', b'V', b'T', b'S', 0xFC, 0xFF, 0xFF, 0xFF, 4, 0, 4, 0];
        let mut out = 16u32.to_le_bytes().to_vec();
        out.extend(b);
        out
    }

    /// An LZ4 frame (magic, FLG 0x60: version 1, independent blocks, no checksums; BD 0x40: 64 KiB;
    /// header checksum 0x82) holding one uncompressed block, then the end mark.
    fn lz4_stored(data: &[u8]) -> Vec<u8> {
        let mut f = vec![0x04, 0x22, 0x4D, 0x18, 0x60, 0x40, 0x82];
        f.extend_from_slice(&(0x8000_0000u32 | data.len() as u32).to_le_bytes());
        f.extend_from_slice(data);
        f.extend_from_slice(&0u32.to_le_bytes());
        f
    }

    /// A zstd frame (single segment, 1- or 2-byte content size) holding one raw last block.
    fn zstd_raw(data: &[u8]) -> Vec<u8> {
        let mut f = vec![0x28, 0xB5, 0x2F, 0xFD];
        if data.len() < 256 {
            f.extend_from_slice(&[0x20, data.len() as u8]);
        } else {
            f.push(0x60);
            f.extend_from_slice(&(data.len() as u16 - 256).to_le_bytes());
        }
        let block = ((data.len() as u32) << 3) | 1;
        f.extend_from_slice(&block.to_le_bytes()[..3]);
        f.extend_from_slice(data);
        f
    }

    fn lz4(frame: &[u8]) -> Vec<u8> {
        let mut out = vec![1; 100_000];
        let n = lz4_decompress(frame, &mut out).unwrap();
        out.truncate(n);
        out
    }

    fn zstd(frame: &[u8]) -> Vec<u8> {
        let (mut context, mut out) = (None, vec![1, 2, 3]);
        zstd_decompress(frame, &mut context, &mut out).unwrap();
        out
    }

    fn packet(stream: i32, payload: &[u8]) -> Vec<u8> {
        let mut p = stream.to_le_bytes().to_vec();
        p.extend_from_slice(&(payload.len() as i32).to_le_bytes());
        p.extend_from_slice(payload);
        p
    }

    fn as_tuples(ev: &Events) -> Vec<Ev> {
        (0..ev.len()).map(|i| (ev.t[i], ev.x[i] as i16, ev.y[i] as i16, ev.p[i] > 0)).collect()
    }

    fn decode(file: &[u8], piece: usize) -> Result<(Events, DecodeStats)> {
        let h = parse_aedat4_header(file, "f.aedat4")?;
        let mut dec = Aedat4Decoder::new("f.aedat4", &h);
        let ev = feed::pieces(&mut dec, &file[h.data_offset..], h.data_offset as u64, piece)?;
        Ok((ev, dec.stats()))
    }

    const A: [Ev; 3] = [
        (1_633_000_000_000_001, 0, 0, true),
        (1_633_000_000_000_002, 63, 47, false),
        (1_633_000_000_000_002, 5, 6, true),
    ];
    const B: [Ev; 2] = [(1_633_000_000_000_010, 7, 8, false), (1_633_000_000_000_011, 9, 10, true)];

    #[test]
    fn lz4_interleaved_streams_and_data_table() {
        let mut file = io_header(Some(1), Some(0), XML);
        let h_len = file.len();
        for (stream, payload) in [
            (0, lz4_stored(b"imu payload, never decoded")),
            (3, lz4_stored(&events_packet(&A))),
            (2, lz4_stored(&[0xFF; 40])),
            (3, lz4_stored(&events_packet(&B))),
        ] {
            file.extend(packet(stream, &payload));
        }
        let table = file.len() as i64;
        file[18 + 16..18 + 24].copy_from_slice(&table.to_le_bytes());
        // The table starts with the LZ4 magic too; read as a packet it would be garbage.
        file.extend_from_slice(&[0x04, 0x22, 0x4D, 0x18, 0x60, 0x40, 0x82, 0x10, 0, 0, 0, 1, 2]);

        let h = parse_aedat4_header(&file, "f.aedat4").unwrap();
        let want = Aedat4Header {
            compression: Aedat4Compression::Lz4,
            data_table_position: table,
            width: 64,
            height: 48,
            event_stream_id: 3,
            data_offset: h_len,
        };
        assert_eq!(h, want);
        let expected: Vec<Ev> = A.iter().chain(&B).copied().collect();
        for piece in [usize::MAX, 7, 1] {
            let (ev, stats) = decode(&file, piece.min(file.len())).unwrap();
            assert_eq!(as_tuples(&ev), expected, "piece {piece}");
            assert_eq!((ev.width, ev.height), (64, 48));
            assert_eq!(stats.skipped_packets, 2);
        }
    }

    #[test]
    fn absent_header_fields_take_defaults_and_absent_elements_are_empty() {
        let mut file = io_header(None, None, XML);
        file.extend(packet(3, &events_packet(&A)));
        file.extend(packet(3, &empty_packet()));
        file.extend(packet(3, &events_packet(&B)));
        let h = parse_aedat4_header(&file, "f.aedat4").unwrap();
        assert_eq!((h.compression, h.data_table_position), (Aedat4Compression::None, -1));
        let (ev, _) = decode(&file, 5).unwrap();
        assert_eq!(as_tuples(&ev), A.iter().chain(&B).copied().collect::<Vec<_>>());
    }

    #[test]
    fn zstd_packets_to_end_of_file_and_truncation() {
        let mut file = io_header(Some(3), Some(-1), XML);
        let many: Vec<Ev> = (0..20).map(|i| (1000 + i, i as i16, 2, i % 3 == 0)).collect();
        file.extend(packet(3, &zstd_raw(&events_packet(&A))));
        file.extend(packet(0, b"not even zstd"));
        file.extend(packet(3, &zstd_raw(&events_packet(&many))));
        let (ev, stats) = decode(&file, file.len()).unwrap();
        assert_eq!(as_tuples(&ev), A.iter().chain(&many).copied().collect::<Vec<_>>());
        assert_eq!(stats.skipped_packets, 1);

        let last = file.len() - (8 + zstd_raw(&events_packet(&many)).len());
        let e = decode(&file[..file.len() - 3], 64).unwrap_err().to_string();
        assert!(
            e.contains("f.aedat4") && e.contains(&format!("byte offset {last}")) && e.contains("truncated"),
            "{e}"
        );
    }

    #[test]
    fn bad_input_names_the_position() {
        let e = parse_aedat4_header(b"#!AEDAT4.0\r\n\0\0\0\0", "f.aedat4").unwrap_err().to_string();
        assert!(e.contains("magic"), "{e}");
        let full = io_header(Some(0), None, XML);
        let e = parse_aedat4_header(&full[..40], "f.aedat4").unwrap_err().to_string();
        assert!(e.contains("IOHeader"), "{e}");
        let e = parse_aedat4_header(&io_header(Some(7), None, XML), "f.aedat4").unwrap_err().to_string();
        assert!(e.contains("compression 7"), "{e}");
        let e = parse_aedat4_header(&io_header(None, None, "<dv></dv>"), "f.aedat4").unwrap_err().to_string();
        assert!(e.contains("EVTS"), "{e}");

        let mut file = io_header(None, None, XML);
        let at = file.len();
        file.extend(packet(3, &events_packet(&[(5, 64, 0, true)])));
        let e = decode(&file, 1000).unwrap_err().to_string();
        assert!(e.contains(&format!("byte offset {at}")) && e.contains("(64, 0)"), "{e}");
        let mut file = io_header(None, None, XML);
        file.extend(packet(3, &events_packet(&[(5, 1, 1, true), (6, 3, -2, true)])));
        let e = decode(&file, 1000).unwrap_err().to_string();
        assert!(e.contains("event 1: (3, -2)"), "{e}");

        let mut file = io_header(Some(0), Some(0), XML);
        let at = file.len();
        file.extend(packet(3, &events_packet(&A)));
        let table = (file.len() - 4) as i64;
        file[18 + 16..18 + 24].copy_from_slice(&table.to_le_bytes());
        let e = decode(&file, 1000).unwrap_err().to_string();
        assert!(e.contains(&format!("byte offset {at}")) && e.contains("runs past"), "{e}");

        let mut file = io_header(None, None, XML);
        let mut bad = events_packet(&A);
        bad[8] = b'X';
        file.extend(packet(3, &bad));
        let e = decode(&file, 1000).unwrap_err().to_string();
        assert!(e.contains("identifier"), "{e}");
    }

    #[test]
    fn round_trips_with_data_table() {
        let ev = feed::random_events(10_000, 3, 1_700_000_000_000_000, 5, 346, 260);
        for compression in [Aedat4Compression::None, Aedat4Compression::Lz4, Aedat4Compression::Zstd] {
            let file = encode_aedat4(ev.view(), compression, 777).unwrap();
            let h = parse_aedat4_header(&file, "f.aedat4").unwrap();
            assert_eq!((h.compression, h.width, h.height, h.event_stream_id), (compression, 346, 260, 0));
            for piece in [file.len(), 4096, 7] {
                let (got, _) = decode(&file, piece).unwrap();
                assert_eq!(got, ev, "{compression:?} piece {piece}");
            }
            // The table indexes every packet's payload.
            let position = h.data_table_position as usize;
            let table = match compression {
                Aedat4Compression::None => file[position..].to_vec(),
                Aedat4Compression::Lz4 => lz4(&file[position..]),
                Aedat4Compression::Zstd => zstd(&file[position..]),
            };
            let b = &table[4..];
            let (first, n) = vector(b, root(b, b"FTAB").unwrap(), 0).unwrap();
            assert_eq!(n, 10_000usize.div_ceil(777));
            let mut offset = h.data_offset;
            for k in 0..n {
                let entry = follow(b, first + 4 * k).unwrap();
                let at =
                    |slot| i64::from_le_bytes(bytes(b, field(b, entry, slot).unwrap().unwrap()).unwrap());
                assert_eq!(at(0) as usize, offset + 8);
                let size = u32_at(&file, offset + 4).unwrap();
                assert_eq!(at(1), (size as i64) << 32); // PacketInfo{stream 0, size}
                assert_eq!(at(2), if k + 1 < n { 777 } else { 10_000 % 777 });
                assert_eq!((at(3), at(4)), (ev.t[k * 777], ev.t[(k * 777 + 776).min(9_999)]));
                offset += 8 + size;
            }
            assert_eq!(offset, position);
        }
    }

    #[test]
    fn result_is_independent_of_thread_count() {
        let ev = feed::random_events(20_000, 5, 0, 3, 128, 128);
        let file = encode_aedat4(ev.view(), Aedat4Compression::Lz4, 500).unwrap();
        let decode_with = |threads| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| decode(&file, file.len()).unwrap().0)
        };
        assert_eq!(decode_with(1), ev);
        assert_eq!(decode_with(3), ev);
    }

    #[test]
    fn zstd_frames_carry_their_content_size() {
        let data: Vec<u8> = (0..5000u32).map(|i| (i * 7 % 251) as u8).collect();
        let z = compress(&data, Aedat4Compression::Zstd);
        assert_eq!(zstd::zstd_safe::get_frame_content_size(&z).ok(), Some(Some(5000)));
        assert_eq!(zstd(&z), data);
    }

    /// Packets whose frames state no content size, or whose layout differs from DV's (padding after
    /// the events), take the general path; the result and the first error are the same as on the
    /// direct path, whichever path a call takes.
    #[test]
    fn direct_and_general_paths_agree() {
        let many: Vec<Ev> =
            (0..300).map(|i| (1000 + i, (i % 64) as i16, (i % 48) as i16, i % 3 == 0)).collect();
        let padded = |events: &[Ev]| {
            let mut p = events_packet(events);
            p.extend_from_slice(&[0; 16]);
            let n = p.len() as u32 - 4;
            p[..4].copy_from_slice(&n.to_le_bytes());
            p
        };
        let sized = |p: &[u8]| compress(p, Aedat4Compression::Lz4);
        let cases: [(Vec<u8>, &str); 3] = [
            (sized(&events_packet(&many)), "direct"),
            (lz4_stored(&events_packet(&many)), "no content size"),
            (sized(&padded(&many)), "padded"),
        ];
        let mut header = io_header(Some(1), None, XML);
        header.extend(packet(3, &sized(&events_packet(&A))));
        for (last, what) in cases {
            let mut file = header.clone();
            file.extend(packet(3, &last));
            let (ev, _) = decode(&file, file.len()).unwrap();
            assert_eq!(as_tuples(&ev), A.iter().chain(&many).copied().collect::<Vec<_>>(), "{what}");
            // A bad coordinate in the first packet is reported before anything in later packets.
            let mut bad = io_header(Some(1), None, XML);
            bad.extend(packet(3, &sized(&events_packet(&[(5, 1, 1, true), (6, 64, 0, true)]))));
            bad.extend(packet(3, &last));
            bad.extend(packet(3, b"\x04\x22\x4d\x18garbage"));
            let e = decode(&bad, bad.len()).unwrap_err().to_string();
            assert!(e.contains("event 1: (64, 0)"), "{what}: {e}");
        }
    }
}

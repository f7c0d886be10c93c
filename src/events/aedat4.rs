//! iniVation AEDAT 4.0 decoder and encoder (LZ4 and ZSTD packets; EVENT_FORMATS.md §4).

use super::raw_header::DecodeStats;
use super::{Decoder, Events, EventsView};
use crate::error::{Error, Result};

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
    pub width: u32,
    pub height: u32,
    pub event_stream_id: i32,
    /// Absolute offset of the first packet.
    pub data_offset: usize,
}

/// Not implemented yet (API placeholder so dependent branches build).
pub fn parse_aedat4_header(_data: &[u8], path: &str) -> Result<Aedat4Header> {
    Err(Error::Invalid(format!("{path}: AEDAT 4 decoding is not implemented yet")))
}

/// Streaming AEDAT 4.0 decoder; fed the bytes after `data_offset`.
#[derive(Debug, Clone)]
pub struct Aedat4Decoder {
    path: String,
    stats: DecodeStats,
}

impl Aedat4Decoder {
    pub fn new(path: &str, _header: &Aedat4Header) -> Self {
        Aedat4Decoder { path: path.to_string(), stats: DecodeStats::default() }
    }

    pub fn stats(&self) -> DecodeStats {
        self.stats
    }
}

impl Decoder for Aedat4Decoder {
    fn decode(&mut self, _data: &[u8], _offset: u64, _out: &mut Events) -> Result<usize> {
        Err(Error::Invalid(format!("{}: AEDAT 4 decoding is not implemented yet", self.path)))
    }

    fn finish(&mut self, _tail: &[u8], _offset: u64, _out: &mut Events) -> Result<()> {
        Err(Error::Invalid(format!("{}: AEDAT 4 decoding is not implemented yet", self.path)))
    }
}

/// Not implemented yet (API placeholder so dependent branches build).
pub fn encode_aedat4(
    _ev: EventsView<'_>,
    _compression: Aedat4Compression,
    _events_per_packet: usize,
) -> Vec<u8> {
    unimplemented!("encode_aedat4")
}

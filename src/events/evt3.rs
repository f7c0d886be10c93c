//! Prophesee EVT 3.0 decoder and encoder (16-bit words, vectorised events; EVENT_FORMATS.md §3).

use super::raw_header::DecodeStats;
use super::{Decoder, Events, EventsView};
use crate::error::{Error, Result};

/// Streaming EVT 3.0 decoder; fed the payload after the RAW header.
#[derive(Debug, Clone)]
pub struct Evt3Decoder {
    path: String,
    stats: DecodeStats,
}

impl Evt3Decoder {
    pub fn new(path: &str, _width: u32, _height: u32, _time_shift: bool) -> Self {
        Evt3Decoder { path: path.to_string(), stats: DecodeStats::default() }
    }

    pub fn stats(&self) -> DecodeStats {
        self.stats
    }
}

impl Decoder for Evt3Decoder {
    fn decode(&mut self, _data: &[u8], _offset: u64, _out: &mut Events) -> Result<usize> {
        Err(Error::Invalid(format!("{}: EVT 3.0 decoding is not implemented yet", self.path)))
    }

    fn finish(&mut self, _tail: &[u8], _offset: u64, _out: &mut Events) -> Result<()> {
        Err(Error::Invalid(format!("{}: EVT 3.0 decoding is not implemented yet", self.path)))
    }
}

/// Not implemented yet (API placeholder so dependent branches build).
pub fn encode_evt3(_ev: EventsView<'_>) -> Vec<u8> {
    unimplemented!("encode_evt3")
}

//! Chunk index: frame timestamps → half-open event index ranges.

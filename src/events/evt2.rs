//! Prophesee EVT 2.0 decoder (32-bit words).

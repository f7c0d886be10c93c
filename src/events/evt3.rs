//! Prophesee EVT 3.0 decoder (16-bit words, vectorised events).

"""Event streams: reading, writing and describing event files (the Rust core does the decoding)."""

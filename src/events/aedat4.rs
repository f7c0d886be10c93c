//! iniVation AEDAT 4.0 decoder (LZ4 and ZSTD packets).

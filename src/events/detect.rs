//! File-format detection from content (magic bytes, headers, text sniffing), not only the extension.

//! File-format detection from content (magic bytes, headers, text sniffing), not only the extension.
//!
//! The content decides; the extension only makes the error for an unrecognised file more helpful.

use crate::error::{Error, Result};
use crate::events::raw_header::{parse_raw_header, RawEncoding};

/// Every event-file format evgs reads. The first five decode in Rust; the rest go through Python
/// libraries (numpy, h5py, polars), so detection reports them and the Python side dispatches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Text,
    Npy,
    Evt2,
    Evt3,
    Aedat4,
    Npz,
    Hdf5,
    Parquet,
}

impl Format {
    pub const ALL: [Format; 8] = [
        Format::Text,
        Format::Npy,
        Format::Evt2,
        Format::Evt3,
        Format::Aedat4,
        Format::Npz,
        Format::Hdf5,
        Format::Parquet,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Format::Text => "text",
            Format::Npy => "npy",
            Format::Evt2 => "evt2",
            Format::Evt3 => "evt3",
            Format::Aedat4 => "aedat4",
            Format::Npz => "npz",
            Format::Hdf5 => "hdf5",
            Format::Parquet => "parquet",
        }
    }

    /// A format by name; `csv` and `txt` are text.
    pub fn parse(name: &str) -> Result<Format> {
        match name.to_ascii_lowercase().as_str() {
            "csv" | "txt" => Ok(Format::Text),
            n => Format::ALL.into_iter().find(|f| f.name() == n).ok_or_else(|| {
                let names: Vec<_> = Format::ALL.iter().map(|f| f.name()).collect();
                Error::Invalid(format!(
                    "unknown event format {name:?} (known: {}, csv, txt)",
                    names.join(", ")
                ))
            }),
        }
    }
}

const AEDAT4_MAGIC: &[u8] = b"#!AER-DAT4.0\r\n";

/// Bytes read for detection and headers (RAW/AEDAT 4 headers and text sniffing fit easily).
pub const HEAD: usize = 1 << 20;

/// Read the first [`HEAD`] bytes of `file` (fewer if it is shorter).
pub fn read_head(file: &mut std::fs::File, path: &str) -> Result<Vec<u8>> {
    use std::io::Read;
    let mut head = Vec::with_capacity(HEAD);
    file.take(HEAD as u64).read_to_end(&mut head).map_err(|e| Error::io(path, e))?;
    Ok(head)
}

/// Detect the format of the file at `path` from its content.
pub fn detect_file(path: &str) -> Result<Format> {
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    detect(&read_head(&mut file, path)?, path)
}

/// Detect the format of a file from its first bytes (`head`: 1 MiB or the whole file if smaller).
pub fn detect(head: &[u8], path: &str) -> Result<Format> {
    let magic: [(&[u8], Format); 5] = [
        (AEDAT4_MAGIC, Format::Aedat4),
        (super::npy::MAGIC, Format::Npy),
        (b"PK\x03\x04", Format::Npz),
        (b"\x89HDF\r\n\x1a\n", Format::Hdf5),
        (b"PAR1", Format::Parquet),
    ];
    if let Some((_, f)) = magic.iter().find(|(m, _)| head.starts_with(m)) {
        return Ok(*f);
    }
    if head.starts_with(b"% ") {
        return Ok(match parse_raw_header(head, path)?.encoding {
            RawEncoding::Evt2 => Format::Evt2,
            RawEncoding::Evt3 => Format::Evt3,
        });
    }
    if head.is_empty() {
        return Err(Error::format(path, "byte offset 0", "empty file"));
    }
    if head.starts_with(b"#!AER-DAT") {
        let version = head.iter().take(20).take_while(|&&b| b != b'\r' && b != b'\n').count();
        let v = String::from_utf8_lossy(&head[..version]);
        return Err(Error::format(path, "byte offset 0", format!("{v}: only AEDAT 4.0 is supported")));
    }
    let sample = &head[..head.len().min(4096)];
    if let Some(i) = sample.iter().position(|&b| b == 0 || (b < 0x20 && !b"\t\r\n\x0c".contains(&b))) {
        let hint = match path.rsplit('.').next().map(str::to_ascii_lowercase).as_deref() {
            Some("raw") => " (a .raw file needs its `% ` header to say EVT 2.0 or 3.0)",
            Some("aedat4" | "aedat") => " (AEDAT 4 files start with #!AER-DAT4.0)",
            _ => "",
        };
        return Err(Error::format(
            path,
            format!("byte offset {i}"),
            format!("unrecognised binary content, not a known event format{hint}"),
        ));
    }
    Ok(Format::Text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn magic_bytes_and_text() {
        let cases: [(&[u8], Format); 8] = [
            (b"#!AER-DAT4.0\r\n\x10\0\0\0", Format::Aedat4),
            (b"\x93NUMPY\x01\x00", Format::Npy),
            (b"PK\x03\x04rest", Format::Npz),
            (b"\x89HDF\r\n\x1a\nxx", Format::Hdf5),
            (b"PAR1\x15", Format::Parquet),
            (b"% evt 2.0\n% end\n\0\0\0\x80", Format::Evt2),
            (b"% format EVT3;height=720;width=1280\n\0\x80", Format::Evt3),
            (b"t,x,y,p\n1,2,3,0\n", Format::Text),
        ];
        for (head, want) in cases {
            assert_eq!(detect(head, "f.bin").unwrap(), want, "{head:?}");
        }
        for f in Format::ALL {
            assert_eq!(Format::parse(f.name()).unwrap(), f);
        }
        assert_eq!(Format::parse("CSV").unwrap(), Format::Text);
    }

    #[test]
    fn unknown_binary_and_empty_are_errors() {
        let e = detect(b"abc\x01\x02", "x.raw").unwrap_err().to_string();
        assert!(e.starts_with("x.raw: byte offset 3: unrecognised") && e.contains("header"), "{e}");
        assert!(detect(b"", "e.csv").unwrap_err().to_string().contains("empty file"));
        assert!(detect(b"#!AER-DAT2.0\r\n", "a.aedat").unwrap_err().to_string().contains("only AEDAT 4.0"));
    }
}

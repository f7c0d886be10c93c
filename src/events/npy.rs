//! NumPy `.npy` reader and writer (the IncEventGS N×4 float layout and structured arrays).
//!
//! Header per the NPY format spec: magic `\x93NUMPY`, version byte pair, a little-endian u16 (v1) or
//! u32 (v2, v3) header length, then a Python dict literal with `descr`, `fortran_order` and `shape`.
//! Two array kinds hold events: a 2-D `(N, K≥4)` numeric array (columns x, y, t, p by default, as
//! IncEventGS writes them) and a 1-D structured array whose field names say which is which.
//! Float times are seconds, integer times microseconds, unless a unit is given.

use std::mem::MaybeUninit;

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::events::text::TimeUnit;
use crate::events::{ColumnsMut, Decoder, Events, EventsView};

pub const MAGIC: &[u8] = b"\x93NUMPY";

/// A Python literal as it appears in an NPY header.
#[derive(Debug, Clone, PartialEq)]
enum Lit {
    Str(String),
    Int(u64),
    Bool(bool),
    Seq(Vec<Lit>),
    Dict(Vec<(Lit, Lit)>),
}

struct LitParser<'a> {
    s: &'a [u8],
    i: usize,
}

impl LitParser<'_> {
    fn ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        self.ws();
        let hit = self.s.get(self.i) == Some(&c);
        self.i += usize::from(hit);
        hit
    }

    fn value(&mut self) -> std::result::Result<Lit, String> {
        self.ws();
        let c = *self.s.get(self.i).ok_or("unexpected end of header")?;
        match c {
            b'\'' | b'"' => {
                let end = self.s[self.i + 1..].iter().position(|&b| b == c).ok_or("unterminated string")?;
                let v = String::from_utf8_lossy(&self.s[self.i + 1..self.i + 1 + end]).into_owned();
                self.i += end + 2;
                Ok(Lit::Str(v))
            }
            b'(' | b'[' => {
                let close = if c == b'(' { b')' } else { b']' };
                self.i += 1;
                let mut items = Vec::new();
                while !self.eat(close) {
                    items.push(self.value()?);
                    if !self.eat(b',') && !self.eat(close) {
                        return Err(format!("expected ',' or '{}' at header byte {}", close as char, self.i));
                    } else if self.s[self.i - 1] == close {
                        break;
                    }
                }
                Ok(Lit::Seq(items))
            }
            b'{' => {
                self.i += 1;
                let mut items = Vec::new();
                while !self.eat(b'}') {
                    let k = self.value()?;
                    if !self.eat(b':') {
                        return Err(format!("expected ':' at header byte {}", self.i));
                    }
                    items.push((k, self.value()?));
                    if !self.eat(b',') && !self.eat(b'}') {
                        return Err(format!("expected ',' or '}}' at header byte {}", self.i));
                    } else if self.s[self.i - 1] == b'}' {
                        break;
                    }
                }
                Ok(Lit::Dict(items))
            }
            _ => {
                let start = self.i;
                while self.i < self.s.len()
                    && (self.s[self.i].is_ascii_alphanumeric() || self.s[self.i] == b'_')
                {
                    self.i += 1;
                }
                match &self.s[start..self.i] {
                    b"True" => Ok(Lit::Bool(true)),
                    b"False" => Ok(Lit::Bool(false)),
                    w => std::str::from_utf8(w)
                        .ok()
                        .and_then(|w| w.trim_end_matches('L').parse().ok())
                        .map(Lit::Int)
                        .ok_or_else(|| {
                            format!("unexpected {:?} at header byte {start}", String::from_utf8_lossy(w))
                        }),
                }
            }
        }
    }
}

/// Scalar element types an event column may have.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scalar {
    Bool,
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Scalar {
    fn size(self) -> usize {
        match self {
            Scalar::Bool | Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::I64 | Scalar::U64 | Scalar::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Scalar::F32 | Scalar::F64)
    }

    /// Parse a dtype string such as `<f4`, `|b1`, `>i8`; returns the type and whether it is big-endian.
    fn parse(descr: &str) -> std::result::Result<(Scalar, bool), String> {
        let b = descr.as_bytes();
        let (big, rest) = match b.first() {
            Some(b'>') => (true, &descr[1..]),
            Some(b'<' | b'|' | b'=') => (false, &descr[1..]),
            _ => (false, descr),
        };
        let s = match rest {
            "b1" | "?" => Scalar::Bool,
            "i1" => Scalar::I8,
            "u1" => Scalar::U8,
            "i2" => Scalar::I16,
            "u2" => Scalar::U16,
            "i4" => Scalar::I32,
            "u4" => Scalar::U32,
            "i8" => Scalar::I64,
            "u8" => Scalar::U64,
            "f4" => Scalar::F32,
            "f8" => Scalar::F64,
            _ => return Err(format!("unsupported dtype {descr:?} for an event column")),
        };
        Ok((s, big && s.size() > 1))
    }
}

/// Where one event column lives inside a row.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Field {
    pub offset: usize,
    pub scalar: Scalar,
    pub big_endian: bool,
}

/// The parsed header: where rows start, how many, and where t/x/y/p sit in each row.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NpyLayout {
    pub data_offset: usize,
    pub rows: u64,
    pub row_size: usize,
    /// t, x, y, p.
    pub fields: [Field; 4],
    pub time_unit: TimeUnit,
}

fn other_field_size(descr: &str) -> Option<usize> {
    let d = descr.trim_start_matches(['<', '>', '|', '=']);
    let n: usize = d.get(1..)?.parse().ok()?;
    match d.as_bytes()[0] {
        b'U' => Some(4 * n),
        b'S' | b'V' | b'a' | b'c' | b'm' | b'M' => Some(n),
        _ => None,
    }
}

fn dict_get<'a>(d: &'a [(Lit, Lit)], key: &str) -> Option<&'a Lit> {
    d.iter().find(|(k, _)| *k == Lit::Str(key.into())).map(|(_, v)| v)
}

fn field_index(name: &str) -> Option<usize> {
    match name.to_ascii_lowercase().as_str() {
        "t" | "ts" | "time" | "timestamp" | "timestamps" => Some(0),
        "x" | "xs" => Some(1),
        "y" | "ys" => Some(2),
        "p" | "ps" | "pol" | "polarity" | "polarities" => Some(3),
        _ => None,
    }
}

/// Parse the NPY header at the start of `head`. `columns` (letters t/x/y/p/_, default `"xytp"`)
/// names the columns of a 2-D array; `time_unit` overrides the float-seconds / integer-µs default.
pub fn parse_npy_header(
    head: &[u8],
    path: &str,
    columns: Option<&str>,
    time_unit: Option<TimeUnit>,
) -> Result<NpyLayout> {
    let err = |loc: &str, msg: String| Error::format(path, loc, msg);
    if !head.starts_with(MAGIC) || head.len() < 10 {
        return Err(err("byte offset 0", "not an NPY file (no \\x93NUMPY magic)".into()));
    }
    let (len, start) = match head[6] {
        1 => (usize::from(u16::from_le_bytes([head[8], head[9]])), 10),
        2 | 3 if head.len() >= 12 => (u32::from_le_bytes(head[8..12].try_into().unwrap()) as usize, 12),
        v => return Err(err("byte offset 6", format!("unsupported NPY version {v}"))),
    };
    let text = head.get(start..start + len).ok_or_else(|| {
        err("byte offset 8", format!("header of {len} bytes is truncated (file has {} bytes)", head.len()))
    })?;
    let loc = format!("header at byte offset {start}");
    let dict = match (LitParser { s: text, i: 0 }).value() {
        Ok(Lit::Dict(d)) => d,
        Ok(_) => return Err(err(&loc, "header is not a dict".into())),
        Err(e) => return Err(err(&loc, e)),
    };
    let get = |k: &str| dict_get(&dict, k).ok_or_else(|| err(&loc, format!("header has no {k:?}")));
    if *get("fortran_order")? != Lit::Bool(false) {
        return Err(err(
            &loc,
            "Fortran-order arrays are not supported (save with np.ascontiguousarray)".into(),
        ));
    }
    let shape: Vec<u64> = match get("shape")? {
        Lit::Seq(s) => s
            .iter()
            .map(|v| if let Lit::Int(n) = v { Ok(*n) } else { Err(err(&loc, "bad shape".into())) })
            .collect::<Result<_>>()?,
        _ => return Err(err(&loc, "bad shape".into())),
    };
    let scalar = |d: &str| Scalar::parse(d).map_err(|m| err(&loc, m));
    let mut fields: [Option<Field>; 4] = [None; 4];
    let (rows, row_size) = match (get("descr")?, shape.as_slice()) {
        (Lit::Str(d), [n, k]) => {
            let (s, big) = scalar(d)?;
            let letters = columns.unwrap_or("xytp");
            if letters.len() as u64 != *k {
                return Err(err(
                    &loc,
                    format!("array has {k} columns; columns={letters:?} names {}", letters.len()),
                ));
            }
            for (j, c) in letters.chars().enumerate() {
                if c == '_' {
                    continue;
                }
                let slot = "txyp".find(c).ok_or_else(|| err(&loc, format!("bad column letter {c:?}")))?;
                fields[slot] = Some(Field { offset: j * s.size(), scalar: s, big_endian: big });
            }
            (*n, *k as usize * s.size())
        }
        (Lit::Seq(items), [n]) => {
            let mut off = 0;
            for item in items {
                let (name, d) = match item {
                    Lit::Seq(v) if v.len() == 2 => match (&v[0], &v[1]) {
                        (Lit::Str(name), Lit::Str(d)) => (name, d),
                        _ => return Err(err(&loc, format!("unsupported structured field {item:?}"))),
                    },
                    _ => return Err(err(&loc, format!("unsupported structured field {item:?}"))),
                };
                let size = match Scalar::parse(d) {
                    Ok((s, big)) => {
                        if let Some(slot) = field_index(name) {
                            fields[slot] = Some(Field { offset: off, scalar: s, big_endian: big });
                        }
                        s.size()
                    }
                    // Other fields are skipped: their size is the dtype's digits (×4 for unicode).
                    Err(_) => other_field_size(d)
                        .ok_or_else(|| err(&loc, format!("field {name:?} has unsupported dtype {d:?}")))?,
                };
                off += size;
            }
            (*n, off)
        }
        (d, s) => {
            return Err(err(
                &loc,
                format!("expected an (N, 4) array or structured (N,) array, got {d:?} {s:?}"),
            ))
        }
    };
    let names = ["t", "x", "y", "p"];
    let mut out = [Field { offset: 0, scalar: Scalar::U8, big_endian: false }; 4];
    for (k, f) in fields.iter().enumerate() {
        out[k] = f.ok_or_else(|| err(&loc, format!("no {} column/field", names[k])))?;
    }
    let time_unit = time_unit.unwrap_or(if out[0].scalar.is_float() { TimeUnit::S } else { TimeUnit::Us });
    Ok(NpyLayout { data_offset: start + len, rows, row_size, fields: out, time_unit })
}

type ColResult = std::result::Result<(), (usize, String)>;

/// Conversion of one column's raw values to event values. The hot loop only asks for an `Option`;
/// the message is built for the first failing row alone.
trait Conv<T> {
    fn int(&self, v: i64) -> Option<T>;
    fn float(&self, v: f64) -> Option<T>;
    fn why(&self, v: String) -> String;
}

/// Time to µs in the layout's unit.
struct TimeConv(TimeUnit);

impl Conv<i64> for TimeConv {
    #[inline(always)]
    fn int(&self, v: i64) -> Option<i64> {
        match self.0 {
            TimeUnit::S => v.checked_mul(1_000_000),
            TimeUnit::Ms => v.checked_mul(1_000),
            TimeUnit::Us => Some(v),
            TimeUnit::Ns => Some((v as f64 * 1e-3).round() as i64),
        }
    }
    #[inline(always)]
    fn float(&self, v: f64) -> Option<i64> {
        let scale = match self.0 {
            TimeUnit::S => 1e6,
            TimeUnit::Ms => 1e3,
            TimeUnit::Us => 1.0,
            TimeUnit::Ns => 1e-3,
        };
        v.is_finite().then(|| (v * scale).round() as i64)
    }
    fn why(&self, v: String) -> String {
        format!("time {v} is not finite or overflows")
    }
}

/// A pixel coordinate: an integer in 0..=65535 (floats must be integral).
struct CoordConv(&'static str);

impl Conv<u16> for CoordConv {
    #[inline(always)]
    fn int(&self, v: i64) -> Option<u16> {
        u16::try_from(v).ok()
    }
    #[inline(always)]
    fn float(&self, v: f64) -> Option<u16> {
        (v.fract() == 0.0 && (0.0..=65535.0).contains(&v)).then_some(v as u16)
    }
    fn why(&self, v: String) -> String {
        format!("{} = {v} is not a pixel coordinate in 0..=65535", self.0)
    }
}

/// Polarity: 1 → +1; 0 or −1 → −1.
struct PolConv;

impl Conv<i8> for PolConv {
    #[inline(always)]
    fn int(&self, v: i64) -> Option<i8> {
        match v {
            1 => Some(1),
            0 | -1 => Some(-1),
            _ => None,
        }
    }
    #[inline(always)]
    fn float(&self, v: f64) -> Option<i8> {
        if v == 1.0 {
            Some(1)
        } else if v == 0.0 || v == -1.0 {
            Some(-1)
        } else {
            None
        }
    }
    fn why(&self, v: String) -> String {
        format!("polarity {v} is not one of 0/1, -1/+1")
    }
}

/// Convert column `f` of every row in `data` into `out`. One tight loop per element type, so the
/// per-value work inlines.
#[inline]
fn column<T>(data: &[u8], rs: usize, f: Field, out: &mut [MaybeUninit<T>], conv: &impl Conv<T>) -> ColResult {
    macro_rules! go {
        ($t:ty, $n:expr, $to:expr, $method:ident) => {{
            for (i, (row, o)) in data.chunks_exact(rs).zip(out.iter_mut()).enumerate() {
                let a: [u8; $n] = row[f.offset..f.offset + $n].try_into().unwrap();
                let v = $to(if f.big_endian { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) });
                match conv.$method(v) {
                    Some(c) => {
                        o.write(c);
                    }
                    None => return Err((i, conv.why(v.to_string()))),
                }
            }
        }};
    }
    match f.scalar {
        Scalar::Bool => go!(u8, 1, |v: u8| i64::from(v != 0), int),
        Scalar::I8 => go!(i8, 1, i64::from, int),
        Scalar::U8 => go!(u8, 1, i64::from, int),
        Scalar::I16 => go!(i16, 2, i64::from, int),
        Scalar::U16 => go!(u16, 2, i64::from, int),
        Scalar::I32 => go!(i32, 4, i64::from, int),
        Scalar::U32 => go!(u32, 4, i64::from, int),
        Scalar::I64 => go!(i64, 8, |v: i64| v, int),
        Scalar::U64 => go!(u64, 8, |v: u64| i64::try_from(v).unwrap_or(i64::MAX), int),
        Scalar::F32 => go!(f32, 4, f64::from, float),
        Scalar::F64 => go!(f64, 8, |v: f64| v, float),
    }
    Ok(())
}

/// Convert whole rows in `data` (rows `first_row..`) to events appended to `out`, in parallel chunks
/// written straight into the output columns; the error names the first bad row.
fn decode_rows(layout: &NpyLayout, data: &[u8], first_row: u64, path: &str, out: &mut Events) -> Result<()> {
    const CH: usize = 1 << 15;
    let rs = layout.row_size;
    let n = data.len() / rs;
    let time = TimeConv(layout.time_unit);
    let [ft, fx, fy, fp] = layout.fields;
    let ColumnsMut { t, x, y, p } = out.spare_parts([n]).pop().expect("one part");
    let first_error = t
        .par_chunks_mut(CH)
        .zip(x.par_chunks_mut(CH))
        .zip(y.par_chunks_mut(CH))
        .zip(p.par_chunks_mut(CH))
        .zip(data[..n * rs].par_chunks(CH * rs))
        .enumerate()
        .filter_map(|(c, ((((t, x), y), p), d))| {
            [
                column(d, rs, ft, t, &time),
                column(d, rs, fx, x, &CoordConv("x")),
                column(d, rs, fy, y, &CoordConv("y")),
                column(d, rs, fp, p, &PolConv),
            ]
            .into_iter()
            .filter_map(|r| r.err())
            .min_by_key(|(i, _)| *i)
            .map(|(i, m)| (c * CH + i, m))
        })
        .min_by_key(|(i, _)| *i);
    if let Some((i, msg)) = first_error {
        let row = first_row + i as u64;
        let off = layout.data_offset as u64 + row * rs as u64;
        return Err(Error::format(path, format!("row {row} (byte offset {off})"), msg));
    }
    // SAFETY: without an error every column converted every one of the `n` rows.
    unsafe { out.assume_filled(n) };
    Ok(())
}

/// Streaming NPY decoder over the bytes after the header.
pub struct NpyDecoder {
    path: String,
    layout: NpyLayout,
    rows_done: u64,
}

impl NpyDecoder {
    pub fn new(path: &str, layout: NpyLayout) -> Self {
        NpyDecoder { path: path.to_owned(), layout, rows_done: 0 }
    }

    pub fn layout(&self) -> &NpyLayout {
        &self.layout
    }
}

impl Decoder for NpyDecoder {
    fn decode(&mut self, data: &[u8], offset: u64, out: &mut Events) -> Result<usize> {
        let left = self.layout.rows - self.rows_done;
        let rows = ((data.len() / self.layout.row_size) as u64).min(left);
        let used = rows as usize * self.layout.row_size;
        if rows == left && data.len() > used {
            return Err(Error::format(
                &self.path,
                format!("byte offset {}", offset + used as u64),
                format!("data continues after the {} rows the header declares", self.layout.rows),
            ));
        }
        decode_rows(&self.layout, &data[..used], self.rows_done, &self.path, out)?;
        self.rows_done += rows;
        Ok(used)
    }

    fn finish(&mut self, tail: &[u8], offset: u64, _out: &mut Events) -> Result<()> {
        if self.rows_done < self.layout.rows || !tail.is_empty() {
            return Err(Error::format(
                &self.path,
                format!("byte offset {}", offset + tail.len() as u64),
                format!(
                    "truncated: file ends inside row {} of the {} rows the header declares",
                    self.rows_done, self.layout.rows
                ),
            ));
        }
        Ok(())
    }
}

/// How [`encode_npy`] lays events out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NpyStyle {
    /// Structured `(N,)` with fields t `<i8` (µs), x `<u2`, y `<u2`, p `|i1` — lossless.
    Structured,
    /// IncEventGS `(N, 4)` `<f8` columns x, y, t (s), p (±1).
    Xytp,
}

/// Header length used by [`npy_header`]: fixed so a streaming writer can rewrite the row count in place.
pub const HEADER_LEN: usize = 192;

/// A v1.0 NPY header for `rows` events, always [`HEADER_LEN`] bytes long.
pub fn npy_header(rows: u64, style: NpyStyle) -> Vec<u8> {
    let dict = match style {
        NpyStyle::Structured => format!(
            "{{'descr': [('t', '<i8'), ('x', '<u2'), ('y', '<u2'), ('p', '|i1')], 'fortran_order': False, 'shape': ({rows},), }}"
        ),
        NpyStyle::Xytp => format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({rows}, 4), }}"),
    };
    let mut h = Vec::with_capacity(HEADER_LEN);
    h.extend_from_slice(MAGIC);
    h.extend_from_slice(&[1, 0]);
    h.extend_from_slice(&((HEADER_LEN - 10) as u16).to_le_bytes());
    h.extend_from_slice(dict.as_bytes());
    h.resize(HEADER_LEN - 1, b' ');
    h.push(b'\n');
    h
}

/// The rows of `ev` in `style` (no header), encoded in parallel.
pub fn encode_npy_rows(ev: EventsView<'_>, style: NpyStyle) -> Vec<u8> {
    let rs = match style {
        NpyStyle::Structured => 13,
        NpyStyle::Xytp => 32,
    };
    let mut out = vec![0u8; ev.len() * rs];
    out.par_chunks_mut(rs << 14).enumerate().for_each(|(c, buf)| {
        for (k, row) in buf.chunks_exact_mut(rs).enumerate() {
            let i = (c << 14) + k;
            match style {
                NpyStyle::Structured => {
                    row[..8].copy_from_slice(&ev.t[i].to_le_bytes());
                    row[8..10].copy_from_slice(&ev.x[i].to_le_bytes());
                    row[10..12].copy_from_slice(&ev.y[i].to_le_bytes());
                    row[12] = ev.p[i] as u8;
                }
                NpyStyle::Xytp => {
                    row[..8].copy_from_slice(&f64::from(ev.x[i]).to_le_bytes());
                    row[8..16].copy_from_slice(&f64::from(ev.y[i]).to_le_bytes());
                    row[16..24].copy_from_slice(&(ev.t[i] as f64 * 1e-6).to_le_bytes());
                    row[24..].copy_from_slice(&f64::from(ev.p[i]).to_le_bytes());
                }
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Events {
        let mut ev = Events::with_capacity(3, 0, 0);
        ev.push(0, 1, 2, 1);
        ev.push(1_500_000, 639, 479, -1);
        ev.push(2_000_001, 7, 8, 1);
        ev
    }

    fn decode_all(bytes: &[u8], columns: Option<&str>) -> Result<Events> {
        let layout = parse_npy_header(bytes, "a.npy", columns, None)?;
        let off = layout.data_offset;
        let mut dec = NpyDecoder::new("a.npy", layout);
        let mut out = Events::default();
        let used = dec.decode(&bytes[off..], off as u64, &mut out)?;
        dec.finish(&bytes[off + used..], (off + used) as u64, &mut out)?;
        Ok(out)
    }

    fn file(style: NpyStyle, ev: &Events) -> Vec<u8> {
        let mut b = npy_header(ev.len() as u64, style);
        b.extend(encode_npy_rows(ev.view(), style));
        b
    }

    #[test]
    fn both_styles_round_trip() {
        let ev = sample();
        assert_eq!(decode_all(&file(NpyStyle::Structured, &ev), None).unwrap(), ev);
        assert_eq!(decode_all(&file(NpyStyle::Xytp, &ev), None).unwrap(), ev);
        assert_eq!(npy_header(u64::MAX, NpyStyle::Structured).len(), HEADER_LEN);
    }

    #[test]
    fn spec_header_v2_big_endian_float32_and_named_fields() {
        // Built by hand per the NPY spec: version 2.0, u32 header length, big-endian f4, shape (1, 4).
        let dict = b"{'descr': '>f4', 'fortran_order': False, 'shape': (1, 4), }\n";
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&[2, 0]);
        b.extend_from_slice(&(dict.len() as u32).to_le_bytes());
        b.extend_from_slice(dict);
        for v in [3.0f32, 4.0, 0.25, 0.0] {
            b.extend_from_slice(&v.to_be_bytes());
        }
        let ev = decode_all(&b, None).unwrap();
        assert_eq!((ev.t[0], ev.x[0], ev.y[0], ev.p[0]), (250_000, 3, 4, -1));
        // ELOPE-style structured: x, y, p bool, t µs, plus an unknown field to skip.
        let dict = b"{'descr': [('x', '<i2'), ('q', '<u4'), ('y', '<i2'), ('p', '?'), ('t', '<i8')], 'fortran_order': False, 'shape': (1,)}";
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&[1, 0]);
        b.extend_from_slice(&(dict.len() as u16).to_le_bytes());
        b.extend_from_slice(dict);
        b.extend_from_slice(&5i16.to_le_bytes());
        b.extend_from_slice(&[9; 4]);
        b.extend_from_slice(&6i16.to_le_bytes());
        b.push(1);
        b.extend_from_slice(&77i64.to_le_bytes());
        let ev = decode_all(&b, None).unwrap();
        assert_eq!((ev.t[0], ev.x[0], ev.y[0], ev.p[0]), (77, 5, 6, 1));
    }

    #[test]
    fn errors_name_row_and_offset() {
        let mut ev = sample();
        let good = file(NpyStyle::Xytp, &ev);
        let e = decode_all(&good[..good.len() - 3], None).unwrap_err().to_string();
        assert!(e.contains("a.npy: byte offset") && e.contains("truncated"), "{e}");
        let mut bad = good.clone();
        let nan_at = HEADER_LEN + 32 + 16;
        bad[nan_at..nan_at + 8].copy_from_slice(&f64::NAN.to_le_bytes());
        let e = decode_all(&bad, None).unwrap_err().to_string();
        assert!(
            e.contains(&format!("row 1 (byte offset {})", HEADER_LEN + 32)) && e.contains("not finite"),
            "{e}"
        );
        ev.p[2] = 3;
        let e = decode_all(&file(NpyStyle::Structured, &ev), None).unwrap_err().to_string();
        assert!(e.contains("row 2") && e.contains("polarity 3"), "{e}");
        let e = decode_all(b"\x93NUMPY\x01\x00\xff\x00{'descr'", None).unwrap_err().to_string();
        assert!(e.contains("byte offset 8") && e.contains("truncated"), "{e}");
        let e = decode_all(&good, Some("xyt")).unwrap_err().to_string();
        assert!(e.contains("4 columns"), "{e}");
    }
}

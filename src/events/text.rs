//! Text/CSV event files: any delimiter, optional header, configurable columns, time unit and polarity.
//!
//! The layout is sniffed once from the first bytes of the file ([`TextLayout::sniff`]); the payload is
//! then parsed in line-aligned pieces, each split into sub-chunks that rayon parses in parallel and
//! that are concatenated in file order, so results never depend on the thread count.
//!
//! Time-unit rule when none is given: if any sampled time value has a decimal point or an exponent the
//! unit is seconds (ESIM/RPG `events.txt`, v2e CSVs); otherwise integers are microseconds (SEENIC,
//! Prophesee/iniVation exports), unless a sampled magnitude is ≥ 1e17, which only Unix-epoch
//! nanoseconds reach. Milliseconds and relative nanoseconds must be asked for explicitly.
//! Decimal times are converted exactly (fixed-point, round half away from zero), never through f64.

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::events::{ColumnsMut, Decoder, Events, EventsView};

/// Unit of the time column.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeUnit {
    S,
    Ms,
    Us,
    Ns,
}

impl TimeUnit {
    /// Parse `s`, `ms`, `us` (or `µs`), `ns`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "s" => Ok(TimeUnit::S),
            "ms" => Ok(TimeUnit::Ms),
            "us" | "µs" => Ok(TimeUnit::Us),
            "ns" => Ok(TimeUnit::Ns),
            _ => Err(Error::Invalid(format!("unknown time unit {s:?} (expected s, ms, us or ns)"))),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            TimeUnit::S => "s",
            TimeUnit::Ms => "ms",
            TimeUnit::Us => "us",
            TimeUnit::Ns => "ns",
        }
    }

    /// Decimal exponent from this unit to microseconds (`µs = value · 10^e`).
    fn to_us_exp(self) -> i32 {
        match self {
            TimeUnit::S => 6,
            TimeUnit::Ms => 3,
            TimeUnit::Us => 0,
            TimeUnit::Ns => -3,
        }
    }
}

/// What a column holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    T,
    X,
    Y,
    P,
    Skip,
}

/// How fields are separated: one byte, or runs of spaces/tabs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delimiter {
    Byte(u8),
    Whitespace,
}

/// User choices; `None` fields are sniffed.
#[derive(Debug, Clone, Default)]
pub struct TextOptions {
    /// Field separator; `b' '` means runs of whitespace.
    pub delimiter: Option<u8>,
    pub has_header: Option<bool>,
    /// One letter per column: `t`, `x`, `y`, `p`, or `_` for a column to ignore (e.g. `"txyp"`).
    pub columns: Option<String>,
    pub time_unit: Option<TimeUnit>,
    /// Sensor size; when non-zero, an event outside it is an error naming the line.
    pub width: u32,
    pub height: u32,
    /// Non-decreasing timestamps required (an error names the first offending line).
    pub require_sorted: bool,
}

/// The resolved layout of a text event file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TextLayout {
    pub delimiter: Delimiter,
    pub has_header: bool,
    pub roles: Vec<Role>,
    pub time_unit: TimeUnit,
}

/// How many non-blank lines the sniffer looks at.
const SNIFF_LINES: usize = 1000;

fn is_blank_or_comment(line: &[u8]) -> bool {
    let s = line.trim_ascii_start();
    s.is_empty() || s[0] == b'#'
}

fn strip_cr(line: &[u8]) -> &[u8] {
    line.strip_suffix(b"\r").unwrap_or(line)
}

fn split_fields(line: &[u8], delim: Delimiter) -> Vec<&[u8]> {
    match delim {
        Delimiter::Byte(d) => line.split(|&b| b == d).map(|f| f.trim_ascii()).collect(),
        Delimiter::Whitespace => line.split(|&b| b == b' ' || b == b'\t').filter(|f| !f.is_empty()).collect(),
    }
}

fn is_bool(f: &[u8]) -> bool {
    f.eq_ignore_ascii_case(b"true") || f.eq_ignore_ascii_case(b"false")
}

fn role_from_name(name: &[u8]) -> Role {
    let n = String::from_utf8_lossy(name).trim_matches(|c| c == '"' || c == '\'').trim().to_ascii_lowercase();
    match n.as_str() {
        "t" | "ts" | "time" | "timestamp" | "timestamps" => Role::T,
        "x" => Role::X,
        "y" => Role::Y,
        "p" | "pol" | "polarity" | "polarities" => Role::P,
        _ => Role::Skip,
    }
}

fn roles_from_letters(letters: &str) -> Result<Vec<Role>> {
    letters
        .chars()
        .map(|c| match c {
            't' => Ok(Role::T),
            'x' => Ok(Role::X),
            'y' => Ok(Role::Y),
            'p' => Ok(Role::P),
            '_' => Ok(Role::Skip),
            _ => Err(Error::Invalid(format!("columns {letters:?}: use one of t, x, y, p, _ per column"))),
        })
        .collect()
}

fn check_roles(roles: &[Role], path: &str, what: &str) -> Result<()> {
    for r in [Role::T, Role::X, Role::Y, Role::P] {
        let n = roles.iter().filter(|&&q| q == r).count();
        if n != 1 {
            return Err(Error::format(
                path,
                "line 1",
                format!("{what} names column {r:?} {n} times; each of t, x, y, p must appear once (pass columns=)"),
            ));
        }
    }
    Ok(())
}

impl TextLayout {
    /// Work out delimiter, header, column roles and time unit from the file's first bytes.
    pub fn sniff(head: &[u8], path: &str, opts: &TextOptions) -> Result<Self> {
        let mut lines = head.split(|&b| b == b'\n').enumerate().map(|(i, l)| (i + 1, strip_cr(l)));
        let Some((first_no, first)) = lines.by_ref().find(|(_, l)| !is_blank_or_comment(l)) else {
            return Err(Error::format(path, "line 1", "no event lines found (empty text file)"));
        };
        if first.contains(&0) {
            return Err(Error::format(
                path,
                format!("line {first_no}"),
                "binary data, not a text event file",
            ));
        }
        let delimiter = match opts.delimiter {
            Some(b' ') | Some(b'\t') => Delimiter::Whitespace,
            Some(d) => Delimiter::Byte(d),
            None if first.contains(&b',') => Delimiter::Byte(b','),
            None if first.contains(&b';') => Delimiter::Byte(b';'),
            None => Delimiter::Whitespace,
        };
        let fields = split_fields(first, delimiter);
        let looks_numeric = |f: &[u8]| parse_fixed(f, 0).is_ok() || is_bool(f);
        let has_header = opts.has_header.unwrap_or_else(|| !fields.iter().all(|f| looks_numeric(f)));
        let roles = match (&opts.columns, has_header) {
            (Some(letters), _) => roles_from_letters(letters)?,
            (None, true) => fields.iter().map(|f| role_from_name(f)).collect(),
            (None, false) if fields.len() == 4 => vec![Role::T, Role::X, Role::Y, Role::P],
            (None, false) => {
                return Err(Error::format(
                    path,
                    format!("line {first_no}"),
                    format!("{} columns and no header: pass columns= (e.g. \"txyp\")", fields.len()),
                ))
            }
        };
        check_roles(&roles, path, if opts.columns.is_some() { "columns=" } else { "the header" })?;
        if roles.len() != fields.len() {
            return Err(Error::format(
                path,
                format!("line {first_no}"),
                format!("{} columns, but {} column roles given", fields.len(), roles.len()),
            ));
        }
        let time_unit = match opts.time_unit {
            Some(u) => u,
            None => {
                let ti = roles.iter().position(|&r| r == Role::T).unwrap_or(0);
                let data = std::iter::once((first_no, first))
                    .filter(|_| !has_header)
                    .chain(lines.filter(|(_, l)| !is_blank_or_comment(l)))
                    .take(SNIFF_LINES);
                let mut decimal = false;
                let mut huge = false;
                for (_, l) in data {
                    if let Some(f) = split_fields(l, delimiter).get(ti) {
                        decimal |= f.iter().any(|&b| b == b'.' || b == b'e' || b == b'E');
                        huge |= parse_fixed(f, 0).is_ok_and(|v| v.unsigned_abs() >= 100_000_000_000_000_000);
                    }
                }
                if decimal {
                    TimeUnit::S
                } else if huge {
                    TimeUnit::Ns
                } else {
                    TimeUnit::Us
                }
            }
        };
        Ok(TextLayout { delimiter, has_header, roles, time_unit })
    }
}

/// Parse a decimal number `f` (optional sign, digits, fraction, exponent) and return
/// `round(value · 10^exp)` exactly, rounding half away from zero.
fn parse_fixed(f: &[u8], exp: i32) -> std::result::Result<i64, &'static str> {
    let (neg, body) = match f.first() {
        Some(b'-') => (true, &f[1..]),
        Some(b'+') => (false, &f[1..]),
        _ => (false, f),
    };
    let mut m: i128 = 0;
    let mut digits = 0u32;
    let mut frac = 0i32;
    let mut i = 0;
    let mut seen_dot = false;
    while i < body.len() {
        match body[i] {
            c @ b'0'..=b'9' => {
                if digits >= 36 {
                    return Err("too many digits");
                }
                m = m * 10 + i128::from(c - b'0');
                if m != 0 {
                    digits += 1;
                }
                frac += i32::from(seen_dot);
            }
            b'.' if !seen_dot => seen_dot = true,
            b'e' | b'E' => break,
            _ => return Err(not_a_number(f)),
        }
        i += 1;
    }
    let mantissa_digits = i - usize::from(seen_dot);
    if mantissa_digits == 0 {
        return Err(not_a_number(f));
    }
    let mut e10 = exp - frac;
    if i < body.len() {
        let ex = std::str::from_utf8(&body[i + 1..]).ok().and_then(|s| s.parse::<i32>().ok());
        e10 = e10.checked_add(ex.ok_or("bad exponent")?).ok_or("exponent out of range")?;
    }
    let v = if e10 >= 0 {
        let scale = 10i128.checked_pow(e10 as u32).ok_or("value out of range")?;
        if m == 0 {
            0
        } else {
            m.checked_mul(scale).ok_or("value out of range")?
        }
    } else if e10 < -38 {
        0
    } else {
        let d = 10i128.pow((-e10) as u32);
        (m + d / 2) / d
    };
    let v = if neg { -v } else { v };
    i64::try_from(v).map_err(|_| "value out of range")
}

fn not_a_number(f: &[u8]) -> &'static str {
    let s = f.trim_ascii_start();
    let s = s.strip_prefix(b"-").or_else(|| s.strip_prefix(b"+")).unwrap_or(s);
    if s.eq_ignore_ascii_case(b"nan") || s.eq_ignore_ascii_case(b"inf") || s.eq_ignore_ascii_case(b"infinity")
    {
        "not a finite number"
    } else {
        "not a number"
    }
}

#[inline]
fn parse_uint_fast(f: &[u8]) -> Option<u64> {
    if f.is_empty() || f.len() > 18 {
        return None;
    }
    let mut v = 0u64;
    for &c in f {
        let d = c.wrapping_sub(b'0');
        if d > 9 {
            return None;
        }
        v = v * 10 + u64::from(d);
    }
    Some(v)
}

#[inline]
fn parse_coord(f: &[u8]) -> std::result::Result<u16, String> {
    let v = match parse_uint_fast(f) {
        Some(v) => v as i64,
        None => {
            // Integral floats such as "12.0" are accepted; anything fractional is not a pixel.
            let milli = parse_fixed(f, 3).map_err(|e| format!("coordinate {:?}: {e}", lossy(f)))?;
            if milli % 1000 != 0 {
                return Err(format!("coordinate {:?} is not an integer", lossy(f)));
            }
            milli / 1000
        }
    };
    u16::try_from(v).map_err(|_| format!("coordinate {:?} outside 0..=65535", lossy(f)))
}

#[inline]
fn parse_pol(f: &[u8]) -> std::result::Result<i8, String> {
    match f {
        b"1" | b"+1" => Ok(1),
        b"0" | b"-1" => Ok(-1),
        _ if f.eq_ignore_ascii_case(b"true") => Ok(1),
        _ if f.eq_ignore_ascii_case(b"false") => Ok(-1),
        _ => match parse_fixed(f, 3) {
            Ok(1000) => Ok(1),
            Ok(0) | Ok(-1000) => Ok(-1),
            _ => Err(format!("polarity {:?} is not one of 0/1, -1/+1, true/false", lossy(f))),
        },
    }
}

#[inline]
fn parse_time(f: &[u8], exp: i32) -> std::result::Result<i64, String> {
    if exp == 0 {
        if let Some(v) = parse_uint_fast(f) {
            return Ok(v as i64);
        }
    }
    parse_fixed(f, exp).map_err(|e| format!("time {:?}: {e}", lossy(f)))
}

fn lossy(f: &[u8]) -> String {
    String::from_utf8_lossy(&f[..f.len().min(40)]).into_owned()
}

/// The outcome of parsing one line-aligned sub-chunk.
struct Chunk {
    /// Events written to the front of the chunk's output slots.
    events: usize,
    /// Times of the first and last event.
    first_t: Option<i64>,
    last_t: Option<i64>,
    /// Lines in the chunk (terminated ones, plus a final unterminated one if any).
    lines: u64,
    /// 1-based line (within the chunk) of the first event, for the cross-chunk sortedness check.
    first_event_line: u64,
    /// First error: 1-based line within the chunk and message.
    error: Option<(u64, String)>,
}

struct LineParser<'a> {
    layout: &'a TextLayout,
    exp: i32,
    width: u32,
    height: u32,
    require_sorted: bool,
}

impl LineParser<'_> {
    /// Parse one line's fields into (t, x, y, p).
    #[inline]
    fn parse_line(&self, line: &[u8]) -> std::result::Result<(i64, u16, u16, i8), String> {
        let roles = &self.layout.roles;
        let (mut t, mut x, mut y, mut p) = (0i64, 0u16, 0u16, 0i8);
        let mut rest = line;
        let mut trailing_delim = false;
        for (k, &role) in roles.iter().enumerate() {
            let field = match self.layout.delimiter {
                Delimiter::Byte(d) => {
                    let (f, r) = match rest.iter().position(|&b| b == d) {
                        Some(i) => (&rest[..i], Some(&rest[i + 1..])),
                        None => (rest, None),
                    };
                    match r {
                        Some(r) => rest = r,
                        None if k + 1 < roles.len() => return Err(self.count_error(line)),
                        None => rest = &[],
                    }
                    trailing_delim = r.is_some() && k + 1 == roles.len();
                    f.trim_ascii()
                }
                Delimiter::Whitespace => {
                    let s = rest.trim_ascii_start();
                    let end = s.iter().position(|&b| b == b' ' || b == b'\t').unwrap_or(s.len());
                    if end == 0 {
                        return Err(self.count_error(line));
                    }
                    rest = &s[end..];
                    &s[..end]
                }
            };
            match role {
                Role::T => t = parse_time(field, self.exp)?,
                Role::X => x = parse_coord(field)?,
                Role::Y => y = parse_coord(field)?,
                Role::P => p = parse_pol(field)?,
                Role::Skip => {}
            }
        }
        let extra = match self.layout.delimiter {
            Delimiter::Byte(_) => trailing_delim,
            Delimiter::Whitespace => !rest.trim_ascii().is_empty(),
        };
        if extra {
            return Err(self.count_error(line));
        }
        Ok((t, x, y, p))
    }

    fn count_error(&self, line: &[u8]) -> String {
        let n = split_fields(line, self.layout.delimiter).len();
        format!("expected {} columns, found {n}", self.layout.roles.len())
    }

    /// The common line shape in one pass: unsigned decimals separated by exactly the delimiter,
    /// ending in `\n` / `\r\n` / end of data. Anything else (signs, spaces after commas, exponents,
    /// booleans, comments, errors) returns `None` and goes through [`Self::parse_line`].
    #[inline(always)]
    fn fast_line(&self, data: &[u8], mut i: usize) -> Option<((i64, u16, u16, i8), usize)> {
        let n = data.len();
        let (ws, d) = match self.layout.delimiter {
            Delimiter::Byte(d) => (false, d),
            Delimiter::Whitespace => (true, b' '),
        };
        let (mut t, mut x, mut y, mut p) = (0i64, 0u16, 0u16, 0i8);
        let k = self.layout.roles.len();
        for (j, &role) in self.layout.roles.iter().enumerate() {
            let neg = role == Role::P && data.get(i) == Some(&b'-');
            i += usize::from(neg);
            let mut m = 0u64;
            let start = i;
            while i < n && data[i].wrapping_sub(b'0') <= 9 {
                m = m.wrapping_mul(10) + u64::from(data[i] - b'0');
                i += 1;
            }
            let int_digits = i - start;
            let mut frac = 0;
            if i < n && data[i] == b'.' {
                i += 1;
                let s1 = i;
                while i < n && data[i].wrapping_sub(b'0') <= 9 {
                    m = m.wrapping_mul(10) + u64::from(data[i] - b'0');
                    i += 1;
                }
                frac = i - s1;
            }
            if int_digits == 0 || int_digits + frac > 18 {
                return None;
            }
            if j + 1 < k {
                if data.get(i) != Some(&d) && !(ws && data.get(i) == Some(&b'\t')) {
                    return None;
                }
                i += 1;
                while ws && i < n && (data[i] == b' ' || data[i] == b'\t') {
                    i += 1;
                }
            } else {
                i += usize::from(data.get(i) == Some(&b'\r'));
                if i < n {
                    if data[i] != b'\n' {
                        return None;
                    }
                    i += 1;
                }
            }
            match role {
                Role::T => {
                    let e = self.exp - frac as i32;
                    t = if e >= 0 {
                        i64::try_from(m.checked_mul(POW10[e as usize])?).ok()?
                    } else if -e <= 18 {
                        let div = POW10[(-e) as usize];
                        ((m + div / 2) / div) as i64
                    } else {
                        return None;
                    };
                }
                Role::X | Role::Y => {
                    let v = u16::try_from(m).ok().filter(|_| frac == 0)?;
                    if role == Role::X {
                        x = v;
                    } else {
                        y = v;
                    }
                }
                Role::P => {
                    p = match (neg, m, frac) {
                        (false, 1, 0) => 1,
                        (false, 0, 0) | (true, 1, 0) => -1,
                        _ => return None,
                    }
                }
                Role::Skip => {}
            }
        }
        Some(((t, x, y, p), i))
    }

    /// Parse a line-aligned piece into `out`, which has one slot per line (blank and comment lines
    /// leave slots unused at the end).
    fn parse_chunk(&self, data: &[u8], out: ColumnsMut<'_>) -> Chunk {
        let ColumnsMut { t: ts, x: xs, y: ys, p: ps } = out;
        let mut k = 0;
        let mut lines = 0u64;
        let mut first_event_line = 0u64;
        // Times of the first and latest event (`ts` is write-only).
        let (mut first_t, mut last_t) = (0i64, 0i64);
        let plain = match self.layout.delimiter {
            Delimiter::Byte(d)
                if self.exp == 0 && self.layout.roles == [Role::T, Role::X, Role::Y, Role::P] =>
            {
                Some(d)
            }
            _ => None,
        };
        let mut pos = 0;
        while pos < data.len() {
            lines += 1;
            let fast = match plain {
                Some(d) if pos + PLAIN_WINDOW <= data.len() => plain_line(data, pos, d),
                _ => None,
            };
            let parsed = match fast.or_else(|| self.fast_line(data, pos)) {
                Some((ev, next)) => {
                    pos = next;
                    Ok(ev)
                }
                None => {
                    let end = memchr::memchr(b'\n', &data[pos..]).map_or(data.len(), |i| pos + i);
                    let line = strip_cr(&data[pos..end]);
                    pos = end + 1;
                    if is_blank_or_comment(line) {
                        continue;
                    }
                    self.parse_line(line)
                }
            };
            let msg = match parsed {
                Ok((t, x, y, p)) => {
                    if (self.width > 0 && u32::from(x) >= self.width)
                        || (self.height > 0 && u32::from(y) >= self.height)
                    {
                        format!("event ({x}, {y}) outside the {}x{} sensor", self.width, self.height)
                    } else if self.require_sorted && k > 0 && t < last_t {
                        format!("time goes backwards ({t} < previous {last_t})")
                    } else {
                        if k == 0 {
                            first_event_line = lines;
                            first_t = t;
                        }
                        last_t = t;
                        ts[k].write(t);
                        xs[k].write(x);
                        ys[k].write(y);
                        ps[k].write(p);
                        k += 1;
                        continue;
                    }
                }
                Err(msg) => msg,
            };
            return Chunk {
                events: k,
                first_t: None,
                last_t: None,
                lines,
                first_event_line,
                error: Some((lines, msg)),
            };
        }
        let (first_t, last_t) = ((k > 0).then_some(first_t), (k > 0).then_some(last_t));
        Chunk { events: k, first_t, last_t, lines, first_event_line, error: None }
    }
}

/// Bytes [`plain_line`] may look at: the longest line it accepts, with room to spare.
const PLAIN_WINDOW: usize = 48;

/// The most common layout, `t,x,y,p` with integer µs and 0/1 polarity, with fixed field limits and no
/// end-of-data checks (the caller guarantees [`PLAIN_WINDOW`] bytes). Anything else — more digits,
/// signs, spaces, other polarity spellings, errors — returns `None` for the general parsers.
#[inline(always)]
fn plain_line(data: &[u8], pos: usize, d: u8) -> Option<((i64, u16, u16, i8), usize)> {
    let b: &[u8; PLAIN_WINDOW] = data[pos..pos + PLAIN_WINDOW].try_into().unwrap();
    // An unsigned field of 1..`max` digits followed by `end`; returns (value, index after `end`).
    let field = |mut i: usize, max: usize, end: u8| {
        let (start, mut v) = (i, 0u64);
        while i < start + max && b[i].wrapping_sub(b'0') <= 9 {
            v = v * 10 + u64::from(b[i] - b'0');
            i += 1;
        }
        (i > start && i < start + max && b[i] == end).then_some((v, i + 1))
    };
    let (t, i) = field(0, 18, d)?;
    let (x, i) = field(i, 6, d)?;
    let (y, i) = field(i, 6, d)?;
    let p = match b[i] {
        b'0' => -1,
        b'1' => 1,
        _ => return None,
    };
    let i = i + 1 + usize::from(b[i + 1] == b'\r');
    if b[i] != b'\n' {
        return None;
    }
    Some(((t as i64, u16::try_from(x).ok()?, u16::try_from(y).ok()?, p), pos + i + 1))
}

const POW10: [u64; 19] = {
    let mut p = [1u64; 19];
    let mut i = 1;
    while i < 19 {
        p[i] = p[i - 1] * 10;
        i += 1;
    }
    p
};

/// Split `data` into about `n` pieces that each end just after a newline (the last may not).
fn split_at_lines(data: &[u8], n: usize) -> Vec<&[u8]> {
    let target = (data.len() / n.max(1)).max(1 << 16);
    let mut pieces = Vec::with_capacity(n + 1);
    let mut start = 0;
    while start < data.len() {
        let cut = start + target;
        let end = if cut >= data.len() {
            data.len()
        } else {
            memchr::memchr(b'\n', &data[cut..]).map_or(data.len(), |i| cut + i + 1)
        };
        pieces.push(&data[start..end]);
        start = end;
    }
    pieces
}

/// Streaming text decoder: consumes whole lines, parses them in parallel, keeps the line count.
pub struct TextDecoder {
    path: String,
    layout: TextLayout,
    width: u32,
    height: u32,
    require_sorted: bool,
    /// Lines consumed so far (the next line is `lines + 1`).
    lines: u64,
    header_pending: bool,
    /// Last timestamp so far, for sortedness across pieces.
    last: Option<i64>,
}

impl TextDecoder {
    /// Sniff the layout from the file's first bytes (`head`) and build the decoder.
    pub fn new(head: &[u8], path: &str, opts: &TextOptions) -> Result<Self> {
        let layout = TextLayout::sniff(head, path, opts)?;
        Ok(TextDecoder {
            path: path.to_owned(),
            header_pending: layout.has_header,
            layout,
            width: opts.width,
            height: opts.height,
            require_sorted: opts.require_sorted,
            lines: 0,
            last: None,
        })
    }

    pub fn layout(&self) -> &TextLayout {
        &self.layout
    }

    /// Parse complete lines in `data` (which starts at a line boundary) and append to `out`.
    fn parse(&mut self, mut data: &[u8], out: &mut Events) -> Result<()> {
        while self.header_pending && !data.is_empty() {
            let end = memchr::memchr(b'\n', data).map_or(data.len(), |i| i + 1);
            self.lines += 1;
            self.header_pending = is_blank_or_comment(&data[..end]);
            data = &data[end..];
        }
        let parser = LineParser {
            layout: &self.layout,
            exp: self.layout.time_unit.to_us_exp(),
            width: self.width,
            height: self.height,
            require_sorted: self.require_sorted,
        };
        // Each piece parses straight into the output, one slot per line (counted with SIMD memchr);
        // slots left by blank and comment lines are closed up afterwards.
        let pieces = split_at_lines(data, 4 * rayon::current_num_threads());
        let slots: Vec<usize> = pieces
            .par_iter()
            .map(|p| memchr::memchr_iter(b'\n', p).count() + usize::from(!p.ends_with(b"\n")))
            .collect();
        let parts = out.spare_parts(slots.iter().copied());
        let chunks: Vec<Chunk> =
            pieces.par_iter().zip(parts).map(|(p, part)| parser.parse_chunk(p, part)).collect();
        // Close up the unused slots in the spare columns: events `slot..slot + c.events` move to `end`.
        let (mut slot, mut end) = (0, 0);
        for (c, n) in chunks.iter().zip(&slots) {
            if let Some((line, msg)) = &c.error {
                return Err(Error::format(&self.path, format!("line {}", self.lines + line), msg));
            }
            if let (true, Some(last), Some(t0)) = (self.require_sorted, self.last, c.first_t) {
                if t0 < last {
                    return Err(Error::format(
                        &self.path,
                        format!("line {}", self.lines + c.first_event_line),
                        format!("time goes backwards ({t0} < previous {last})"),
                    ));
                }
            }
            self.last = c.last_t.or(self.last);
            self.lines += c.lines;
            if slot != end {
                let spare = out.spare_mut();
                spare.t.copy_within(slot..slot + c.events, end);
                spare.x.copy_within(slot..slot + c.events, end);
                spare.y.copy_within(slot..slot + c.events, end);
                spare.p.copy_within(slot..slot + c.events, end);
            }
            end += c.events;
            slot += n;
        }
        // SAFETY: each piece wrote its first `c.events` slots, now closed up into `0..end`.
        unsafe { out.assume_filled(end) };
        Ok(())
    }
}

impl Decoder for TextDecoder {
    fn decode(&mut self, data: &[u8], _offset: u64, out: &mut Events) -> Result<usize> {
        let Some(last_nl) = memchr::memrchr(b'\n', data) else { return Ok(0) };
        self.parse(&data[..=last_nl], out)?;
        Ok(last_nl + 1)
    }

    fn finish(&mut self, tail: &[u8], _offset: u64, out: &mut Events) -> Result<()> {
        self.parse(tail, out)
    }
}

/// How [`encode_text`] writes events.
#[derive(Debug, Clone, Copy)]
pub struct TextStyle {
    pub delimiter: u8,
    pub time_unit: TimeUnit,
    /// Write a `t,x,y,p` header line.
    pub header: bool,
    /// Polarity as 0/1 (SEENIC, ESIM) instead of −1/+1.
    pub zero_one: bool,
}

fn push_u64(buf: &mut Vec<u8>, mut v: u64) {
    let mut tmp = [0u8; 20];
    let mut i = tmp.len();
    loop {
        i -= 1;
        tmp[i] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 {
            break;
        }
    }
    buf.extend_from_slice(&tmp[i..]);
}

fn push_time(buf: &mut Vec<u8>, t: i64, unit: TimeUnit) {
    if t < 0 {
        buf.push(b'-');
    }
    let a = t.unsigned_abs();
    // Integer part, '.', then the remainder zero-padded to `width` digits.
    let frac = |buf: &mut Vec<u8>, div: u64, width: u32| {
        push_u64(buf, a / div);
        buf.push(b'.');
        let r = a % div;
        let digits = r.checked_ilog10().map_or(1, |d| d + 1);
        buf.extend(std::iter::repeat_n(b'0', (width - digits) as usize));
        push_u64(buf, r);
    };
    match unit {
        TimeUnit::S => frac(buf, 1_000_000, 6),
        TimeUnit::Ms => frac(buf, 1_000, 3),
        TimeUnit::Us => push_u64(buf, a),
        TimeUnit::Ns => push_u64(buf, a * 1000),
    }
}

/// Format events as text lines (parallel over chunks, concatenated in order).
pub fn encode_text(ev: EventsView<'_>, style: TextStyle) -> Vec<u8> {
    const CHUNK: usize = 1 << 16;
    let n = ev.len();
    let parts: Vec<Vec<u8>> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let range = c * CHUNK..((c + 1) * CHUNK).min(n);
            let mut buf = Vec::with_capacity(range.len() * 24);
            for i in range {
                push_time(&mut buf, ev.t[i], style.time_unit);
                buf.push(style.delimiter);
                push_u64(&mut buf, u64::from(ev.x[i]));
                buf.push(style.delimiter);
                push_u64(&mut buf, u64::from(ev.y[i]));
                buf.push(style.delimiter);
                match (ev.p[i] > 0, style.zero_one) {
                    (true, _) => buf.push(b'1'),
                    (false, true) => buf.push(b'0'),
                    (false, false) => buf.extend_from_slice(b"-1"),
                }
                buf.push(b'\n');
            }
            buf
        })
        .collect();
    let mut out = Vec::with_capacity(parts.iter().map(Vec::len).sum::<usize>() + 16);
    if style.header {
        let d = style.delimiter as char;
        out.extend_from_slice(format!("t{d}x{d}y{d}p\n").as_bytes());
    }
    for p in parts {
        out.extend_from_slice(&p);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(text: &str, opts: &TextOptions) -> Result<Events> {
        let mut dec = TextDecoder::new(text.as_bytes(), "f.csv", opts)?;
        let mut out = Events::default();
        let used = dec.decode(text.as_bytes(), 0, &mut out)?;
        dec.finish(&text.as_bytes()[used..], used as u64, &mut out)?;
        Ok(out)
    }

    #[test]
    fn fixed_point_is_exact() {
        assert_eq!(parse_fixed(b"1.5", 6), Ok(1_500_000));
        assert_eq!(parse_fixed(b"0.0000015", 6), Ok(2));
        assert_eq!(parse_fixed(b"-0.0000015", 6), Ok(-2));
        assert_eq!(parse_fixed(b"1e-3", 6), Ok(1000));
        assert_eq!(parse_fixed(b"1999", -3), Ok(2));
        assert_eq!(parse_fixed(b"nan", 0), Err("not a finite number"));
        assert_eq!(parse_fixed(b"-inf", 0), Err("not a finite number"));
        assert_eq!(parse_fixed(b"1x", 0), Err("not a number"));
        assert_eq!(parse_fixed(b".", 0), Err("not a number"));
    }

    #[test]
    fn seenic_with_and_without_header() {
        let a = read("t,x,y,p\n10,1,2,0\n20,3,4,1\n", &TextOptions::default()).unwrap();
        let b = read("10,1,2,0\n20,3,4,1", &TextOptions::default()).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.t, vec![10, 20]);
        assert_eq!(a.p, vec![-1, 1]);
    }

    #[test]
    fn ems_header_maps_columns_and_esim_seconds() {
        let e = read("x;polarity;timestamp;y\r\n5;true;7;6\r\n", &TextOptions::default()).unwrap();
        assert_eq!((e.t[0], e.x[0], e.y[0], e.p[0]), (7, 5, 6, 1));
        let e = read("0.000001 1 2 0\n1.25  3\t4 1\n", &TextOptions::default()).unwrap();
        assert_eq!(e.t, vec![1, 1_250_000]);
    }

    #[test]
    fn errors_name_the_line() {
        let opts = TextOptions { require_sorted: true, width: 10, height: 10, ..Default::default() };
        let cases = [
            ("t,x,y,p\n1,1,1,1\n2,1,1\n", "line 3", "expected 4 columns, found 3"),
            ("1,1,1,1\n2,1,1,1,5\n", "line 2", "expected 4 columns, found 5"),
            ("1,1,1,1\n2,1,1,1,\n", "line 2", "expected 4 columns, found 5"),
            ("1,1,1,1\n\n# c\nnan,1,1,1\n", "line 4", "not a finite number"),
            ("1,1,1,1\n0,1,1,1\n", "line 2", "backwards"),
            ("1,1,1,1\n2,10,1,1\n", "line 2", "outside the 10x10 sensor"),
            ("1,1,1,1\n2,1,1,2\n", "line 2", "polarity"),
            ("1,1,1,1\n2,1.5,1,1\n", "line 2", "not an integer"),
        ];
        for (text, loc, msg) in cases {
            let e = read(text, &opts).unwrap_err().to_string();
            assert!(e.starts_with(&format!("f.csv: {loc}: ")) && e.contains(msg), "{text:?} -> {e}");
        }
    }

    #[test]
    fn parallel_pieces_keep_order_and_line_numbers() {
        let mut text = String::new();
        for i in 0..50_000 {
            text.push_str(&format!("{i},{},{},{}\n", i % 640, i % 480, i % 2));
        }
        text.push_str("oops,1,1,1\n");
        let e = read(&text, &TextOptions::default()).unwrap_err().to_string();
        assert!(e.contains("line 50001"), "{e}");
        let ev = read(&text[..text.len() - 11], &TextOptions::default()).unwrap();
        assert_eq!(ev.t, (0..50_000).collect::<Vec<i64>>());
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let again = pool.install(|| read(&text[..text.len() - 11], &TextOptions::default()).unwrap());
            assert_eq!(again, ev, "{threads} threads");
        }
    }

    /// Blank and comment lines leave output slots unused; they are closed up across pieces.
    #[test]
    fn blank_and_comment_lines_between_pieces() {
        let mut text = String::from("t,x,y,p\n");
        for i in 0..60_000 {
            text.push_str(&format!("{i},{},{},{}\n", i % 640, i % 480, i % 2));
            if i % 7_001 == 0 {
                text.push_str("# comment\n\n  \r\n");
            }
        }
        text.push_str("60000,1,2,1");
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let ev = pool.install(|| read(&text, &TextOptions::default()).unwrap());
            assert_eq!(ev.t, (0..=60_000).collect::<Vec<i64>>(), "{threads} threads");
            assert_eq!((ev.x[60_000], ev.y[59_999], ev.p[3]), (1, 59_999 % 480, 1));
        }
    }

    #[test]
    fn fast_path_agrees_with_general_parser() {
        let lines = [
            "12,3,4,1",
            "12345678,640,4,0",
            "123456789012345,1,65535,1\r",
            "1234567890123456,1,2,1",
            "123456789012345678,1,2,1",
            "0.0000005,3,4,0",
            "1.25,65535,0,-1",
            "7,65536,0,1",
            "7,1.0,0,1",
            "7,1,2,3",
            "5,1,2,1\r",
            "1e3,1,2,1",
            " 5,1,2,1",
            "5, 1,2,1",
            "5,1,2,true",
            "99999999999999999999,1,1,1",
            "1,2,3,4,5",
            "1,2,3",
        ];
        for unit in [TimeUnit::S, TimeUnit::Us, TimeUnit::Ns] {
            let layout = TextLayout {
                delimiter: Delimiter::Byte(b','),
                has_header: false,
                roles: vec![Role::T, Role::X, Role::Y, Role::P],
                time_unit: unit,
            };
            let parser = LineParser {
                layout: &layout,
                exp: unit.to_us_exp(),
                width: 0,
                height: 0,
                require_sorted: false,
            };
            for line in lines {
                let general = parser.parse_line(strip_cr(line.as_bytes())).ok();
                let padded = format!("{line}\n{}", " ".repeat(PLAIN_WINDOW));
                if let (TimeUnit::Us, Some((ev, next))) = (unit, plain_line(padded.as_bytes(), 0, b',')) {
                    assert_eq!((Some(ev), next), (general, line.len() + 1), "{line:?} plain");
                }
                if let Some((ev, next)) = parser.fast_line(line.as_bytes(), 0) {
                    assert_eq!((Some(ev), next), (general, line.len()), "{line:?} in {unit:?}");
                }
            }
        }
    }

    #[test]
    fn encode_then_decode_round_trips() {
        let mut ev = Events::with_capacity(3, 0, 0);
        ev.push(-5, 1, 2, 1);
        ev.push(1_000_001, 3, 4, -1);
        ev.push(2_000_000, 65535, 0, 1);
        for unit in [TimeUnit::S, TimeUnit::Ms, TimeUnit::Us, TimeUnit::Ns] {
            for (delimiter, header, zero_one) in
                [(b',', true, true), (b' ', false, false), (b'\t', true, false)]
            {
                let text = encode_text(ev.view(), TextStyle { delimiter, time_unit: unit, header, zero_one });
                let opts = TextOptions { time_unit: Some(unit), ..Default::default() };
                assert_eq!(read(std::str::from_utf8(&text).unwrap(), &opts).unwrap(), ev);
            }
        }
    }
}

//! PLY: `ascii`, `binary_little_endian` and `binary_big_endian`, any
//! elements in any order. Vertices are loaded into memory; faces are
//! streamed (twice when normals must be computed), with a fast path for the
//! common binary little-endian `list uchar int` triangle layout.

use super::input::{Input, BUF_SIZE};
use super::{
    color_channel, Ids, ImportError, ImportOptions, ImportSummary, ModelFormat, ModelProbe,
    VertexTable,
};
use crate::mesh::Triangle;
use glam::Vec3;
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

fn arr<const N: usize>(b: &[u8]) -> [u8; N] {
    let mut a = [0u8; N];
    a.copy_from_slice(&b[..N]);
    a
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn name(self) -> &'static str {
        match self {
            Scalar::I8 => "char",
            Scalar::U8 => "uchar",
            Scalar::I16 => "short",
            Scalar::U16 => "ushort",
            Scalar::I32 => "int",
            Scalar::U32 => "uint",
            Scalar::F32 => "float",
            Scalar::F64 => "double",
        }
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Scalar::F32 | Scalar::F64)
    }

    fn range(self) -> (i64, i64) {
        match self {
            Scalar::I8 => (i8::MIN as i64, i8::MAX as i64),
            Scalar::U8 => (0, u8::MAX as i64),
            Scalar::I16 => (i16::MIN as i64, i16::MAX as i64),
            Scalar::U16 => (0, u16::MAX as i64),
            Scalar::I32 => (i32::MIN as i64, i32::MAX as i64),
            Scalar::U32 => (0, u32::MAX as i64),
            Scalar::F32 | Scalar::F64 => (i64::MIN, i64::MAX),
        }
    }

    #[inline]
    fn load(self, b: &[u8], big: bool) -> f64 {
        match self {
            Scalar::F32 => {
                let a = arr::<4>(b);
                (if big {
                    f32::from_be_bytes(a)
                } else {
                    f32::from_le_bytes(a)
                }) as f64
            }
            Scalar::F64 => {
                let a = arr::<8>(b);
                if big {
                    f64::from_be_bytes(a)
                } else {
                    f64::from_le_bytes(a)
                }
            }
            _ => self.load_int(b, big) as f64,
        }
    }

    #[inline]
    fn load_int(self, b: &[u8], big: bool) -> i64 {
        macro_rules! get {
            ($t:ty, $n:literal) => {{
                let a = arr::<$n>(b);
                (if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as i64
            }};
        }
        match self {
            Scalar::I8 => b[0] as i8 as i64,
            Scalar::U8 => b[0] as i64,
            Scalar::I16 => get!(i16, 2),
            Scalar::U16 => get!(u16, 2),
            Scalar::I32 => get!(i32, 4),
            Scalar::U32 => get!(u32, 4),
            Scalar::F32 | Scalar::F64 => self.load(b, big) as i64,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Encoding {
    Ascii,
    Le,
    Be,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Scalar(Scalar),
    /// Count type, item type.
    List(Scalar, Scalar),
}

#[derive(Debug)]
struct Prop {
    name: String,
    kind: Kind,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: u64,
    props: Vec<Prop>,
    /// Header line declaring the element.
    line: u64,
}

#[derive(Debug)]
struct Header {
    encoding: Encoding,
    elements: Vec<Element>,
    data_offset: u64,
    /// Line number of the first data line (ASCII).
    data_line: u64,
}

fn parse_header(inp: &mut Input) -> Result<Header, ImportError> {
    let path = inp.path.clone();
    inp.seek(0)?;
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut line_no = 0u64;
    loop {
        let (s, e) = match inp.line() {
            Ok(Some(r)) => r,
            Ok(None) => {
                return Err(ImportError::at_line(
                    &path,
                    line_no.max(1),
                    "the file ends before end_header",
                ))
            }
            Err(Some(e)) => return Err(e),
            Err(None) => {
                return Err(ImportError::at_line(
                    &path,
                    line_no + 1,
                    "header line too long (no end_header)",
                ))
            }
        };
        line_no += 1;
        if inp.offset() > BUF_SIZE as u64 {
            return Err(ImportError::at_line(
                &path,
                line_no,
                "header longer than 1 MiB (no end_header?)",
            ));
        }
        let err = |m: String| ImportError::at_line(&path, line_no, m);
        let text = std::str::from_utf8(&inp.buf[s..e])
            .map_err(|_| err("header line is not text (no end_header?)".into()))?;
        let words: Vec<&str> = text.split_ascii_whitespace().collect();
        if line_no == 1 {
            if words != ["ply"] {
                return Err(err("missing 'ply' magic line".into()));
            }
            continue;
        }
        let Some(&keyword) = words.first() else {
            continue;
        };
        match keyword {
            "comment" | "obj_info" => {}
            "format" => {
                encoding = Some(match words.get(1).copied() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary_little_endian") => Encoding::Le,
                    Some("binary_big_endian") => Encoding::Be,
                    Some(other) => return Err(err(format!("unknown format '{other}'"))),
                    None => return Err(err("format line without an encoding".into())),
                });
            }
            "element" => {
                let (Some(name), Some(count)) = (words.get(1), words.get(2)) else {
                    return Err(err("element line needs a name and a count".into()));
                };
                let count: u64 = count
                    .parse()
                    .map_err(|_| err(format!("invalid element count '{count}'")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                    line: line_no,
                });
            }
            "property" => {
                let Some(el) = elements.last_mut() else {
                    return Err(err("property before any element".into()));
                };
                let ty = |w: Option<&&str>| -> Result<Scalar, ImportError> {
                    let w = w.ok_or_else(|| err("incomplete property line".into()))?;
                    Scalar::parse(w).ok_or_else(|| err(format!("unknown property type '{w}'")))
                };
                let (kind, name) = if words.get(1) == Some(&"list") {
                    let count = ty(words.get(2))?;
                    let item = ty(words.get(3))?;
                    if count.is_float() {
                        return Err(err(format!(
                            "list count type '{}' is not an integer type",
                            count.name()
                        )));
                    }
                    (Kind::List(count, item), words.get(4))
                } else {
                    (Kind::Scalar(ty(words.get(1))?), words.get(2))
                };
                let name = name.ok_or_else(|| err("property without a name".into()))?;
                el.props.push(Prop {
                    name: name.to_string(),
                    kind,
                });
            }
            "end_header" => {
                let encoding =
                    encoding.ok_or_else(|| err("no format line before end_header".into()))?;
                return Ok(Header {
                    encoding,
                    elements,
                    data_offset: inp.offset(),
                    data_line: line_no + 1,
                });
            }
            other => return Err(err(format!("unknown header keyword '{other}'"))),
        }
    }
}

/// Where the importer finds what it needs in the header.
struct Layout {
    vertex: usize,
    face: usize,
    index_prop: usize,
    /// Per vertex property: slot 0..9 (x y z nx ny nz red green blue) or None.
    slots: Vec<Option<usize>>,
    color_float: [bool; 3],
    has_normals: bool,
    has_colors: bool,
}

fn layout(path: &Path, h: &Header, len: u64) -> Result<Layout, ImportError> {
    let vertex = h
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| ImportError::file(path, "no vertex element in the header"))?;
    let face = h
        .elements
        .iter()
        .position(|e| e.name == "face" && e.count > 0)
        .ok_or_else(|| {
            ImportError::file(
                path,
                "no faces (the header declares no face element or 0 faces)",
            )
        })?;
    let ve = &h.elements[vertex];
    let fe = &h.elements[face];
    let at = |e: &Element, m: String| ImportError::at_line(path, e.line, m);

    const NAMES: [&str; 9] = ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"];
    let mut found: [Option<usize>; 9] = [None; 9];
    for (pi, p) in ve.props.iter().enumerate() {
        if let Some(s) = NAMES.iter().position(|n| *n == p.name) {
            if found[s].is_none() {
                found[s] = Some(pi);
            }
        }
    }
    for (s, n) in NAMES.iter().enumerate().take(3) {
        match found[s] {
            None => return Err(at(ve, format!("vertex element has no '{n}' property"))),
            Some(pi) if !matches!(ve.props[pi].kind, Kind::Scalar(_)) => {
                return Err(at(ve, format!("vertex property '{n}' is a list")))
            }
            _ => {}
        }
    }
    let scalar_group = |r: std::ops::Range<usize>| {
        r.clone()
            .all(|s| found[s].is_some_and(|pi| matches!(ve.props[pi].kind, Kind::Scalar(_))))
    };
    let has_normals = scalar_group(3..6);
    let has_colors = scalar_group(6..9);
    let mut slots = vec![None; ve.props.len()];
    let mut color_float = [false; 3];
    for (s, f) in found.iter().enumerate() {
        let Some(pi) = *f else { continue };
        if s < 3 || (s < 6 && has_normals) || (s >= 6 && has_colors) {
            slots[pi] = Some(s);
        }
        if s >= 6 && has_colors {
            if let Kind::Scalar(t) = ve.props[pi].kind {
                color_float[s - 6] = t.is_float();
            }
        }
    }

    let lists: Vec<usize> = (0..fe.props.len())
        .filter(|&i| matches!(fe.props[i].kind, Kind::List(..)))
        .collect();
    let index_prop = lists
        .iter()
        .copied()
        .find(|&i| matches!(fe.props[i].name.as_str(), "vertex_indices" | "vertex_index"))
        .or(lists.first().copied())
        .ok_or_else(|| {
            at(
                fe,
                "face element has no list property (vertex indices)".into(),
            )
        })?;
    if let Kind::List(_, item) = fe.props[index_prop].kind {
        if item.is_float() {
            return Err(at(
                fe,
                format!("vertex index type '{}' is not an integer type", item.name()),
            ));
        }
    }

    // The counts must fit in the file: each record needs at least this many
    // bytes (lists may be empty). Checked before trusting any count.
    let avail = len.saturating_sub(h.data_offset) as u128;
    let mut need: u128 = 0;
    for e in &h.elements {
        let min: u128 = e
            .props
            .iter()
            .map(|p| match (h.encoding, p.kind) {
                (Encoding::Ascii, _) => 2,
                (_, Kind::Scalar(t)) | (_, Kind::List(t, _)) => t.size() as u128,
            })
            .sum();
        need += min * e.count as u128;
        let slack = if h.encoding == Encoding::Ascii { 1 } else { 0 };
        if need > avail + slack {
            let m = format!(
                "element '{}' (header line {}) declares {} records, more than the {} bytes of data after the header can hold (truncated file or wrong header counts)",
                e.name, e.line, e.count, avail
            );
            return Err(if h.encoding == Encoding::Ascii {
                at(e, m)
            } else {
                ImportError::at_byte(path, len, m)
            });
        }
    }
    if ve.count > u32::MAX as u64 {
        return Err(at(
            ve,
            format!("{} vertices is more than u32 indices allow", ve.count),
        ));
    }
    Ok(Layout {
        vertex,
        face,
        index_prop,
        slots,
        color_float,
        has_normals,
        has_colors,
    })
}

/// Reads values of the data section, binary or ASCII.
trait Values {
    type Mark: Copy;
    fn input(&mut self) -> &mut Input;
    fn set_element(&mut self, name: &str);
    /// Starts record `i` of the current element.
    fn begin(&mut self, i: u64);
    fn scalar(&mut self, t: Scalar) -> Result<f64, ImportError>;
    fn int(&mut self, t: Scalar) -> Result<i64, ImportError>;
    fn skip(&mut self, t: Scalar) -> Result<(), ImportError>;
    /// Errors unless `n` list items of type `t` can fit in the rest of the file.
    fn check_list(&mut self, n: i64, t: Scalar) -> Result<(), ImportError>;
    fn skip_list(&mut self, n: i64, t: Scalar) -> Result<(), ImportError>;
    /// Skips `count` fixed-size records of `stride` bytes if the encoding
    /// allows (binary); false if not done.
    fn skip_fixed(&mut self, count: u64, stride: u64) -> Result<bool, ImportError>;
    /// An error at the last value read.
    fn err_value(&self, m: String) -> ImportError;
    /// An error at the start of the current record.
    fn err_record(&self, m: String) -> ImportError;
    fn mark(&self) -> Self::Mark;
    fn restore(&mut self, m: Self::Mark) -> Result<(), ImportError>;
    /// The input, for the binary little-endian fast path.
    fn fast_le(&mut self) -> Option<&mut Input>;
    /// Binary only: consumes a whole fixed-size record of `stride` bytes and
    /// returns where it starts in `input().buf`, with the byte order.
    fn fixed_record(&mut self, stride: usize) -> Result<Option<(usize, bool)>, ImportError>;
}

struct Binary {
    inp: Input,
    big: bool,
    elem: String,
    record: u64,
    rec_off: u64,
    val_off: u64,
}

impl Binary {
    #[cold]
    fn eof(&self) -> ImportError {
        ImportError::at_byte(
            &self.inp.path,
            self.val_off,
            format!(
                "unexpected end of file in element '{}' record {} (the file is truncated or the header counts exceed the data)",
                self.elem, self.record
            ),
        )
    }

    #[inline]
    fn bytes(&mut self, n: usize) -> Result<usize, ImportError> {
        self.val_off = self.inp.offset();
        if !self.inp.fill(n)? {
            return Err(self.eof());
        }
        let at = self.inp.pos;
        self.inp.pos += n;
        Ok(at)
    }
}

impl Values for Binary {
    type Mark = u64;
    fn input(&mut self) -> &mut Input {
        &mut self.inp
    }
    fn set_element(&mut self, name: &str) {
        self.elem = name.to_string();
    }
    #[inline]
    fn begin(&mut self, i: u64) {
        self.record = i;
        self.rec_off = self.inp.offset();
    }
    #[inline]
    fn scalar(&mut self, t: Scalar) -> Result<f64, ImportError> {
        let at = self.bytes(t.size())?;
        Ok(t.load(&self.inp.buf[at..], self.big))
    }
    #[inline]
    fn int(&mut self, t: Scalar) -> Result<i64, ImportError> {
        let at = self.bytes(t.size())?;
        Ok(t.load_int(&self.inp.buf[at..], self.big))
    }
    #[inline]
    fn skip(&mut self, t: Scalar) -> Result<(), ImportError> {
        self.bytes(t.size()).map(|_| ())
    }
    fn check_list(&mut self, n: i64, t: Scalar) -> Result<(), ImportError> {
        if n < 0 {
            return Err(self.err_value(format!(
                "element '{}' record {}: negative list count {n}",
                self.elem, self.record
            )));
        }
        if (n as u128) * (t.size() as u128) > self.inp.remaining() as u128 {
            return Err(self.err_value(format!(
                "element '{}' record {}: list of {n} items runs past the end of the file",
                self.elem, self.record
            )));
        }
        Ok(())
    }
    fn skip_list(&mut self, n: i64, t: Scalar) -> Result<(), ImportError> {
        self.check_list(n, t)?;
        self.inp.skip(n as u64 * t.size() as u64)?;
        Ok(())
    }
    fn skip_fixed(&mut self, count: u64, stride: u64) -> Result<bool, ImportError> {
        self.val_off = self.inp.offset();
        let n = (count as u128) * (stride as u128);
        if n > self.inp.remaining() as u128 || !self.inp.skip(n as u64)? {
            self.record = self.inp.remaining() / stride.max(1);
            return Err(self.eof());
        }
        Ok(true)
    }
    fn err_value(&self, m: String) -> ImportError {
        ImportError::at_byte(&self.inp.path, self.val_off, m)
    }
    fn err_record(&self, m: String) -> ImportError {
        ImportError::at_byte(&self.inp.path, self.rec_off, m)
    }
    fn mark(&self) -> u64 {
        self.inp.offset()
    }
    fn restore(&mut self, m: u64) -> Result<(), ImportError> {
        self.inp.seek(m)
    }
    #[inline]
    fn fixed_record(&mut self, stride: usize) -> Result<Option<(usize, bool)>, ImportError> {
        if !self.inp.fill(stride)? {
            self.val_off = self.rec_off;
            return Err(self.eof());
        }
        let at = self.inp.pos;
        self.inp.pos += stride;
        Ok(Some((at, self.big)))
    }
    fn fast_le(&mut self) -> Option<&mut Input> {
        if self.big {
            None
        } else {
            Some(&mut self.inp)
        }
    }
}

/// Longest ASCII token accepted.
const MAX_TOKEN: usize = 4096;

struct Ascii {
    inp: Input,
    /// Line of `inp.pos`.
    line: u64,
    elem: String,
    record: u64,
    rec_line: u64,
    val_line: u64,
    /// A record began: its line is that of its first token.
    rec_pending: bool,
}

impl Ascii {
    /// The next whitespace-separated token, as a range of `inp.buf`.
    fn token(&mut self) -> Result<(usize, usize), ImportError> {
        loop {
            while self.inp.pos < self.inp.end {
                let c = self.inp.buf[self.inp.pos];
                if !c.is_ascii_whitespace() {
                    break;
                }
                if c == b'\n' {
                    self.line += 1;
                }
                self.inp.pos += 1;
            }
            if self.inp.pos < self.inp.end {
                break;
            }
            if !self.inp.fill(1)? {
                self.val_line = self.line;
                return Err(ImportError::at_line(
                    &self.inp.path,
                    self.line,
                    format!(
                        "unexpected end of file in element '{}' record {} (the file is truncated or the header counts exceed the data)",
                        self.elem, self.record
                    ),
                ));
            }
        }
        self.val_line = self.line;
        if self.rec_pending {
            self.rec_pending = false;
            self.rec_line = self.line;
        }
        let mut len = 0;
        loop {
            let start = self.inp.pos;
            while start + len < self.inp.end && !self.inp.buf[start + len].is_ascii_whitespace() {
                len += 1;
            }
            if start + len < self.inp.end {
                break;
            }
            if len > MAX_TOKEN {
                return Err(self.err_value("token too long".into()));
            }
            if !self.inp.fill(len + 1)? {
                break;
            }
        }
        let start = self.inp.pos;
        self.inp.pos += len;
        Ok((start, start + len))
    }

    fn text(&mut self) -> Result<&str, ImportError> {
        let (s, e) = self.token()?;
        match std::str::from_utf8(&self.inp.buf[s..e]) {
            Ok(t) => Ok(t),
            Err(_) => Err(ImportError::at_line(
                &self.inp.path,
                self.val_line,
                "invalid (non-text) value",
            )),
        }
    }

    fn bad(&self, t: Scalar, v: &str) -> ImportError {
        let v: String = v.chars().take(40).collect();
        self.err_value(format!(
            "element '{}' record {}: invalid {} value '{v}'",
            self.elem,
            self.record,
            t.name()
        ))
    }
}

impl Values for Ascii {
    type Mark = (u64, u64);
    fn input(&mut self) -> &mut Input {
        &mut self.inp
    }
    fn set_element(&mut self, name: &str) {
        self.elem = name.to_string();
    }
    fn begin(&mut self, i: u64) {
        self.record = i;
        self.rec_line = self.line;
        self.rec_pending = true;
    }
    fn scalar(&mut self, t: Scalar) -> Result<f64, ImportError> {
        if !t.is_float() {
            return self.int(t).map(|v| v as f64);
        }
        let s = self.text()?;
        match s.parse::<f64>() {
            Ok(v) => Ok(v),
            Err(_) => {
                let s = s.to_string();
                Err(self.bad(t, &s))
            }
        }
    }
    fn int(&mut self, t: Scalar) -> Result<i64, ImportError> {
        let s = self.text()?;
        let v = if t.is_float() {
            s.parse::<f64>().ok().map(|v| v as i64)
        } else {
            s.parse::<i64>().ok()
        };
        let (lo, hi) = t.range();
        match v {
            Some(v) if v >= lo && v <= hi => Ok(v),
            _ => {
                let s = s.to_string();
                Err(self.bad(t, &s))
            }
        }
    }
    fn skip(&mut self, t: Scalar) -> Result<(), ImportError> {
        self.scalar(t).map(|_| ())
    }
    fn check_list(&mut self, n: i64, _t: Scalar) -> Result<(), ImportError> {
        if n < 0 {
            return Err(self.err_value(format!(
                "element '{}' record {}: negative list count {n}",
                self.elem, self.record
            )));
        }
        if (n as u128) * 2 > self.inp.remaining() as u128 + 1 {
            return Err(self.err_value(format!(
                "element '{}' record {}: list of {n} items runs past the end of the file",
                self.elem, self.record
            )));
        }
        Ok(())
    }
    fn skip_list(&mut self, n: i64, t: Scalar) -> Result<(), ImportError> {
        self.check_list(n, t)?;
        for _ in 0..n {
            self.skip(t)?;
        }
        Ok(())
    }
    fn skip_fixed(&mut self, _count: u64, _stride: u64) -> Result<bool, ImportError> {
        Ok(false)
    }
    fn err_value(&self, m: String) -> ImportError {
        ImportError::at_line(&self.inp.path, self.val_line, m)
    }
    fn err_record(&self, m: String) -> ImportError {
        ImportError::at_line(&self.inp.path, self.rec_line, m)
    }
    fn mark(&self) -> (u64, u64) {
        (self.inp.offset(), self.line)
    }
    fn restore(&mut self, m: (u64, u64)) -> Result<(), ImportError> {
        self.line = m.1;
        self.inp.seek(m.0)
    }
    fn fast_le(&mut self) -> Option<&mut Input> {
        None
    }
    fn fixed_record(&mut self, _stride: usize) -> Result<Option<(usize, bool)>, ImportError> {
        Ok(None)
    }
}

fn skip_element<V: Values>(v: &mut V, e: &Element) -> Result<(), ImportError> {
    let fixed: Option<u64> = e
        .props
        .iter()
        .map(|p| match p.kind {
            Kind::Scalar(t) => Some(t.size() as u64),
            Kind::List(..) => None,
        })
        .sum();
    if let Some(stride) = fixed {
        v.begin(0);
        if v.skip_fixed(e.count, stride)? {
            return Ok(());
        }
    }
    for i in 0..e.count {
        v.begin(i);
        for p in &e.props {
            match p.kind {
                Kind::Scalar(t) => v.skip(t)?,
                Kind::List(c, t) => {
                    let n = v.int(c)?;
                    v.skip_list(n, t)?;
                }
            }
        }
    }
    Ok(())
}

/// A vertex property in a fixed-size record: (slot, byte offset, type).
type UsedProp = (usize, usize, Scalar);

fn load_vertices<V: Values>(
    v: &mut V,
    e: &Element,
    lay: &Layout,
    opts: &ImportOptions,
) -> Result<VertexTable, ImportError> {
    let n = e.count;
    let bytes = n as u128 * VertexTable::bytes_per_vertex(lay.has_colors) as u128;
    if bytes > opts.max_vertex_bytes as u128 {
        let path = v.input().path.clone();
        return Err(ImportError::at_line(
            &path,
            e.line,
            format!(
                "{n} vertices need {bytes} bytes of memory, more than the memory budget of {} bytes (ImportOptions::max_vertex_bytes)",
                opts.max_vertex_bytes
            ),
        ));
    }
    let n = n as usize;
    let alloc_err = |v: &mut V| {
        let path = v.input().path.clone();
        ImportError::file(&path, format!("cannot allocate memory for {n} vertices"))
    };
    let mut positions: Vec<Vec3> = Vec::new();
    let mut normals: Vec<Vec3> = Vec::new();
    positions.try_reserve_exact(n).map_err(|_| alloc_err(v))?;
    normals.try_reserve_exact(n).map_err(|_| alloc_err(v))?;
    let mut colors = if lay.has_colors {
        let mut c: Vec<[u8; 4]> = Vec::new();
        c.try_reserve_exact(n).map_err(|_| alloc_err(v))?;
        Some(c)
    } else {
        None
    };
    // Fixed-size records (no lists): the byte offset of each used property.
    let mut fixed: Option<(usize, Vec<UsedProp>)> = Some((0, Vec::new()));
    for (p, slot) in e.props.iter().zip(&lay.slots) {
        match (p.kind, &mut fixed) {
            (Kind::Scalar(t), Some((stride, used))) => {
                if let Some(s) = slot {
                    used.push((*s, *stride, t));
                }
                *stride += t.size();
            }
            _ => fixed = None,
        }
    }
    let fixed = fixed.filter(|(stride, _)| *stride > 0 && *stride <= 1024);
    for i in 0..e.count {
        v.begin(i);
        let mut vals = [0f64; 9];
        let mut done = false;
        if let Some((stride, used)) = &fixed {
            if let Some((at, big)) = v.fixed_record(*stride)? {
                let buf = &v.input().buf[at..];
                for &(s, off, t) in used {
                    vals[s] = t.load(&buf[off..], big);
                }
                done = true;
            }
        }
        for (p, slot) in e.props.iter().zip(&lay.slots) {
            if done {
                break;
            }
            match (p.kind, slot) {
                (Kind::Scalar(t), Some(s)) => vals[*s] = v.scalar(t)?,
                (Kind::Scalar(t), None) => v.skip(t)?,
                (Kind::List(c, t), _) => {
                    let k = v.int(c)?;
                    v.skip_list(k, t)?;
                }
            }
        }
        let p = Vec3::new(vals[0] as f32, vals[1] as f32, vals[2] as f32);
        if !p.is_finite() {
            let what = if p.is_nan() {
                "a NaN coordinate"
            } else {
                "an infinite coordinate (or one too large for f32)"
            };
            return Err(v.err_record(format!("vertex {i} has {what}")));
        }
        positions.push(p);
        normals.push(if lay.has_normals {
            Vec3::new(vals[3] as f32, vals[4] as f32, vals[5] as f32).normalize_or_zero()
        } else {
            Vec3::ZERO
        });
        if let Some(c) = &mut colors {
            c.push([
                color_channel(vals[6], lay.color_float[0]),
                color_channel(vals[7], lay.color_float[1]),
                color_channel(vals[8], lay.color_float[2]),
                255,
            ]);
        }
    }
    Ok(VertexTable {
        positions,
        normals,
        colors,
    })
}

#[inline]
fn index<V: Values>(v: &mut V, t: Scalar, nverts: u32, f: u64) -> Result<u32, ImportError> {
    let i = v.int(t)?;
    if i < 0 {
        Err(v.err_value(format!("face {f}: negative vertex index {i}")))
    } else if i >= nverts as i64 {
        Err(v.err_value(format!(
            "face {f}: vertex index {i} out of range (the model has {nverts} vertices)"
        )))
    } else {
        Ok(i as u32)
    }
}

/// Streams the triangles (fans) of the face element from the current place.
fn faces<V: Values>(
    v: &mut V,
    fe: &Element,
    ip: usize,
    nverts: u32,
    mut tri: impl FnMut([u32; 3]) -> Result<(), ImportError>,
) -> Result<(), ImportError> {
    if let [Prop {
        kind: Kind::List(Scalar::U8, it @ (Scalar::I32 | Scalar::U32)),
        ..
    }] = fe.props.as_slice()
    {
        let signed = *it == Scalar::I32;
        if let Some(inp) = v.fast_le() {
            return faces_fast_le(inp, fe.count, nverts, signed, tri);
        }
    }
    for f in 0..fe.count {
        v.begin(f);
        for (pi, p) in fe.props.iter().enumerate() {
            match p.kind {
                Kind::Scalar(t) => v.skip(t)?,
                Kind::List(c, t) => {
                    let n = v.int(c)?;
                    if pi != ip {
                        v.skip_list(n, t)?;
                        continue;
                    }
                    if n < 3 {
                        return Err(v.err_value(format!(
                            "face {f} has {n} vertices; a face needs at least 3"
                        )));
                    }
                    v.check_list(n, t)?;
                    let a = index(v, t, nverts, f)?;
                    let mut b = index(v, t, nverts, f)?;
                    for _ in 2..n {
                        let c = index(v, t, nverts, f)?;
                        tri([a, b, c])?;
                        b = c;
                    }
                }
            }
        }
    }
    Ok(())
}

/// Binary little-endian faces whose only property is `list uchar int|uint`.
fn faces_fast_le(
    inp: &mut Input,
    count: u64,
    nverts: u32,
    signed: bool,
    mut tri: impl FnMut([u32; 3]) -> Result<(), ImportError>,
) -> Result<(), ImportError> {
    #[cold]
    fn bad(inp: &Input, at: usize, f: u64, v: u32, signed: bool, nverts: u32) -> ImportError {
        let off = inp.base + at as u64;
        if signed && (v as i32) < 0 {
            ImportError::at_byte(
                &inp.path,
                off,
                format!("face {f}: negative vertex index {}", v as i32),
            )
        } else {
            ImportError::at_byte(
                &inp.path,
                off,
                format!(
                    "face {f}: vertex index {v} out of range (the model has {nverts} vertices)"
                ),
            )
        }
    }
    #[inline(always)]
    fn rd(b: &[u8], at: usize) -> u32 {
        u32::from_le_bytes(arr::<4>(&b[at..]))
    }
    for f in 0..count {
        if inp.available() < 13 && !inp.fill(13)? && inp.available() == 0 {
            return Err(ImportError::at_byte(
                &inp.path,
                inp.offset(),
                format!("unexpected end of file in element 'face' record {f} (the file is truncated or the header counts exceed the data)"),
            ));
        }
        let p = inp.pos;
        let n = inp.buf[p] as usize;
        if n == 3 && inp.available() >= 13 {
            let (a, b, c) = (
                rd(&inp.buf, p + 1),
                rd(&inp.buf, p + 5),
                rd(&inp.buf, p + 9),
            );
            if a >= nverts || b >= nverts || c >= nverts {
                let (k, v) = if a >= nverts {
                    (0, a)
                } else if b >= nverts {
                    (1, b)
                } else {
                    (2, c)
                };
                return Err(bad(inp, p + 1 + 4 * k, f, v, signed, nverts));
            }
            inp.pos = p + 13;
            tri([a, b, c])?;
            continue;
        }
        if n < 3 {
            return Err(ImportError::at_byte(
                &inp.path,
                inp.offset(),
                format!("face {f} has {n} vertices; a face needs at least 3"),
            ));
        }
        let need = 1 + 4 * n;
        if !inp.fill(need)? {
            return Err(ImportError::at_byte(
                &inp.path,
                inp.offset(),
                format!("element 'face' record {f}: list of {n} items runs past the end of the file (truncated?)"),
            ));
        }
        let p = inp.pos;
        for k in 0..n {
            let v = rd(&inp.buf, p + 1 + 4 * k);
            if v >= nverts {
                return Err(bad(inp, p + 1 + 4 * k, f, v, signed, nverts));
            }
        }
        inp.pos = p + need;
        let a = rd(&inp.buf, p + 1);
        let mut b = rd(&inp.buf, p + 5);
        for k in 2..n {
            let c = rd(&inp.buf, p + 1 + 4 * k);
            tri([a, b, c])?;
            b = c;
        }
    }
    Ok(())
}

fn run<V: Values>(
    v: &mut V,
    h: &Header,
    lay: &Layout,
    first_id: u32,
    opts: &ImportOptions,
    sink: &mut dyn FnMut(&Triangle) -> std::io::Result<()>,
) -> Result<ImportSummary, ImportError> {
    let path = v.input().path.clone();
    let t0 = std::time::Instant::now();
    let mut table = None;
    let mut face_mark = None;
    for (ei, e) in h.elements.iter().enumerate() {
        v.set_element(&e.name);
        if ei == lay.vertex {
            table = Some(load_vertices(v, e, lay, opts)?);
            if face_mark.is_some() {
                break;
            }
        } else if ei == lay.face {
            face_mark = Some(v.mark());
            if table.is_some() {
                break;
            }
            skip_element(v, e)?;
        } else {
            skip_element(v, e)?;
        }
    }
    let (Some(mut table), Some(face_mark)) = (table, face_mark) else {
        return Err(ImportError::file(
            &path,
            "internal error: elements not found",
        ));
    };
    let fe = &h.elements[lay.face];
    tracing::debug!("{}: vertices loaded in {:?}", path.display(), t0.elapsed());
    v.set_element(&fe.name);
    let nverts = table.positions.len() as u32;
    let mut ids = Ids::new(first_id);
    if !lay.has_normals {
        v.restore(face_mark)?;
        let mut count = 0u64;
        faces(v, fe, lay.index_prop, nverts, |idx| {
            table.accumulate(idx);
            count += 1;
            Ok(())
        })?;
        table.normalize();
        ids.check(&path, count)?;
        tracing::debug!("{}: normals computed at {:?}", path.display(), t0.elapsed());
    }
    v.restore(face_mark)?;
    let mut triangles = 0u64;
    faces(v, fe, lay.index_prop, nverts, |idx| {
        let id = ids.next(&path)?;
        let t = table.triangle(idx, table.vertex_normals(idx), id);
        triangles += 1;
        sink(&t).map_err(|e| ImportError::sink(&path, e))
    })?;
    Ok(ImportSummary {
        vertices: nverts as u64,
        triangles,
        has_normals: lay.has_normals,
        has_colors: lay.has_colors,
    })
}

pub(crate) fn import(
    mut inp: Input,
    first_id: u32,
    opts: &ImportOptions,
    sink: &mut dyn FnMut(&Triangle) -> std::io::Result<()>,
) -> Result<ImportSummary, ImportError> {
    let h = parse_header(&mut inp)?;
    let lay = layout(&inp.path.clone(), &h, inp.len())?;
    match h.encoding {
        Encoding::Ascii => {
            let mut v = Ascii {
                inp,
                line: h.data_line,
                elem: String::new(),
                record: 0,
                rec_line: h.data_line,
                val_line: h.data_line,
                rec_pending: false,
            };
            run(&mut v, &h, &lay, first_id, opts, sink)
        }
        Encoding::Le | Encoding::Be => {
            let off = h.data_offset;
            let mut v = Binary {
                inp,
                big: h.encoding == Encoding::Be,
                elem: String::new(),
                record: 0,
                rec_off: off,
                val_off: off,
            };
            run(&mut v, &h, &lay, first_id, opts, sink)
        }
    }
}

pub(crate) fn probe(mut inp: Input) -> Result<ModelProbe, ImportError> {
    let h = parse_header(&mut inp)?;
    let count = |name: &str| {
        h.elements
            .iter()
            .find(|e| e.name == name)
            .map_or(0, |e| e.count)
    };
    Ok(ModelProbe {
        format: ModelFormat::Ply,
        vertices: count("vertex"),
        faces: count("face"),
    })
}

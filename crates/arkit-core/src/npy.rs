//! NumPy `.npy` and `.npz` files, read and written as numpy does.
//!
//! A `.npy` file is the magic `\x93NUMPY`, a version (1.0, 2.0 or 3.0), a little-endian
//! header length (2 bytes in 1.0, 4 bytes after), a Python dict literal
//! `{'descr': '<f4', 'fortran_order': False, 'shape': (1220, 3), }` padded with spaces
//! to a multiple of 64 bytes and ended by `\n`, then the raw data. An `.npz` is a zip
//! archive of `.npy` members (`savez` stores them, `savez_compressed` deflates them).
//!
//! Supported: bool, (u)int8/16/32/64 and float32/64 in either byte order, C and Fortran
//! order (Fortran data is returned in C order), any number of dimensions. Anything else
//! (object arrays, strings, structured dtypes, complex) is refused with an error naming
//! the file and the dtype.
//!
//! Bounded reading (see [`crate::limits`]): nothing is allocated from a size the file
//! states before that size is checked. A header is at most
//! [`limits::MAX_NPY_HEADER_BYTES`]; its shape times the element size (overflow-checked)
//! is checked against [`limits::MAX_ARRAY_BYTES`] before the data is read; the data is
//! then read as a stream, exactly the declared bytes. Up to
//! [`limits::MAX_NPY_TRAILING_BYTES`] bytes after the data are ignored, as numpy ignores
//! them; more are refused, so that a file with gigabytes after a valid array is not read
//! through. `.npz` archives: at most [`limits::MAX_NPZ_MEMBERS`] members and
//! `limits::MAX_NPZ_ARRAY_BYTES` of data in all; the zip directory's size claims are
//! never trusted (members are read through capped streams), and a deflated member is
//! refused from its header before it is inflated. Files are checked against
//! `limits::MAX_NPY_FILE_BYTES` / [`limits::MAX_NPZ_FILE_BYTES`] before reading.
//! Tested below with crafted bytes for each limit, in `tests/bounded_memory.rs` (peak
//! allocation while reading hostile files), and by the `npy` and `npz` fuzz targets.
//!
//! Writing produces version 1.0 files byte-identical to numpy's for C-order
//! little-endian arrays, and zip archives with fixed timestamps, so output is
//! deterministic.

use crate::error::{Error, Result};
use crate::limits;
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

/// Element types this module reads and writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DType {
    /// `|b1`
    Bool,
    /// `|u1`
    U8,
    /// `|i1`
    I8,
    /// `<u2`
    U16,
    /// `<i2`
    I16,
    /// `<u4`
    U32,
    /// `<i4`
    I32,
    /// `<u8`
    U64,
    /// `<i8`
    I64,
    /// `<f4`
    F32,
    /// `<f8`
    F64,
}

impl DType {
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::Bool | DType::U8 | DType::I8 => 1,
            DType::U16 | DType::I16 => 2,
            DType::U32 | DType::I32 | DType::F32 => 4,
            DType::U64 | DType::I64 | DType::F64 => 8,
        }
    }

    /// numpy's little-endian descr string (`<f4`, `|u1`, ...).
    pub fn descr(self) -> &'static str {
        match self {
            DType::Bool => "|b1",
            DType::U8 => "|u1",
            DType::I8 => "|i1",
            DType::U16 => "<u2",
            DType::I16 => "<i2",
            DType::U32 => "<u4",
            DType::I32 => "<i4",
            DType::U64 => "<u8",
            DType::I64 => "<i8",
            DType::F32 => "<f4",
            DType::F64 => "<f8",
        }
    }

    /// Parses a descr; returns the dtype and whether the data is big-endian.
    fn parse(descr: &str) -> Option<(DType, bool)> {
        if !descr.is_ascii() {
            return None;
        }
        let (order, code) = descr.split_at(descr.len().checked_sub(2)?);
        let big = match order {
            ">" => true,
            "<" | "|" | "" => false,
            "=" => cfg!(target_endian = "big"),
            _ => return None,
        };
        let t = match code {
            "b1" => DType::Bool,
            "u1" => DType::U8,
            "i1" => DType::I8,
            "u2" => DType::U16,
            "i2" => DType::I16,
            "u4" => DType::U32,
            "i4" => DType::I32,
            "u8" => DType::U64,
            "i8" => DType::I64,
            "f4" => DType::F32,
            "f8" => DType::F64,
            _ => return None,
        };
        Some((t, big))
    }
}

/// The values of an array, in C (row-major) order.
#[derive(Clone, Debug, PartialEq)]
pub enum ArrayData {
    /// bool
    Bool(Vec<bool>),
    /// uint8
    U8(Vec<u8>),
    /// int8
    I8(Vec<i8>),
    /// uint16
    U16(Vec<u16>),
    /// int16
    I16(Vec<i16>),
    /// uint32
    U32(Vec<u32>),
    /// int32
    I32(Vec<i32>),
    /// uint64
    U64(Vec<u64>),
    /// int64
    I64(Vec<i64>),
    /// float32
    F32(Vec<f32>),
    /// float64
    F64(Vec<f64>),
}

macro_rules! each_variant {
    ($data:expr, $v:ident => $body:expr) => {
        match $data {
            ArrayData::Bool($v) => $body,
            ArrayData::U8($v) => $body,
            ArrayData::I8($v) => $body,
            ArrayData::U16($v) => $body,
            ArrayData::I16($v) => $body,
            ArrayData::U32($v) => $body,
            ArrayData::I32($v) => $body,
            ArrayData::U64($v) => $body,
            ArrayData::I64($v) => $body,
            ArrayData::F32($v) => $body,
            ArrayData::F64($v) => $body,
        }
    };
}

impl ArrayData {
    /// Number of elements.
    pub fn len(&self) -> usize {
        each_variant!(self, v => v.len())
    }

    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The element type.
    pub fn dtype(&self) -> DType {
        match self {
            ArrayData::Bool(_) => DType::Bool,
            ArrayData::U8(_) => DType::U8,
            ArrayData::I8(_) => DType::I8,
            ArrayData::U16(_) => DType::U16,
            ArrayData::I16(_) => DType::I16,
            ArrayData::U32(_) => DType::U32,
            ArrayData::I32(_) => DType::I32,
            ArrayData::U64(_) => DType::U64,
            ArrayData::I64(_) => DType::I64,
            ArrayData::F32(_) => DType::F32,
            ArrayData::F64(_) => DType::F64,
        }
    }
}

/// An n-dimensional array: shape and C-order data.
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    shape: Vec<usize>,
    data: ArrayData,
}

impl NpyArray {
    /// An array; errors unless the product of `shape` is the number of values.
    pub fn new(shape: Vec<usize>, data: ArrayData) -> Result<Self> {
        let n = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        if n != Some(data.len()) {
            let n = n.map_or("more than usize::MAX".to_string(), |n| n.to_string());
            return Err(Error::invalid(
                "array",
                format!("shape {shape:?} holds {n} values, {} given", data.len()),
            ));
        }
        Ok(NpyArray { shape, data })
    }

    /// A float32 array.
    pub fn from_f32(shape: Vec<usize>, data: Vec<f32>) -> Result<Self> {
        Self::new(shape, ArrayData::F32(data))
    }

    /// A float64 array.
    pub fn from_f64(shape: Vec<usize>, data: Vec<f64>) -> Result<Self> {
        Self::new(shape, ArrayData::F64(data))
    }

    /// An int64 array.
    pub fn from_i64(shape: Vec<usize>, data: Vec<i64>) -> Result<Self> {
        Self::new(shape, ArrayData::I64(data))
    }

    /// The shape (empty for a 0-d array).
    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    /// The element type.
    pub fn dtype(&self) -> DType {
        self.data.dtype()
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The values.
    pub fn data(&self) -> &ArrayData {
        &self.data
    }

    /// All values as f64 (exact for every dtype but 64-bit integers beyond 2^53).
    pub fn to_f64_vec(&self) -> Vec<f64> {
        match &self.data {
            ArrayData::Bool(v) => v.iter().map(|&b| b as u8 as f64).collect(),
            ArrayData::F32(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::F64(v) => v.clone(),
            ArrayData::U8(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::I8(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::U16(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::I16(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::U32(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::I32(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::U64(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::I64(v) => v.iter().map(|&x| x as f64).collect(),
        }
    }

    /// All values as f32 (rounded for float64 and large integers).
    pub fn to_f32_vec(&self) -> Vec<f32> {
        match &self.data {
            ArrayData::F32(v) => v.clone(),
            _ => self.to_f64_vec().into_iter().map(|x| x as f32).collect(),
        }
    }

    /// All values as i64; errors for floating-point arrays and for uint64 values above
    /// `i64::MAX`.
    pub fn to_i64_vec(&self) -> Result<Vec<i64>> {
        let ints = |v: Vec<i64>| Ok(v);
        match &self.data {
            ArrayData::F32(_) | ArrayData::F64(_) => Err(Error::invalid(
                "array",
                format!("expected integers, found {}", self.dtype().descr()),
            )),
            ArrayData::Bool(v) => ints(v.iter().map(|&b| b as i64).collect()),
            ArrayData::U8(v) => ints(v.iter().map(|&x| x as i64).collect()),
            ArrayData::I8(v) => ints(v.iter().map(|&x| x as i64).collect()),
            ArrayData::U16(v) => ints(v.iter().map(|&x| x as i64).collect()),
            ArrayData::I16(v) => ints(v.iter().map(|&x| x as i64).collect()),
            ArrayData::U32(v) => ints(v.iter().map(|&x| x as i64).collect()),
            ArrayData::I32(v) => ints(v.iter().map(|&x| x as i64).collect()),
            ArrayData::I64(v) => ints(v.clone()),
            ArrayData::U64(v) => v
                .iter()
                .map(|&x| {
                    i64::try_from(x).map_err(|_| {
                        Error::invalid("array", format!("value {x} does not fit in int64"))
                    })
                })
                .collect(),
        }
    }
}

/// The parsed header of a `.npy` file.
#[derive(Clone, Debug, PartialEq)]
struct Header {
    dtype: DType,
    big_endian: bool,
    fortran_order: bool,
    shape: Vec<usize>,
}

/// Parses the header dict literal.
fn parse_header_dict(text: &str) -> std::result::Result<(String, bool, Vec<usize>), String> {
    let t = text.trim().trim_end_matches('\n').trim();
    let inner = t
        .strip_prefix('{')
        .and_then(|s| s.strip_suffix('}'))
        .ok_or_else(|| format!("header is not a dict: {t:?}"))?;
    let mut descr = None;
    let mut fortran = None;
    let mut shape = None;
    let mut rest = inner.trim();
    while !rest.is_empty() {
        let quote = rest
            .chars()
            .next()
            .filter(|c| *c == '\'' || *c == '"')
            .ok_or_else(|| format!("expected a quoted key at {rest:?}"))?;
        let end = rest[1..].find(quote).ok_or("unterminated key")? + 1;
        let key = &rest[1..end];
        rest = rest[end + 1..]
            .trim_start()
            .strip_prefix(':')
            .ok_or("expected ':' after a key")?
            .trim_start();
        // Value: a quoted string, True/False, or a tuple.
        let (value, after) = if rest.starts_with('\'') || rest.starts_with('"') {
            let q = rest.chars().next().unwrap_or('\'');
            let e = rest[1..].find(q).ok_or("unterminated string value")? + 1;
            (&rest[..=e], &rest[e + 1..])
        } else if rest.starts_with('(') {
            let e = rest.find(')').ok_or("unterminated tuple")?;
            (&rest[..=e], &rest[e + 1..])
        } else {
            let e = rest.find(',').unwrap_or(rest.len());
            (rest[..e].trim(), &rest[e..])
        };
        match key {
            "descr" => {
                if !(value.starts_with('\'') || value.starts_with('"')) {
                    return Err(format!(
                        "unsupported dtype {value} (structured or record arrays are not supported)"
                    ));
                }
                descr = Some(value[1..value.len() - 1].to_string());
            }
            "fortran_order" => {
                fortran = Some(match value {
                    "True" => true,
                    "False" => false,
                    _ => {
                        return Err(format!(
                            "fortran_order must be True or False, found {value}"
                        ));
                    }
                })
            }
            "shape" => {
                let body = value.trim_start_matches('(').trim_end_matches(')');
                let dims: std::result::Result<Vec<usize>, String> = body
                    .split(',')
                    .map(|d| d.trim())
                    .filter(|d| !d.is_empty())
                    .map(|d| {
                        d.trim_end_matches('L')
                            .parse::<usize>()
                            .map_err(|_| format!("bad dimension {d:?} in shape {value}"))
                    })
                    .collect();
                shape = Some(dims?);
            }
            other => return Err(format!("unexpected header key '{other}'")),
        }
        rest = after.trim_start();
        rest = rest.strip_prefix(',').unwrap_or(rest).trim_start();
    }
    Ok((
        descr.ok_or("header has no 'descr'")?,
        fortran.ok_or("header has no 'fortran_order'")?,
        shape.ok_or("header has no 'shape'")?,
    ))
}

/// Parses `.npy` bytes; `source` names the file in errors. At most
/// [`limits::MAX_NPY_TRAILING_BYTES`] bytes may follow the data (see the module docs).
pub fn parse_npy(bytes: &[u8], source: &Path) -> Result<NpyArray> {
    let io = |e: std::io::Error| Error::format(source, format!("cannot read: {e}"));
    let mut r = bytes;
    read_npy_from(&mut r, source, limits::MAX_ARRAY_BYTES, "per array", &io).map(|(a, _)| a)
}

/// Reads into `buf` until it is full or the reader ends; returns the count read.
fn read_up_to<R: Read + ?Sized>(r: &mut R, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(k) => got += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// Reads one array from a stream: the header (at most
/// [`limits::MAX_NPY_HEADER_BYTES`]), then exactly the data it declares (checked against
/// `max_data`, named `limit_name` in the error, before any of it is read), then at most
/// [`limits::MAX_NPY_TRAILING_BYTES`] + 1 bytes to check the tail. Memory is bounded by
/// the declared data size, never by what the stream claims elsewhere. Returns the array
/// and its data size in bytes.
fn read_npy_from<R: Read + ?Sized>(
    r: &mut R,
    source: &Path,
    max_data: u64,
    limit_name: &str,
    io: &dyn Fn(std::io::Error) -> Error,
) -> Result<(NpyArray, u64)> {
    let err = |m: String| Error::format(source, m);
    let mut pre = [0u8; 12];
    if read_up_to(r, &mut pre[..10]).map_err(io)? < 10 || &pre[..6] != b"\x93NUMPY" {
        return Err(err("not a .npy file (magic bytes missing)".into()));
    }
    let (major, minor) = (pre[6], pre[7]);
    let header_len = match major {
        1 => u16::from_le_bytes([pre[8], pre[9]]) as usize,
        2 | 3 => {
            if read_up_to(r, &mut pre[10..12]).map_err(io)? < 2 {
                return Err(err("truncated header".into()));
            }
            u32::from_le_bytes([pre[8], pre[9], pre[10], pre[11]]) as usize
        }
        _ => {
            return Err(err(format!(
                "unsupported .npy format version {major}.{minor}"
            )));
        }
    };
    if header_len > limits::MAX_NPY_HEADER_BYTES {
        return Err(err(format!(
            "header length {header_len} is more than the {} bytes allowed (numpy's own limit)",
            limits::MAX_NPY_HEADER_BYTES
        )));
    }
    let mut raw = vec![0u8; header_len];
    if read_up_to(r, &mut raw).map_err(io)? < header_len {
        return Err(err("truncated header".into()));
    }
    let text = if major == 3 {
        String::from_utf8(raw).map_err(|_| err("header is not UTF-8".into()))?
    } else {
        raw.iter().map(|&b| b as char).collect()
    };
    let (descr, fortran_order, shape) =
        parse_header_dict(&text).map_err(|m| err(format!("malformed header: {m}")))?;
    let (dtype, big_endian) = DType::parse(&descr).ok_or_else(|| {
        err(format!(
            "unsupported dtype '{descr}' (supported: bool, int8-64, uint8-64, float32, float64)"
        ))
    })?;
    let header = Header {
        dtype,
        big_endian,
        fortran_order,
        shape,
    };
    let need = header
        .shape
        .iter()
        .try_fold(dtype.size() as u64, |a, &d| a.checked_mul(d as u64))
        .ok_or_else(|| err(format!("shape {:?} is too large", header.shape)))?;
    if need > max_data {
        return Err(err(format!(
            "header says {} {} = {} bytes, more than the {} bytes allowed {}",
            shape_text(&header.shape),
            descr,
            need,
            max_data,
            limit_name
        )));
    }
    // `need` is at most `max_data`. The buffer grows as data actually arrives (doubling
    // from 1 MiB, never beyond `need`), so a short stream declaring much costs little
    // and a full one costs `need`, not the next power of two.
    let mut data: Vec<u8> = Vec::new();
    let mut want = need.min(1 << 20);
    loop {
        data.reserve_exact(want as usize - data.len());
        r.take(want - data.len() as u64)
            .read_to_end(&mut data)
            .map_err(io)?;
        if (data.len() as u64) < want || want == need {
            break;
        }
        want = want.saturating_mul(2).min(need);
    }
    if (data.len() as u64) < need {
        return Err(err(format!(
            "truncated: header says {} {} = {} bytes, file holds {}",
            shape_text(&header.shape),
            descr,
            need,
            data.len()
        )));
    }
    let extra = std::io::copy(
        &mut r.take(limits::MAX_NPY_TRAILING_BYTES + 1),
        &mut std::io::sink(),
    )
    .map_err(io)?;
    if extra > limits::MAX_NPY_TRAILING_BYTES {
        return Err(err(format!(
            "more than {} bytes after the array's data (np.save writes none)",
            limits::MAX_NPY_TRAILING_BYTES
        )));
    }
    let values = decode(data, &header);
    let values = if header.fortran_order && header.shape.len() > 1 {
        fortran_to_c(values, &header.shape)
    } else {
        values
    };
    let array = NpyArray::new(header.shape, values).map_err(|e| e.in_file(source))?;
    Ok((array, need))
}

fn shape_text(shape: &[usize]) -> String {
    if shape.is_empty() {
        "scalar".into()
    } else {
        shape
            .iter()
            .map(|d| d.to_string())
            .collect::<Vec<_>>()
            .join("x")
    }
}

fn decode(bytes: Vec<u8>, h: &Header) -> ArrayData {
    macro_rules! num {
        ($t:ty, $n:expr, $variant:ident) => {{
            let v: Vec<$t> = bytes
                .chunks_exact($n)
                .map(|c| {
                    let a: [u8; $n] = c.try_into().expect("chunk size");
                    if h.big_endian {
                        <$t>::from_be_bytes(a)
                    } else {
                        <$t>::from_le_bytes(a)
                    }
                })
                .collect();
            ArrayData::$variant(v)
        }};
    }
    match h.dtype {
        DType::Bool => ArrayData::Bool(bytes.iter().map(|&b| b != 0).collect()),
        DType::U8 => ArrayData::U8(bytes),
        DType::I8 => ArrayData::I8(bytes.iter().map(|&b| b as i8).collect()),
        DType::U16 => num!(u16, 2, U16),
        DType::I16 => num!(i16, 2, I16),
        DType::U32 => num!(u32, 4, U32),
        DType::I32 => num!(i32, 4, I32),
        DType::U64 => num!(u64, 8, U64),
        DType::I64 => num!(i64, 8, I64),
        DType::F32 => num!(f32, 4, F32),
        DType::F64 => num!(f64, 8, F64),
    }
}

/// Reorders Fortran-order (column-major) values into C order, walking the Fortran
/// index incrementally (O(1) per value, no index table). Axes of length 1 do not change
/// the order and are skipped, so a header with thousands of them costs nothing.
fn fortran_to_c(data: ArrayData, shape: &[usize]) -> ArrayData {
    let dims: Vec<usize> = shape.iter().copied().filter(|&d| d != 1).collect();
    let nd = dims.len();
    if nd < 2 || dims.contains(&0) {
        return data;
    }
    let mut strides = Vec::with_capacity(nd);
    let mut stride = 1usize;
    for &d in &dims {
        strides.push(stride);
        stride = stride.saturating_mul(d);
    }
    each_variant!(data, v => {
        let mut out = Vec::with_capacity(v.len());
        let mut idx = vec![0usize; nd];
        let mut f = 0usize;
        for _ in 0..v.len() {
            out.push(v[f]);
            for d in (0..nd).rev() {
                idx[d] += 1;
                f += strides[d];
                if idx[d] < dims[d] {
                    break;
                }
                f -= strides[d] * dims[d];
                idx[d] = 0;
            }
        }
        reconstruct(&v, out)
    })
}

/// Builds the same variant as `_like` holding `values`.
trait Reconstruct<T> {
    fn build(values: Vec<T>) -> ArrayData;
}
macro_rules! impl_reconstruct {
    ($t:ty, $variant:ident) => {
        impl Reconstruct<$t> for ArrayData {
            fn build(values: Vec<$t>) -> ArrayData {
                ArrayData::$variant(values)
            }
        }
    };
}
impl_reconstruct!(bool, Bool);
impl_reconstruct!(u8, U8);
impl_reconstruct!(i8, I8);
impl_reconstruct!(u16, U16);
impl_reconstruct!(i16, I16);
impl_reconstruct!(u32, U32);
impl_reconstruct!(i32, I32);
impl_reconstruct!(u64, U64);
impl_reconstruct!(i64, I64);
impl_reconstruct!(f32, F32);
impl_reconstruct!(f64, F64);

fn reconstruct<T>(_like: &[T], values: Vec<T>) -> ArrayData
where
    ArrayData: Reconstruct<T>,
{
    <ArrayData as Reconstruct<T>>::build(values)
}

/// Checks a file's length against `max` before it is read.
fn check_file_len(path: &Path, max: u64, what: &str) -> Result<std::fs::File> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    if len > max {
        return Err(Error::format(
            path,
            format!("file is {len} bytes, more than the {max} bytes allowed for {what}"),
        ));
    }
    Ok(file)
}

/// Reads a `.npy` file: its length is checked against `limits::MAX_NPY_FILE_BYTES`,
/// then it is read as a stream (header, declared data, bounded tail), never whole.
pub fn read_npy(path: &Path) -> Result<NpyArray> {
    let file = check_file_len(path, limits::MAX_NPY_FILE_BYTES, "a .npy file")?;
    let mut r = std::io::BufReader::new(file);
    let io = |e: std::io::Error| Error::io(path, e);
    read_npy_from(&mut r, path, limits::MAX_ARRAY_BYTES, "per array", &io).map(|(a, _)| a)
}

/// Writes `array` as a version 1.0 `.npy` (C order, little-endian), laid out exactly as
/// numpy's `np.save`: the header dict padded with spaces so that the data starts at a
/// multiple of 64 bytes.
pub fn write_npy(w: &mut dyn Write, array: &NpyArray) -> std::io::Result<()> {
    let shape = match array.shape.len() {
        0 => "()".to_string(),
        1 => format!("({},)", array.shape[0]),
        _ => format!(
            "({})",
            array
                .shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {}, }}",
        array.dtype().descr(),
        shape
    );
    // magic(6) + version(2) + length(2) + header + '\n' is a multiple of 64.
    let total = 10 + header.len() + 1;
    let pad = (64 - total % 64) % 64;
    header.push_str(&" ".repeat(pad));
    header.push('\n');
    w.write_all(b"\x93NUMPY\x01\x00")?;
    w.write_all(&(header.len() as u16).to_le_bytes())?;
    w.write_all(header.as_bytes())?;
    let mut buf = Vec::with_capacity(array.len() * array.dtype().size());
    match &array.data {
        ArrayData::Bool(v) => buf.extend(v.iter().map(|&b| b as u8)),
        ArrayData::U8(v) => buf.extend_from_slice(v),
        ArrayData::I8(v) => buf.extend(v.iter().map(|&x| x as u8)),
        ArrayData::U16(v) => v
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
        ArrayData::I16(v) => v
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
        ArrayData::U32(v) => v
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
        ArrayData::I32(v) => v
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
        ArrayData::U64(v) => v
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
        ArrayData::I64(v) => v
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
        ArrayData::F32(v) => v
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
        ArrayData::F64(v) => v
            .iter()
            .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
    }
    w.write_all(&buf)
}

/// The arrays of an `.npz` archive.
#[derive(Clone, Debug)]
pub struct Npz {
    path: PathBuf,
    members: Vec<(String, NpyArray)>,
}

/// How `.npz` members are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NpzCompression {
    /// As `np.savez`: stored, uncompressed.
    Stored,
    /// As `np.savez_compressed`: deflated.
    Deflated,
}

impl Npz {
    /// The file it came from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Keys (member names without `.npy`), in archive order.
    pub fn keys(&self) -> impl Iterator<Item = &str> {
        self.members.iter().map(|(k, _)| k.as_str())
    }

    /// The array of `key`, if present.
    pub fn get(&self, key: &str) -> Option<&NpyArray> {
        self.members.iter().find(|(k, _)| k == key).map(|(_, a)| a)
    }

    fn member_path(&self, key: &str) -> PathBuf {
        PathBuf::from(format!("{}:{}.npy", self.path.display(), key))
    }

    /// The array of `key`, or an error naming the file and the keys present.
    pub fn require(&self, key: &str) -> Result<&NpyArray> {
        self.get(key).ok_or_else(|| {
            Error::format(
                &self.path,
                format!(
                    "missing key '{key}' (keys present: {})",
                    self.keys().collect::<Vec<_>>().join(", ")
                ),
            )
        })
    }

    /// The array of `key` with exactly `shape`.
    pub(crate) fn require_shape(&self, key: &str, shape: &[usize]) -> Result<&NpyArray> {
        let a = self.require(key)?;
        if a.shape() != shape {
            return Err(Error::format(
                self.member_path(key),
                format!("'{key}' must have shape {shape:?}, found {:?}", a.shape()),
            ));
        }
        Ok(a)
    }

    /// The values of `key` as f64, checking the shape and that every value is finite.
    pub fn require_finite_f64(&self, key: &str, shape: &[usize]) -> Result<Vec<f64>> {
        let a = self.require_shape(key, shape)?;
        if a.dtype() == DType::Bool {
            return Err(Error::format(
                self.member_path(key),
                format!("'{key}' must be numeric, found bool"),
            ));
        }
        let v = a.to_f64_vec();
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(Error::format(
                self.member_path(key),
                format!(
                    "'{key}' has a non-finite value ({}) at flat index {i}",
                    v[i]
                ),
            ));
        }
        Ok(v)
    }
}

/// Parses `.npz` bytes; `source` names the archive in errors.
///
/// At most [`limits::MAX_NPZ_MEMBERS`] members; each is read as a stream (see
/// [`parse_npy`]) whose data is bounded by [`limits::MAX_ARRAY_BYTES`] and, summed over
/// the archive, by `limits::MAX_NPZ_ARRAY_BYTES`. The sizes the zip directory claims
/// are never used to allocate: a member claiming 100 GB that holds 14 KB is read as
/// numpy reads it, and a deflate bomb is refused from its header, before inflating.
pub fn parse_npz(bytes: &[u8], source: &Path) -> Result<Npz> {
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes)).map_err(|e| {
        Error::format(
            source,
            format!("not a valid zip archive (truncated or corrupt): {e}"),
        )
    })?;
    if zip.len() > limits::MAX_NPZ_MEMBERS {
        return Err(Error::format(
            source,
            format!(
                "{} members, more than the {} allowed",
                zip.len(),
                limits::MAX_NPZ_MEMBERS
            ),
        ));
    }
    let mut members = Vec::with_capacity(zip.len());
    let mut total = 0u64;
    for i in 0..zip.len() {
        let mut f = zip
            .by_index(i)
            .map_err(|e| Error::format(source, format!("cannot open member {i}: {e}")))?;
        let name = f
            .name()
            .map_err(|e| Error::format(source, format!("member {i} has an unreadable name: {e}")))?
            .to_string();
        let member = PathBuf::from(format!("{}:{}", source.display(), name));
        let Some(key) = name.strip_suffix(".npy") else {
            return Err(Error::format(&member, "member is not a .npy array"));
        };
        let io = |e: std::io::Error| {
            Error::format(
                &member,
                format!("cannot read member (truncated or corrupt): {e}"),
            )
        };
        let left = limits::MAX_NPZ_ARRAY_BYTES - total;
        let (max, limit_name) = if left < limits::MAX_ARRAY_BYTES {
            (left, "for the rest of the archive")
        } else {
            (limits::MAX_ARRAY_BYTES, "per array")
        };
        let (array, size) = read_npy_from(&mut f, &member, max, limit_name, &io)?;
        total += size;
        members.push((key.to_string(), array));
    }
    Ok(Npz {
        path: source.to_path_buf(),
        members,
    })
}

/// Reads an `.npz` file: its length is checked against [`limits::MAX_NPZ_FILE_BYTES`]
/// before it is read, and the read is capped there too (for files whose length lies).
pub fn read_npz(path: &Path) -> Result<Npz> {
    let file = check_file_len(path, limits::MAX_NPZ_FILE_BYTES, "an .npz file")?;
    let mut bytes = Vec::new();
    file.take(limits::MAX_NPZ_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    if bytes.len() as u64 > limits::MAX_NPZ_FILE_BYTES {
        return Err(Error::format(
            path,
            format!(
                "file grew beyond the {} bytes allowed for an .npz file",
                limits::MAX_NPZ_FILE_BYTES
            ),
        ));
    }
    parse_npz(&bytes, path)
}

/// Writes an `.npz` archive of `members` (as `np.savez` or `np.savez_compressed`),
/// deterministically: fixed timestamps (1980-01-01) and permissions.
pub fn write_npz<W: Write + Seek>(
    w: &mut W,
    members: &[(&str, &NpyArray)],
    compression: NpzCompression,
) -> Result<()> {
    let bad = |e: String| Error::invalid("npz", e);
    let mut zip = zip::ZipWriter::new(w);
    let method = match compression {
        NpzCompression::Stored => zip::CompressionMethod::Stored,
        NpzCompression::Deflated => zip::CompressionMethod::Deflated,
    };
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(method)
        .last_modified_time(zip::DateTime::default())
        .unix_permissions(0o644)
        .large_file(false);
    for (key, array) in members {
        zip.start_file(format!("{key}.npy"), options)
            .map_err(|e| bad(e.to_string()))?;
        write_npy(&mut zip, array).map_err(|e| bad(e.to_string()))?;
    }
    zip.finish().map_err(|e| bad(e.to_string()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p() -> &'static Path {
        Path::new("test.npy")
    }

    #[test]
    fn header_variants() {
        let (d, f, s) =
            parse_header_dict("{'descr': '<f4', 'fortran_order': False, 'shape': (3,), }").unwrap();
        assert_eq!((d.as_str(), f, s), ("<f4", false, vec![3]));
        let (_, f, s) = parse_header_dict(
            "{\"descr\": \"<u2\", \"fortran_order\": True, \"shape\": (2304, 3)}",
        )
        .unwrap();
        assert_eq!((f, s), (true, vec![2304, 3]));
        let (_, _, s) =
            parse_header_dict("{'descr': '|b1', 'fortran_order': False, 'shape': (), }   \n")
                .unwrap();
        assert!(s.is_empty());
        assert!(
            parse_header_dict("{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (1,)}")
                .is_err()
        );
        assert!(
            parse_header_dict("{'descr': '<f4', 'shape': (1,)}")
                .unwrap_err()
                .contains("fortran_order")
        );
    }

    fn all_dtypes() -> Vec<NpyArray> {
        vec![
            NpyArray::new(vec![3], ArrayData::Bool(vec![true, false, true])).unwrap(),
            NpyArray::new(vec![2], ArrayData::U8(vec![0, 255])).unwrap(),
            NpyArray::new(vec![2], ArrayData::I8(vec![-128, 127])).unwrap(),
            NpyArray::new(vec![2, 1], ArrayData::U16(vec![0, 65535])).unwrap(),
            NpyArray::new(vec![2], ArrayData::I16(vec![-3, 3])).unwrap(),
            NpyArray::new(vec![1], ArrayData::U32(vec![u32::MAX])).unwrap(),
            NpyArray::new(vec![2], ArrayData::I32(vec![i32::MIN, 5])).unwrap(),
            NpyArray::new(vec![1], ArrayData::U64(vec![u64::MAX])).unwrap(),
            NpyArray::new(vec![2, 2], ArrayData::I64(vec![1, -2, 3, -4])).unwrap(),
            NpyArray::new(
                vec![2, 3],
                ArrayData::F32(vec![0.5, -1.0, 2.25, f32::MAX, 0.0, -0.0]),
            )
            .unwrap(),
            NpyArray::new(vec![], ArrayData::F64(vec![std::f64::consts::PI])).unwrap(),
        ]
    }

    #[test]
    fn npy_round_trip_every_dtype() {
        for a in all_dtypes() {
            let mut buf = Vec::new();
            write_npy(&mut buf, &a).unwrap();
            assert_eq!(
                (buf.len() - a.len() * a.dtype().size()) % 64,
                0,
                "data aligned to 64"
            );
            assert_eq!(parse_npy(&buf, p()).unwrap(), a);
        }
    }

    #[test]
    fn npz_round_trip_both_compressions_and_deterministic() {
        let arrays = all_dtypes();
        let names: Vec<String> = (0..arrays.len()).map(|i| format!("a{i}")).collect();
        let members: Vec<(&str, &NpyArray)> = names
            .iter()
            .map(|s| s.as_str())
            .zip(arrays.iter())
            .collect();
        for c in [NpzCompression::Stored, NpzCompression::Deflated] {
            let mut cur = std::io::Cursor::new(Vec::new());
            write_npz(&mut cur, &members, c).unwrap();
            let mut again = std::io::Cursor::new(Vec::new());
            write_npz(&mut again, &members, c).unwrap();
            assert_eq!(cur.get_ref(), again.get_ref());
            let npz = parse_npz(cur.get_ref(), Path::new("x.npz")).unwrap();
            assert_eq!(
                npz.keys().collect::<Vec<_>>(),
                names.iter().map(|s| s.as_str()).collect::<Vec<_>>()
            );
            for (n, a) in &members {
                assert_eq!(npz.get(n).unwrap(), *a);
            }
        }
    }

    #[test]
    fn fortran_order_is_returned_in_c_order() {
        // A 2x3 array [[0,1,2],[3,4,5]] stored column-major: 0 3 1 4 2 5.
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        let mut h = "{'descr': '<u2', 'fortran_order': True, 'shape': (2, 3), }".to_string();
        while !(10 + h.len() + 1).is_multiple_of(64) {
            h.push(' ');
        }
        h.push('\n');
        bytes.extend((h.len() as u16).to_le_bytes());
        bytes.extend(h.as_bytes());
        for v in [0u16, 3, 1, 4, 2, 5] {
            bytes.extend(v.to_le_bytes());
        }
        let a = parse_npy(&bytes, p()).unwrap();
        assert_eq!(a.data(), &ArrayData::U16(vec![0, 1, 2, 3, 4, 5]));
        // Axes of length 1 anywhere do not change the order (they are skipped).
        let shaped = |shape: &str| {
            let mut b = b"\x93NUMPY\x01\x00".to_vec();
            let h = format!("{{'descr': '<u2', 'fortran_order': True, 'shape': {shape}, }}\n");
            b.extend((h.len() as u16).to_le_bytes());
            b.extend(h.as_bytes());
            for v in [0u16, 3, 1, 4, 2, 5] {
                b.extend(v.to_le_bytes());
            }
            parse_npy(&b, p()).unwrap()
        };
        for shape in ["(1, 2, 1, 3, 1)", "(2, 1, 3)", "(1, 1, 2, 3)"] {
            assert_eq!(
                shaped(shape).data(),
                &ArrayData::U16(vec![0, 1, 2, 3, 4, 5])
            );
        }
        // A 2x2x2 array: C index (i, j, k) holds Fortran element i + 2j + 4k.
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        let h = "{'descr': '|u1', 'fortran_order': True, 'shape': (2, 2, 2), }\n";
        b.extend((h.len() as u16).to_le_bytes());
        b.extend(h.as_bytes());
        b.extend(0u8..8);
        let a = parse_npy(&b, p()).unwrap();
        assert_eq!(a.data(), &ArrayData::U8(vec![0, 4, 2, 6, 1, 5, 3, 7]));
    }

    #[test]
    fn every_truncation_is_an_error_not_a_panic() {
        let a = NpyArray::from_f32(vec![4, 3], (0..12).map(|i| i as f32).collect()).unwrap();
        let mut buf = Vec::new();
        write_npy(&mut buf, &a).unwrap();
        for n in 0..buf.len() {
            assert!(parse_npy(&buf[..n], p()).is_err(), "prefix {n}");
        }
        let mut cur = std::io::Cursor::new(Vec::new());
        write_npz(&mut cur, &[("verts", &a)], NpzCompression::Deflated).unwrap();
        let z = cur.into_inner();
        for n in 0..z.len() {
            assert!(
                parse_npz(&z[..n], Path::new("t.npz")).is_err(),
                "npz prefix {n}"
            );
        }
        // Flipped bytes never panic (they may or may not parse).
        for i in 0..buf.len() {
            let mut b = buf.clone();
            b[i] ^= 0xA5;
            let _ = parse_npy(&b, p());
        }
    }

    #[test]
    fn errors_name_the_file_and_the_problem() {
        let e = parse_npy(b"PK\x03\x04 not numpy at all", Path::new("a.npy"))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("a.npy:") && e.contains("magic"), "{e}");
        let a = NpyArray::from_f32(vec![1220, 3], vec![0.0; 3660]).unwrap();
        let mut buf = Vec::new();
        write_npy(&mut buf, &a).unwrap();
        let e = parse_npy(&buf[..buf.len() - 640], Path::new("v.npy"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("truncated: header says 1220x3 <f4 = 14640 bytes, file holds 14000"),
            "{e}"
        );
        let mut bad = buf.clone();
        bad[6] = 9;
        assert!(
            parse_npy(&bad, p())
                .unwrap_err()
                .to_string()
                .contains("version 9")
        );
        let mut c = buf.clone();
        let at = c.windows(3).position(|w| w == b"<f4").unwrap();
        c[at..at + 3].copy_from_slice(b"<c8");
        assert!(
            parse_npy(&c, p())
                .unwrap_err()
                .to_string()
                .contains("unsupported dtype '<c8'")
        );
        let mut cur = std::io::Cursor::new(Vec::new());
        write_npz(&mut cur, &[("verts", &a)], NpzCompression::Stored).unwrap();
        let npz = parse_npz(cur.get_ref(), Path::new("s_info.npz")).unwrap();
        let e = npz.require("R_t").unwrap_err().to_string();
        assert_eq!(e, "s_info.npz: missing key 'R_t' (keys present: verts)");
        let e = npz
            .require_shape("verts", &[1220, 2])
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("s_info.npz:verts.npy:") && e.contains("[1220, 3]"),
            "{e}"
        );
        assert!(NpyArray::from_f64(vec![2], vec![1.0]).is_err());
        assert!(
            NpyArray::from_f64(vec![2], vec![1.0, 2.0])
                .unwrap()
                .to_i64_vec()
                .is_err()
        );
        let big = NpyArray::new(vec![1], ArrayData::U64(vec![u64::MAX])).unwrap();
        assert!(big.to_i64_vec().is_err());
    }
}

//! Reading safetensors files without trusting them: the header (names, types, shapes
//! and data offsets) is checked against the file's length before any data is read, the
//! callers match it with what the network expects, and the tensors are then read one
//! at a time. A header that declares 100 GB, or a sparse file of gigabytes with the
//! wrong names, is refused after reading its header only.
//!
//! The checks: the header's length field is at most
//! [`limits::MAX_SAFETENSORS_HEADER_BYTES`] and fits in the file; the header is a JSON
//! object of at most [`limits::MAX_TORCH_TENSORS`] tensors, each with a known type, a
//! shape whose byte size (overflow-checked) equals its data range, and the ranges
//! tile the data exactly (no gap, no overlap, nothing after), as the format requires.

use arkit_core::limits;
use candle_core::{DType, Device, Tensor};
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

/// One tensor of a safetensors file, as its header declares it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Entry {
    /// Its name.
    pub name: String,
    /// Element type.
    pub dtype: DType,
    /// Shape.
    pub shape: Vec<usize>,
    start: u64,
    end: u64,
}

/// A safetensors file whose header has been read and checked.
pub struct SafetensorsFile<R> {
    reader: R,
    data_start: u64,
    entries: Vec<Entry>,
}

fn dtype_of(s: &str) -> Option<DType> {
    Some(match s {
        "F64" => DType::F64,
        "F32" => DType::F32,
        "F16" => DType::F16,
        "BF16" => DType::BF16,
        "I64" => DType::I64,
        "U32" => DType::U32,
        "U8" => DType::U8,
        _ => return None,
    })
}

fn parse_entry(name: &str, v: &serde_json::Value) -> Result<Entry, String> {
    let bad = |what: &str| format!("the header's entry for '{name}' {what}");
    let o = v.as_object().ok_or_else(|| bad("is not an object"))?;
    let dt = o
        .get("dtype")
        .and_then(|d| d.as_str())
        .ok_or_else(|| bad("has no dtype"))?;
    let dtype =
        dtype_of(dt).ok_or_else(|| bad(&format!("has the type {dt}, which is not read")))?;
    let shape = o
        .get("shape")
        .and_then(|s| s.as_array())
        .ok_or_else(|| bad("has no shape"))?
        .iter()
        .map(|d| d.as_u64().and_then(|d| usize::try_from(d).ok()))
        .collect::<Option<Vec<usize>>>()
        .ok_or_else(|| bad("has a shape that is not a list of sizes"))?;
    let offs = o
        .get("data_offsets")
        .and_then(|s| s.as_array())
        .filter(|a| a.len() == 2)
        .and_then(|a| Some((a[0].as_u64()?, a[1].as_u64()?)))
        .ok_or_else(|| bad("has no data_offsets [start, end]"))?;
    let bytes = shape
        .iter()
        .try_fold(dtype.size_in_bytes() as u64, |acc, &d| {
            acc.checked_mul(d as u64)
        });
    if offs.0 > offs.1 || bytes != Some(offs.1 - offs.0) {
        return Err(bad(&format!(
            "declares the shape {shape:?} of {dt} but the data range {}..{}",
            offs.0, offs.1
        )));
    }
    Ok(Entry {
        name: name.to_string(),
        dtype,
        shape,
        start: offs.0,
        end: offs.1,
    })
}

impl<R: Read + Seek> SafetensorsFile<R> {
    /// Reads and checks the header of the safetensors data in `reader`, which holds
    /// `len` bytes. No tensor data is read.
    pub fn new(mut reader: R, len: u64) -> Result<Self, String> {
        let mut n = [0u8; 8];
        if len < 8 || reader.read_exact(&mut n).is_err() {
            return Err(format!("{len} bytes: too short for a safetensors file"));
        }
        let n = u64::from_le_bytes(n);
        if n > limits::MAX_SAFETENSORS_HEADER_BYTES {
            return Err(format!(
                "not a safetensors file: its header would be {n} bytes, more than the {} allowed",
                limits::MAX_SAFETENSORS_HEADER_BYTES
            ));
        }
        if n > len - 8 {
            return Err(format!(
                "not a safetensors file (or truncated): a header of {n} bytes in a file of {len}"
            ));
        }
        let mut header = vec![0u8; n as usize];
        reader
            .read_exact(&mut header)
            .map_err(|e| format!("cannot read the header: {e}"))?;
        let map: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(&header)
            .map_err(|e| format!("not a safetensors file: its header is not a JSON object: {e}"))?;
        if map.len() > limits::MAX_TORCH_TENSORS + 1 {
            return Err(format!(
                "{} tensors, more than the {} allowed",
                map.len(),
                limits::MAX_TORCH_TENSORS
            ));
        }
        let mut entries = Vec::with_capacity(map.len());
        for (name, v) in &map {
            if name == "__metadata__" {
                continue;
            }
            entries.push(parse_entry(name, v)?);
        }
        // The data ranges must tile the data exactly.
        let data_len = len - 8 - n;
        let mut by_start: Vec<&Entry> = entries.iter().collect();
        by_start.sort_by_key(|e| (e.start, e.end));
        let mut at = 0u64;
        for e in by_start {
            if e.start != at {
                return Err(format!(
                    "the data of '{}' starts at byte {} of the data, not {at} (a gap or an overlap)",
                    e.name, e.start
                ));
            }
            at = e.end;
        }
        if at != data_len {
            return Err(format!(
                "the header declares {at} bytes of tensor data, the file holds {data_len}"
            ));
        }
        Ok(Self {
            reader,
            data_start: 8 + n,
            entries,
        })
    }

    /// The tensors the header declares, in the header's (name) order.
    pub fn entries(&self) -> &[Entry] {
        &self.entries
    }

    /// Reads the tensor `name`.
    pub fn read(&mut self, name: &str) -> Result<Tensor, String> {
        let e = self
            .entries
            .iter()
            .find(|e| e.name == name)
            .ok_or_else(|| format!("no tensor {name}"))?;
        let mut buf = vec![0u8; (e.end - e.start) as usize];
        self.reader
            .seek(SeekFrom::Start(self.data_start + e.start))
            .and_then(|_| self.reader.read_exact(&mut buf))
            .map_err(|err| format!("{name}: cannot read its data: {err}"))?;
        Tensor::from_raw_buffer(&buf, e.dtype, &e.shape, &Device::Cpu)
            .map_err(|err| format!("{name}: {err}"))
    }
}

/// Opens the safetensors file `path` ([`SafetensorsFile::new`]); errors do not name
/// the file (callers do).
pub fn open(path: &Path) -> Result<SafetensorsFile<std::io::BufReader<std::fs::File>>, String> {
    let f = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let len = f.metadata().map_err(|e| e.to_string())?.len();
    SafetensorsFile::new(std::io::BufReader::new(f), len)
}

/// The safetensors data in `bytes` ([`SafetensorsFile::new`]).
pub fn from_bytes(bytes: &[u8]) -> Result<SafetensorsFile<std::io::Cursor<&[u8]>>, String> {
    SafetensorsFile::new(std::io::Cursor::new(bytes), bytes.len() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn written() -> Vec<u8> {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.safetensors");
        let mut m = HashMap::new();
        m.insert(
            "a".to_string(),
            Tensor::new(&[1f32, 2.0, 3.0], &Device::Cpu).unwrap(),
        );
        m.insert(
            "b".to_string(),
            Tensor::new(&[[7i64, 8], [9, 10]], &Device::Cpu).unwrap(),
        );
        candle_core::safetensors::save(&m, &p).unwrap();
        std::fs::read(&p).unwrap()
    }

    fn with_header(header: &str, data: usize) -> Vec<u8> {
        let mut b = (header.len() as u64).to_le_bytes().to_vec();
        b.extend(header.as_bytes());
        b.extend(vec![0u8; data]);
        b
    }

    #[test]
    fn reads_what_candle_writes() {
        let bytes = written();
        let mut f = from_bytes(&bytes).unwrap();
        let names: Vec<&str> = f.entries().iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names, ["a", "b"]);
        assert_eq!(
            f.read("a").unwrap().to_vec1::<f32>().unwrap(),
            [1.0, 2.0, 3.0]
        );
        assert_eq!(
            f.read("b").unwrap().to_vec2::<i64>().unwrap(),
            [[7, 8], [9, 10]]
        );
        assert!(f.read("c").is_err());
    }

    /// Sizes from the header are checked against the file before anything is read or
    /// allocated: 100 GB declared, a header longer than the file or than the bound, a
    /// shape that disagrees with its range, gaps, overlaps and trailing bytes.
    #[test]
    fn headers_that_lie_are_refused() {
        let e = from_bytes(&with_header(
            r#"{"w":{"dtype":"F32","shape":[25000000000],"data_offsets":[0,100000000000]}}"#,
            16,
        ))
        .err()
        .unwrap();
        assert!(
            e.contains("declares 100000000000 bytes of tensor data, the file holds 16"),
            "{e}"
        );
        let mut b = u64::MAX.to_le_bytes().to_vec();
        b.extend([0u8; 64]);
        assert!(from_bytes(&b).err().unwrap().contains("more than the"));
        let mut b = 1000u64.to_le_bytes().to_vec();
        b.extend([b'{'; 64]);
        assert!(
            from_bytes(&b)
                .err()
                .unwrap()
                .contains("a header of 1000 bytes in a file of 72")
        );
        let e = from_bytes(&with_header(
            r#"{"w":{"dtype":"F32","shape":[3],"data_offsets":[0,8]}}"#,
            8,
        ))
        .err()
        .unwrap();
        assert!(
            e.contains("'w' declares the shape [3] of F32 but the data range 0..8"),
            "{e}"
        );
        let e = from_bytes(&with_header(
            r#"{"a":{"dtype":"U8","shape":[4],"data_offsets":[0,4]},"b":{"dtype":"U8","shape":[4],"data_offsets":[2,6]}}"#,
            6,
        ))
        .err()
        .unwrap();
        assert!(e.contains("'b' starts at byte 2 of the data, not 4"), "{e}");
        let e = from_bytes(&with_header(
            r#"{"a":{"dtype":"U8","shape":[4],"data_offsets":[0,4]}}"#,
            5,
        ))
        .err()
        .unwrap();
        assert!(
            e.contains("declares 4 bytes of tensor data, the file holds 5"),
            "{e}"
        );
        let e = from_bytes(&with_header(
            r#"{"a":{"dtype":"F32","shape":[4611686018427387904, 8],"data_offsets":[0,0]}}"#,
            0,
        ))
        .err()
        .unwrap();
        assert!(e.contains("declares the shape"), "{e}");
        // Every truncation of a good file is an error.
        let bytes = written();
        for n in 0..bytes.len() {
            assert!(from_bytes(&bytes[..n]).is_err(), "{n}");
        }
    }
}

//! The zip archive: its members checked and read one tensor at a time.

use super::machine::parse_state_dict_pickle;
use super::tensor::TorchTensor;
use crate::error::{Error, Result};
use crate::limits;
use std::io::{Read, Seek};
use std::path::{Path, PathBuf};

/// A `torch.save` zip archive whose pickle has been read and checked; the tensors'
/// data are read one at a time by [`TorchZip::read`].
pub struct TorchZip<R: Read + Seek> {
    zip: zip::ZipArchive<R>,
    source: PathBuf,
    prefix: String,
    tensors: Vec<TorchTensor>,
}

impl std::fmt::Debug for TorchZip<std::fs::File> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "TorchZip({}, {} tensors)",
            self.source.display(),
            self.tensors.len()
        )
    }
}

/// Reads member `name` whole, refusing it when it holds more than `max` bytes; the
/// size the directory claims is used only to refuse early, never to allocate.
pub(super) fn read_member<R: Read + Seek>(
    zip: &mut zip::ZipArchive<R>,
    name: &str,
    max: u64,
    source: &Path,
) -> Result<Vec<u8>> {
    let member = format!("{}:{name}", source.display());
    let f = zip
        .by_name(name)
        .map_err(|e| Error::format(&member, format!("cannot open the member: {e}")))?;
    if f.size() > max {
        return Err(Error::format(
            &member,
            format!("{} bytes, more than the {max} expected", f.size()),
        ));
    }
    let mut out = Vec::new();
    f.take(max + 1).read_to_end(&mut out).map_err(|e| {
        Error::format(
            &member,
            format!("cannot read the member (truncated or corrupt): {e}"),
        )
    })?;
    if out.len() as u64 > max {
        return Err(Error::format(
            &member,
            format!("more than the {max} bytes expected"),
        ));
    }
    Ok(out)
}

impl<R: Read + Seek> TorchZip<R> {
    /// Opens a `torch.save` archive: finds its `data.pkl`, reads it with
    /// `parse_state_dict_pickle`, checks the byte order and that every storage's
    /// member exists with exactly the bytes its tensors need. No tensor data is read.
    pub fn new(reader: R, source: &Path) -> Result<Self> {
        let mut zip = zip::ZipArchive::new(reader).map_err(|e| {
            Error::format(
                source,
                format!(
                    "not a PyTorch state_dict (torch.save zip format): not a valid zip archive: {e}"
                ),
            )
        })?;
        if zip.len() > limits::MAX_TORCH_TENSORS + 16 {
            return Err(Error::format(
                source,
                format!(
                    "{} members, more than a state_dict of at most {} tensors has",
                    zip.len(),
                    limits::MAX_TORCH_TENSORS
                ),
            ));
        }
        let pkls: Vec<String> = zip
            .file_names()
            .filter_map(|n| n.ok().map(|n| n.into_owned()))
            .filter(|n| n.ends_with("/data.pkl") && n.matches('/').count() == 1)
            .collect();
        let [pkl] = pkls.as_slice() else {
            return Err(Error::format(
                source,
                format!(
                    "not a PyTorch state_dict (torch.save zip format): {} members FOLDER/data.pkl, not one",
                    pkls.len()
                ),
            ));
        };
        let prefix = pkl.strip_suffix("data.pkl").expect("checked").to_string();
        let bo = format!("{prefix}byteorder");
        if zip.index_for_name(&bo).is_some() {
            let order = read_member(&mut zip, &bo, 16, source)?;
            if order != b"little" {
                return Err(Error::format(
                    source,
                    format!(
                        "byte order {:?}: only little-endian checkpoints are read",
                        String::from_utf8_lossy(&order)
                    ),
                ));
            }
        }
        let pickle = read_member(&mut zip, pkl, limits::MAX_PICKLE_BYTES, source)?;
        let tensors = parse_state_dict_pickle(&pickle, source)?;
        drop(pickle);
        let mut total = 0u64;
        let mut checked = std::collections::HashSet::new();
        for t in &tensors {
            if !checked.insert(t.storage.clone()) {
                continue;
            }
            let name = format!("{prefix}data/{}", t.storage);
            let member = format!("{}:{name}", source.display());
            let want = t.storage_numel * t.dtype.size() as u64;
            let f = zip.by_name(&name).map_err(|e| {
                Error::format(
                    &member,
                    format!("the storage of '{}' is missing: {e}", t.name),
                )
            })?;
            if f.size() != want {
                return Err(Error::format(
                    &member,
                    format!(
                        "{} bytes, but '{}' declares {} elements of {} ({want} bytes)",
                        f.size(),
                        t.name,
                        t.storage_numel,
                        t.dtype.name()
                    ),
                ));
            }
            total += want;
            if total > limits::MAX_TORCH_DATA_BYTES {
                return Err(Error::format(
                    source,
                    format!(
                        "the tensors hold more than the {} bytes allowed",
                        limits::MAX_TORCH_DATA_BYTES
                    ),
                ));
            }
        }
        Ok(Self {
            zip,
            source: source.to_path_buf(),
            prefix,
            tensors,
        })
    }

    /// The tensors, in the file's order.
    pub fn tensors(&self) -> &[TorchTensor] {
        &self.tensors
    }

    /// The data of tensor `i` ([`TorchTensor`] of [`Self::tensors`]), contiguous
    /// (row-major) little-endian bytes, `numel * dtype.size()` of them. Reads its
    /// storage's member (at most `limits::MAX_TORCH_STORAGE_BYTES`).
    pub fn read(&mut self, i: usize) -> Result<Vec<u8>> {
        let t = self.tensors[i].clone();
        let size = t.dtype.size();
        let want = t.storage_numel * size as u64;
        let name = format!("{}data/{}", self.prefix, t.storage);
        let storage = read_member(&mut self.zip, &name, want, &self.source)?;
        if storage.len() as u64 != want {
            return Err(Error::format(
                format!("{}:{name}", self.source.display()),
                format!("{} bytes, {want} expected (truncated)", storage.len()),
            ));
        }
        let numel = t.numel();
        // Row-major strides: a slice of the storage.
        let mut contiguous = true;
        let mut expect = 1usize;
        for (&n, &s) in t.shape.iter().zip(&t.stride).rev() {
            if n > 1 && s != expect {
                contiguous = false;
            }
            expect = expect.saturating_mul(n);
        }
        if numel == 0 {
            return Ok(Vec::new());
        }
        if contiguous {
            let a = t.offset * size;
            return Ok(storage[a..a + numel * size].to_vec());
        }
        let mut out = Vec::with_capacity(numel * size);
        let mut idx = vec![0usize; t.shape.len()];
        for _ in 0..numel {
            let e = t.offset + idx.iter().zip(&t.stride).map(|(i, s)| i * s).sum::<usize>();
            out.extend_from_slice(&storage[e * size..(e + 1) * size]);
            for d in (0..idx.len()).rev() {
                idx[d] += 1;
                if idx[d] < t.shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        Ok(out)
    }
}

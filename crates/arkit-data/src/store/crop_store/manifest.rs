//! `manifest`: `crops.json`, what a store holds and what it was made from
//! ([`CropStoreManifest`]), read (a store of another format refused first, with what to
//! do) and written; the rules and the header each part file must have follow from it.
//! Uses [`super::format`] and [`super::codec`].

use super::codec::WindowCodec;
use super::format::{FORMAT, HEADER_BYTES, MANIFEST_FILE, PartHeader};
use crate::crop::RuleSet;
use arkit_core::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Largest `crops.json` read (its list of samples without pixels is what can grow).
const MAX_MANIFEST_BYTES: u64 = 256 << 20;

/// `crops.json`: what a store holds and what it was made from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CropStoreManifest {
    /// [`FORMAT`].
    pub format: u32,
    /// The rules the boxes and windows follow (`"compat"`: `"exact"` or `"official"`).
    #[serde(rename = "compat")]
    pub rules: RuleSet,
    /// How the windows are stored.
    pub codec: WindowCodec,
    /// Crop side `S`.
    pub img_size: u32,
    /// [`super::margin`]`(S)`.
    pub margin: u32,
    /// Vertices per mesh.
    pub vertex_count: usize,
    /// Width of each record's key field (`super::key_field_bytes` of the longest key).
    pub key_bytes: usize,
    /// [`crate::store::manifest::dataset_fingerprint`] of the dataset stored.
    pub dataset_fingerprint: String,
    /// One entry per samples shard, by index.
    pub shards: Vec<CropShard>,
    /// The samples stored without pixels, and why.
    pub missing: Vec<MissingCrop>,
}

/// One `part-K.bin`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CropShard {
    /// The samples shard `K`.
    pub index: usize,
    /// `part-K.bin`, relative to the store folder.
    pub file: String,
    /// Records (the shard's rows).
    pub records: usize,
    /// The file's bytes (header, records, index, footer).
    pub bytes: u64,
}

/// A sample stored without pixels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MissingCrop {
    /// Its samples shard.
    pub shard: usize,
    /// Its row there.
    pub row: usize,
    /// `subject/action/img_id`.
    pub key: String,
    /// Why (the error, naming the file).
    pub reason: String,
}

impl CropStoreManifest {
    /// The header of the `part-K.bin` of samples shard `index`, with `records` records.
    pub(crate) fn part_header(
        &self,
        index: usize,
        records: usize,
    ) -> Result<[u8; HEADER_BYTES as usize]> {
        let rules = self.rules.header_code();
        PartHeader {
            format: self.format,
            rules,
            img_size: self.img_size,
            margin: self.margin,
            vertex_count: self.vertex_count as u32,
            records: records as u64,
            codec: self.codec.code(),
            shard: index as u32,
            key_bytes: self.key_bytes as u32,
            fingerprint: &self.dataset_fingerprint,
        }
        .bytes()
    }
}

/// Writes `crops.json` (atomically; last, after every shard file).
pub(crate) fn write_manifest(dir: &Path, manifest: &CropStoreManifest) -> Result<()> {
    let text = serde_json::to_string_pretty(manifest).expect("manifest serialises");
    arkit_core::atomic_file::write_bytes(&dir.join(MANIFEST_FILE), text.as_bytes())
}

/// Reads and parses `dir/crops.json`; a store of another format is refused first, with
/// what to do.
pub fn read_manifest(dir: &Path) -> Result<CropStoreManifest> {
    let path = dir.join(MANIFEST_FILE);
    let meta = std::fs::metadata(&path).map_err(|e| {
        Error::format(
            dir,
            format!("not a crop store ({MANIFEST_FILE}: {e}); make one with `arkit-tool crops`"),
        )
    })?;
    if meta.len() > MAX_MANIFEST_BYTES {
        return Err(Error::format(
            &path,
            format!("{} bytes, more than a manifest can be", meta.len()),
        ));
    }
    let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
    let value: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::format(&path, format!("not a crop store manifest: {e}")))?;
    match value.get("format").and_then(|f| f.as_u64()) {
        Some(f) if f == FORMAT as u64 => {}
        Some(f) => {
            return Err(Error::format(
                &path,
                format!(
                    "a crop store of format {f}; this version reads format {FORMAT} (compressed windows whose centre is decoded alone, zstd meshes, an index per part): rerun `arkit-tool crops`"
                ),
            ));
        }
        None => {
            return Err(Error::format(
                &path,
                "not a crop store manifest: no format number",
            ));
        }
    }
    serde_json::from_value(value)
        .map_err(|e| Error::format(&path, format!("not a crop store manifest: {e}")))
}

//! `crops_dataset`: the crop store ([`crate::store::crop_store`]) of a whole converted
//! dataset, written shard by shard: what `arkit-tool crops` runs.
//!
//! Every sample is read as the loader reads it without a store (its `_info.npz`, checked
//! against the samples table, and its image), its evaluation box computed by the
//! loader's own rules ([`FaceLoader::stored_crop`]), and its crop window resampled from
//! the full-resolution image. Parallel over the samples of a shard, in chunks, written
//! in row order; the output does not depend on the number of threads. A sample that
//! cannot be read (a missing or damaged image, a changed `_info.npz`) never stops the
//! run: its record has no pixels, `crops.json` lists it with the reason, and the loader
//! raises that reason when it is asked for the sample. `crops.json` is removed before
//! the first file is written and written after the last, so a store is complete
//! whenever it has one.
//!
//! One writer per store: the run holds the folder's lock (`.crops.lock`, the
//! [`arkit_core::atomic_file::FolderLock`] that `convert`, `render` and `augment` take)
//! from before it touches anything until it has written `crops.json`, so a second
//! `crops` into the same folder (another dataset's, or the same) is refused at once
//! instead of mixing its parts with the first's. Under the lock it removes what killed
//! runs left ([`arkit_core::atomic_file::remove_stale_temporaries`]: a `.part-K.bin.tmp-PID`
//! per killed run), and after `crops.json` the `part-K.bin` files it no longer names.
//!
//! Tested in `tests/crop_store.rs`.

use crate::crop::RuleSet;
use crate::loader::item::FaceLoader;
use crate::store::crop_store::{
    self, CropStoreManifest, FORMAT, MissingCrop, WindowCodec, encode_record, margin,
};
use arkit_core::{Error, Result};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// Samples computed in parallel before they are written.
const CHUNK: usize = 64;

/// What [`write_crop_store`] did.
#[derive(Clone, Debug, Serialize)]
pub struct CropStoreSummary {
    /// The store folder.
    pub output: PathBuf,
    /// The rules the crops follow (`"compat"` in `--json`: `"exact"` or `"official"`).
    #[serde(rename = "compat")]
    pub rules: RuleSet,
    /// How the windows are stored (`pred-zstd`, `png` or `raw`).
    pub codec: WindowCodec,
    /// Crop side.
    pub img_size: u32,
    /// Window side (`S + 2m`).
    pub window: usize,
    /// Samples in the dataset.
    pub samples: usize,
    /// Samples stored without pixels.
    pub missing: usize,
    /// The first few of them, `key: reason`.
    pub missing_examples: Vec<String>,
    /// Bytes written (all `part-K.bin`).
    pub bytes: u64,
    /// Bytes per sample (the mean, headers and indexes included).
    pub bytes_per_sample: f64,
}

/// Writes the crop store of the dataset `loader` serves (opened with no split, in
/// evaluation mode, with the rules and crop side wanted) into `output`, its windows by
/// the default codec ([`WindowCodec::PredZstd`]); `progress` is called with the number
/// of samples done since its last call.
pub fn write_crop_store(
    loader: &FaceLoader,
    output: &Path,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<CropStoreSummary> {
    write_crop_store_with(loader, output, WindowCodec::PredZstd, progress)
}

/// [`write_crop_store`] with the windows stored by `codec`.
pub fn write_crop_store_with(
    loader: &FaceLoader,
    output: &Path,
    codec: WindowCodec,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<CropStoreSummary> {
    let options = loader.options();
    if options.split.is_some() {
        return Err(Error::invalid(
            "crop store",
            "the loader must serve every sample (no split)",
        ));
    }
    let (rules, s) = (options.rules, options.img_size);
    let vertex_count = loader.mesh_vertex_count();
    let dataset = loader.dataset();
    // Every sample's key fits the records' key field (checked before anything is
    // written).
    let mut longest = 0;
    for i in 0..loader.len() {
        let (key, _) = loader.key(i).expect("in range");
        let len = key.to_string().len();
        if len > crop_store::MAX_KEY_BYTES {
            return Err(Error::invalid(
                "crop store",
                format!(
                    "{key}: a key of {len} bytes; a store's records hold keys of up to {} bytes",
                    crop_store::MAX_KEY_BYTES
                ),
            ));
        }
        longest = longest.max(len);
    }
    let key_bytes = crop_store::key_field_bytes(longest);
    // One writer per store, from here until crops.json is written.
    let _lock = arkit_core::atomic_file::FolderLock::acquire(output, "crops", "crops")?;
    arkit_core::atomic_file::remove_stale_temporaries(output, false)?;
    let manifest_path = output.join(crop_store::MANIFEST_FILE);
    if manifest_path.exists() {
        std::fs::remove_file(&manifest_path).map_err(|e| Error::io(&manifest_path, e))?;
    }
    let mut manifest = CropStoreManifest {
        format: FORMAT,
        rules,
        codec,
        img_size: s,
        margin: margin(s),
        vertex_count,
        key_bytes,
        dataset_fingerprint: crate::store::manifest::dataset_fingerprint(dataset.manifest()),
        shards: Vec::new(),
        missing: Vec::new(),
    };
    let missing = Mutex::new(Vec::new());
    let mut next = 0usize;
    for shard in dataset.shards() {
        let indices: Vec<usize> = (next..next + shard.rows).collect();
        next += shard.rows;
        for &i in &indices {
            if loader.location(i).map(|l| l.0) != Some(shard.index) {
                return Err(Error::invalid(
                    "crop store",
                    format!(
                        "sample {i} is not in samples shard {} as expected",
                        shard.index
                    ),
                ));
            }
        }
        let mut records = indices.chunks(CHUNK).flat_map(|chunk| {
            let done: Vec<Result<Vec<u8>>> = chunk
                .par_iter()
                .map(|&i| {
                    let (_, row) = loader.location(i).expect("checked above");
                    let (key, _) = loader.key(i).expect("in range");
                    let name = key.to_string();
                    match loader.stored_crop(i) {
                        Ok(c) => encode_record(&manifest, shard.index, row, &name, Some(&c)),
                        Err(e) => {
                            missing
                                .lock()
                                .unwrap_or_else(|p| p.into_inner())
                                .push(MissingCrop {
                                    shard: shard.index,
                                    row,
                                    key: name.clone(),
                                    reason: e.to_string(),
                                });
                            encode_record(&manifest, shard.index, row, &name, None)
                        }
                    }
                })
                .collect();
            progress(chunk.len());
            done
        });
        let entry =
            crop_store::write_shard_file(output, &manifest, shard.index, &mut records, shard.rows)?;
        manifest.shards.push(entry);
    }
    let mut missing = missing.into_inner().unwrap_or_else(|p| p.into_inner());
    missing.sort_by_key(|m| (m.shard, m.row));
    manifest.missing = missing;
    crop_store::write_manifest(output, &manifest)?;
    remove_unnamed_parts(output, &manifest)?;
    let bytes: u64 = manifest.shards.iter().map(|c| c.bytes).sum();
    Ok(CropStoreSummary {
        output: output.to_path_buf(),
        rules: manifest.rules,
        codec,
        img_size: s,
        window: crop_store::window_side(s),
        samples: loader.len(),
        missing: manifest.missing.len(),
        missing_examples: manifest
            .missing
            .iter()
            .take(5)
            .map(|m| format!("{}: {}", m.key, m.reason))
            .collect(),
        bytes,
        bytes_per_sample: bytes as f64 / loader.len().max(1) as f64,
    })
}

/// Removes the `part-K.bin` files of `dir` that `manifest` does not name (left by an
/// earlier store of a dataset with more shards): never read, but they take space.
fn remove_unnamed_parts(dir: &Path, manifest: &CropStoreManifest) -> Result<()> {
    let named: std::collections::HashSet<&str> =
        manifest.shards.iter().map(|s| s.file.as_str()).collect();
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let is_part = name
            .strip_prefix("part-")
            .and_then(|n| n.strip_suffix(".bin"))
            .is_some_and(|k| !k.is_empty() && k.bytes().all(|b| b.is_ascii_digit()));
        if is_part && !named.contains(name.as_str()) {
            let path = entry.path();
            std::fs::remove_file(&path).map_err(|e| Error::io(&path, e))?;
        }
    }
    Ok(())
}

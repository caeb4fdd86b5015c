//! `manifest`: a converted dataset's `dataset.json`: what `convert` made and from what
//! ([`Manifest`]), its shards with their sizes and hashes ([`ShardEntry`]), and the checks
//! every reader runs before it trusts a shard ([`check_shard_file`]: size and the hash of
//! its last `TAIL_BYTES`) or a topology ([`check_topology`]); the fingerprint of its
//! samples that rendered targets and crop stores are tied to ([`dataset_fingerprint`]).
//!
//! A leaf below `convert` (which writes it) and `dataset` (which reads it). Tested
//! through both: `tests/convert.rs` rewrites and truncates shards and expects the
//! readers to refuse them, naming the file.

use crate::mesh::topology::FaceTopology;
use arkit_core::{Error, Result};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::Path;

/// The manifest's file name in a converted dataset.
pub const MANIFEST_FILE: &str = "dataset.json";

/// Which of the two published layouts the input has.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LayoutKind {
    /// `ARKitFace_image_{split}/image/...`, `ARKitFace_info_{split}/info/...`,
    /// `ARKitFace_list/list/ARKitFace_{split}.csv`.
    Download,
    /// `image/...`, `info/...` and list CSV(s) in the root.
    Flat,
}

/// One finished shard in the manifest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShardEntry {
    /// Shard number.
    pub index: usize,
    /// `samples/part-K.parquet`, relative to the output.
    pub samples_file: String,
    /// Rows in it.
    pub rows: usize,
    /// SHA-256 of the file.
    pub sha256: String,
    /// `errors/part-K.parquet`.
    pub errors_file: String,
    /// Rows in it (samples skipped in this shard).
    pub error_rows: usize,
    /// SHA-256 of the errors file.
    pub errors_sha256: String,
    /// Size of the samples file in bytes (checked by every reader).
    #[serde(default)]
    pub bytes: u64,
    /// SHA-256 of the samples file's last `TAIL_BYTES` (the Parquet footer; checked by
    /// every reader).
    #[serde(default)]
    pub tail_sha256: String,
    /// What the shard was made from: the conversion's fingerprint, the shard's rows and
    /// the size and modification time of their files.
    #[serde(default)]
    pub fingerprint: String,
}

/// How many bytes at a file's end [`tail_sha256`] hashes.
pub(crate) const TAIL_BYTES: u64 = 64 * 1024;

/// `dataset.json` (or one part of it for `--shard I/N`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// `arkit-tool`.
    pub tool: String,
    /// The tool's version.
    pub version: String,
    /// Input root as given.
    pub input: String,
    /// Input root as an absolute path (what later commands read images from; empty in
    /// manifests written before it was recorded).
    #[serde(default)]
    pub input_root: String,
    /// The conversion's fingerprint (`crate::ingest::convert::ConversionFingerprint::digest`).
    #[serde(default)]
    pub fingerprint: String,
    /// `topology_digest` of the topology it was converted with (empty in manifests
    /// written before it was recorded).
    #[serde(default)]
    pub topology_sha256: String,
    /// Layout found.
    pub layout: LayoutKind,
    /// The lists read.
    pub lists: Vec<String>,
    /// Where the topology and landmarks came from.
    pub topology: String,
    /// The conversion's arguments.
    pub rows_per_shard: usize,
    /// Whether JPEG bytes are embedded.
    pub embed_images: bool,
    /// Which part this is (`[I, N]`); `[0, 1]` for a whole dataset.
    pub part: [usize; 2],
    /// Rows listed (all shards of the dataset).
    pub listed: usize,
    /// Samples converted (in the shards of this manifest).
    pub converted: usize,
    /// Samples skipped (in the shards of this manifest).
    pub skipped: usize,
    /// Listing problems (orphan files, repeated rows), when this part reports them.
    pub listing_problems: usize,
    /// Shards, by index.
    pub shards: Vec<ShardEntry>,
}

/// Lower-case hex of a digest.
pub(crate) fn hex(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of a whole file, hex.
pub fn sha256_file(path: &Path) -> Result<String> {
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = std::io::Read::read(&mut file, &mut buf).map_err(|e| Error::io(path, e))?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hex(&hasher.finalize()))
}

/// SHA-256 of a file's last `TAIL_BYTES` bytes (all of a smaller file), hex.
pub fn tail_sha256(path: &Path) -> Result<String> {
    use std::io::{Read, Seek, SeekFrom};
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let start = len.saturating_sub(TAIL_BYTES);
    file.seek(SeekFrom::Start(start))
        .map_err(|e| Error::io(path, e))?;
    let mut tail = Vec::with_capacity((len - start) as usize);
    file.read_to_end(&mut tail)
        .map_err(|e| Error::io(path, e))?;
    Ok(hex(&Sha256::digest(&tail)))
}

/// Checks a shard file against its manifest entry the cheap way: its size, and the
/// SHA-256 of its last `TAIL_BYTES`. Entries written before sizes were recorded
/// (`bytes == 0`) are not checked.
pub fn check_shard_file(path: &Path, bytes: u64, tail: &str) -> Result<()> {
    if bytes == 0 {
        return Ok(());
    }
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    if len != bytes {
        return Err(Error::format(
            path,
            format!(
                "{len} bytes, the manifest says {bytes}: the file changed after convert wrote it; rerun `arkit-tool convert`"
            ),
        ));
    }
    if tail_sha256(path)? != tail {
        return Err(Error::format(
            path,
            "its footer does not match the manifest's checksum: the file changed after convert wrote it; rerun `arkit-tool convert`",
        ));
    }
    Ok(())
}

/// SHA-256 of a topology's vertex count, triangles and landmark indices, hex: what
/// decides whether a dataset's meshes and a command's topology agree.
pub(crate) fn topology_digest(topology: &FaceTopology) -> String {
    let mut h = Sha256::new();
    h.update((topology.vertex_count as u64).to_le_bytes());
    for t in &topology.triangles {
        for v in t {
            h.update(v.to_le_bytes());
        }
    }
    h.update(b"landmarks");
    for l in &topology.landmarks {
        h.update(l.to_le_bytes());
    }
    hex(&h.finalize())
}

/// Checks that `topology` (what a command was given: `--resources`, or the built-in
/// face) is the one a dataset was converted with, so no stage renders or trains a
/// dataset of the real ARKit mesh with the built-in stand-in (or the reverse): both have
/// 1,220 vertices, so nothing else would notice. Compared by `topology_digest` (the
/// triangles and landmarks, wherever the folder now is); manifests written before the
/// digest was recorded are compared by whether each is the built-in face.
pub fn check_topology(manifest: &Manifest, topology: &FaceTopology) -> Result<()> {
    let builtin = &crate::mesh::synthetic_face::builtin().topology.source;
    let (dataset_builtin, ours_builtin) =
        (&manifest.topology == builtin, &topology.source == builtin);
    let same = if manifest.topology_sha256.is_empty() {
        dataset_builtin == ours_builtin
    } else {
        manifest.topology_sha256 == topology_digest(topology)
    };
    if same {
        return Ok(());
    }
    Err(Error::invalid(
        "--resources",
        if ours_builtin {
            format!(
                "the dataset was converted with the topology of '{}'; pass --resources with that folder (without it the built-in face is used)",
                manifest.topology
            )
        } else if dataset_builtin {
            format!(
                "the dataset was converted with the built-in face, not with '{}'; leave --resources out",
                topology.source
            )
        } else {
            format!(
                "the dataset was converted with the topology of '{}', whose triangles or landmarks differ from those of '{}'; pass the --resources given to convert",
                manifest.topology, topology.source
            )
        },
    ))
}

/// The most shards a dataset has (a shard index, and the shards a conversion's rows
/// make, are checked against it before anything is allocated from them).
pub const MAX_SHARDS: usize = 1 << 20;

impl Manifest {
    /// Checks what readers take from it before they allocate or open files by it (the
    /// manifest of `path`): its part `[I, N]` with `I < N`; at least one row per shard
    /// and at most [`MAX_SHARDS`] shards for its listed rows; each shard's index below
    /// [`MAX_SHARDS`] and listed once; its files relative paths inside the dataset's
    /// folder (no `..`, no root). Errors name the file and the field.
    pub fn check(&self, path: &Path) -> Result<()> {
        let bad = |why: String| Err(Error::format(path, format!("not a manifest: {why}")));
        let [i, n] = self.part;
        if i >= n {
            return bad(format!("part [{i}, {n}] is not part I < N of N"));
        }
        if self.rows_per_shard == 0 || self.listed.div_ceil(self.rows_per_shard) > MAX_SHARDS {
            return bad(format!(
                "{} listed rows in shards of {} make more than {MAX_SHARDS} shards (or none per shard)",
                self.listed, self.rows_per_shard
            ));
        }
        let mut seen = std::collections::HashSet::new();
        for s in &self.shards {
            if s.index >= MAX_SHARDS || !seen.insert(s.index) {
                return bad(format!(
                    "shard index {} listed twice or not below {MAX_SHARDS}",
                    s.index
                ));
            }
            for f in [&s.samples_file, &s.errors_file] {
                let inside = !f.is_empty()
                    && Path::new(f)
                        .components()
                        .all(|c| matches!(c, std::path::Component::Normal(_)));
                if !inside {
                    return bad(format!(
                        "shard {}: '{f}' is not a file inside the dataset's folder",
                        s.index
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Reads a manifest, checked ([`Manifest::check`]).
pub fn read_manifest(path: &Path) -> Result<Manifest> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let m: Manifest = serde_json::from_str(&text)
        .map_err(|e| Error::format(path, format!("not a manifest: {e}")))?;
    m.check(path)?;
    Ok(m)
}

/// SHA-256 (hex) of what a dataset's targets and crop stores depend on in its manifest:
/// every samples shard's index, file, rows and checksum (a sample's seed follows from
/// the rows before it) and the topology it was converted with. Unlike the bytes of `dataset.json`, it
/// does not change when the same samples are converted again from another path or
/// merged from `convert --shard` parts.
pub fn dataset_fingerprint(manifest: &Manifest) -> String {
    let shards: Vec<serde_json::Value> = manifest
        .shards
        .iter()
        .map(|s| serde_json::json!([s.index, s.samples_file, s.rows, s.sha256]))
        .collect();
    let text = serde_json::json!({"topology": manifest.topology, "shards": shards}).to_string();
    Sha256::digest(text.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

//! `publication`: a dataset published to a bucket ([`push`]) and its record
//! ([`Publication`], `arkit-publication.json`), which is uploaded last and names every
//! object with its size, SHA-256 and ETag, so a reader never takes a half-published
//! dataset for a whole one and checks every object it reads against the record.

use super::client::RemoteStore;
use super::location::RemoteUrl;
use crate::store::Dataset;
use crate::store::manifest::hex;
use arkit_core::{Error, Result};
use bytes::Bytes;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The publication record's name in the dataset's prefix.
pub const PUBLICATION_FILE: &str = "arkit-publication.json";

/// Its format number.
const PUBLICATION_FORMAT: u32 = 1;

/// The largest publication record read.
const MAX_PUBLICATION_BYTES: usize = 64 << 20;

/// `arkit-publication.json`: what a push published.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Publication {
    /// [`PUBLICATION_FORMAT`].
    pub format: u32,
    /// `arkit-tool`.
    pub tool: String,
    /// The tool's version.
    pub version: String,
    /// The dataset's fingerprint (`crate::store::manifest::dataset_fingerprint`).
    pub dataset_fingerprint: String,
    /// Every object, by its path relative to the prefix, in order.
    pub objects: Vec<PublishedObject>,
}

/// One published object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PublishedObject {
    /// Its path relative to the dataset's prefix (`samples/part-0.parquet`).
    pub path: String,
    /// Its size.
    pub bytes: u64,
    /// The SHA-256 of its content.
    pub sha256: String,
    /// Its ETag after the upload, when the store gives one.
    pub etag: Option<String>,
}

impl Publication {
    /// Reads the record of `store`'s prefix; an error naming it when there is none (no
    /// push finished there) or it is not one.
    pub fn read(store: &RemoteStore) -> Result<(Publication, Option<String>)> {
        let shown = store.url().shown_path(PUBLICATION_FILE);
        let Some((bytes, etag)) = store.get_opt(PUBLICATION_FILE)? else {
            return Err(Error::format(
                &shown,
                format!(
                    "no published dataset at {}: no {PUBLICATION_FILE} (publish one with `arkit-tool push DATASET {}`; a push that did not finish publishes nothing)",
                    store.url(),
                    store.url()
                ),
            ));
        };
        Self::parse(&bytes, &shown).map(|p| (p, etag))
    }

    fn parse(bytes: &[u8], shown: &Path) -> Result<Publication> {
        if bytes.len() > MAX_PUBLICATION_BYTES {
            return Err(Error::format(
                shown,
                format!(
                    "{} bytes, more than a publication record can be",
                    bytes.len()
                ),
            ));
        }
        let p: Publication = serde_json::from_slice(bytes)
            .map_err(|e| Error::format(shown, format!("not a publication record: {e}")))?;
        if p.format != PUBLICATION_FORMAT {
            return Err(Error::format(
                shown,
                format!(
                    "a publication of format {}; this version reads format {PUBLICATION_FORMAT}: push the dataset again",
                    p.format
                ),
            ));
        }
        for o in &p.objects {
            let bad = o.path.is_empty()
                || o.path.starts_with('/')
                || o.path
                    .split('/')
                    .any(|c| c.is_empty() || c == "." || c == "..")
                || o.sha256.len() != 64;
            if bad {
                return Err(Error::format(
                    shown,
                    format!(
                        "names an object '{}' that cannot be part of a dataset",
                        o.path
                    ),
                ));
            }
        }
        Ok(p)
    }

    /// The entry of `path`.
    pub fn object(&self, path: &str) -> Option<&PublishedObject> {
        self.objects.iter().find(|o| o.path == path)
    }
}

/// How [`push`] publishes.
#[derive(Clone, Debug)]
pub struct PushOptions {
    /// Replace a dataset of another fingerprint at the URL.
    pub overwrite: bool,
    /// Files at least this large go up as multipart uploads.
    pub multipart_threshold: u64,
    /// The part size of a multipart upload.
    pub part_bytes: usize,
    /// Client settings that take precedence over the environment's (see
    /// [`super::RemoteOptions::settings`]).
    pub settings: Vec<(String, String)>,
}

impl Default for PushOptions {
    fn default() -> Self {
        PushOptions {
            overwrite: false,
            multipart_threshold: 16 << 20,
            part_bytes: 8 << 20,
            settings: Vec::new(),
        }
    }
}

/// What [`push`] did.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct PushSummary {
    /// The URL published to (without secrets).
    pub url: String,
    /// Objects the publication names.
    pub objects: usize,
    /// Their bytes.
    pub bytes: u64,
    /// Objects uploaded by this push.
    pub uploaded: usize,
    /// Their bytes.
    pub uploaded_bytes: u64,
    /// Of them, as multipart uploads.
    pub multipart: usize,
    /// Objects already there with the same content, left alone.
    pub unchanged: usize,
    /// The dataset's fingerprint.
    pub dataset_fingerprint: String,
}

/// A local file to publish.
struct LocalObject {
    path: String,
    file: PathBuf,
    bytes: u64,
    sha256: String,
}

/// The files of the dataset folder `dir` a push publishes: every regular file but
/// temporaries, locks and an earlier publication record, by relative path; manifests
/// (`dataset.json`, each store's `crops.json`) after the files they describe.
fn local_objects(dir: &Path) -> Result<Vec<LocalObject>> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<(String, PathBuf, u64)>) -> Result<()> {
        let mut entries: Vec<_> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .collect::<std::io::Result<_>>()
            .map_err(|e| Error::io(dir, e))?;
        entries.sort_by_key(|e| e.file_name());
        for e in entries {
            let path = e.path();
            let name = e.file_name().to_string_lossy().into_owned();
            if arkit_core::atomic_file::is_temporary_name(&name)
                || name.ends_with(".lock")
                || name == PUBLICATION_FILE
            {
                continue;
            }
            let meta = std::fs::symlink_metadata(&path).map_err(|e| Error::io(&path, e))?;
            if meta.is_dir() {
                walk(root, &path, out)?;
            } else if meta.is_file() {
                let rel = path
                    .strip_prefix(root)
                    .expect("inside the root")
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect::<Vec<_>>()
                    .join("/");
                out.push((rel, path, meta.len()));
            }
        }
        Ok(())
    }
    let mut found = Vec::new();
    walk(dir, dir, &mut found)?;
    let manifest_rank = |p: &str| {
        if p == crate::store::manifest::MANIFEST_FILE {
            2
        } else if p.ends_with("/crops.json") {
            1
        } else {
            0
        }
    };
    found.sort_by(|a, b| (manifest_rank(&a.0), &a.0).cmp(&(manifest_rank(&b.0), &b.0)));
    found
        .into_iter()
        .map(|(path, file, bytes)| {
            let sha256 = crate::store::manifest::sha256_file(&file)?;
            Ok(LocalObject {
                path,
                file,
                bytes,
                sha256,
            })
        })
        .collect()
}

/// Publishes the converted dataset in `dir` (with whatever it holds: splits, targets,
/// crop stores) to `url`: every object that is not already there with the same content
/// is uploaded (multipart from [`PushOptions::multipart_threshold`]), then the
/// publication record last. A push over a dataset of another fingerprint is refused
/// without [`PushOptions::overwrite`]; a push killed and run again uploads only what is
/// missing or different. `on_bytes` is told of the bytes as they go up (for a progress
/// bar; its total is the dataset's size).
pub fn push(
    dir: &Path,
    url: &RemoteUrl,
    options: &PushOptions,
    on_total: &dyn Fn(u64),
    on_bytes: &(dyn Fn(u64) + Sync),
) -> Result<PushSummary> {
    let dataset = Dataset::open(dir)?;
    let fingerprint = crate::store::manifest::dataset_fingerprint(dataset.manifest());
    let local = local_objects(dir)?;
    // What `inspect --verify` checks, from the hashes just taken (each file read once):
    // every samples and errors file the manifest names, against its full SHA-256.
    for s in dataset.shards() {
        for (file, sha) in [
            (&s.samples_file, &s.sha256),
            (&s.errors_file, &s.errors_sha256),
        ] {
            let path = dir.join(file);
            match local.iter().find(|o| o.path == *file) {
                Some(o) if o.sha256 == *sha => {}
                Some(_) => {
                    return Err(Error::format(
                        &path,
                        "its SHA-256 differs from the manifest's: the file changed after convert wrote it; rerun `arkit-tool convert`",
                    ));
                }
                None => {
                    return Err(Error::format(
                        &path,
                        "named by dataset.json but not in the folder; rerun `arkit-tool convert`",
                    ));
                }
            }
        }
    }
    let total: u64 = local.iter().map(|o| o.bytes).sum();
    on_total(total);
    let store: Arc<RemoteStore> = RemoteStore::with_settings(url, &options.settings)?;
    // What is there now: a whole publication, or the objects of a push that stopped.
    let previous = match store.get_opt(PUBLICATION_FILE)? {
        Some((bytes, _)) => Some(Publication::parse(
            &bytes,
            &url.shown_path(PUBLICATION_FILE),
        )?),
        None => None,
    };
    let remote_manifest = store.get_opt(crate::store::manifest::MANIFEST_FILE)?;
    let remote_fingerprint = match (&previous, &remote_manifest) {
        (Some(p), _) => Some(p.dataset_fingerprint.clone()),
        (None, Some((bytes, _))) => {
            serde_json::from_slice::<crate::store::manifest::Manifest>(bytes)
                .ok()
                .map(|m| crate::store::manifest::dataset_fingerprint(&m))
        }
        (None, None) => None,
    };
    if let Some(theirs) = &remote_fingerprint
        && *theirs != fingerprint
        && !options.overwrite
    {
        return Err(Error::invalid(
            "push",
            format!(
                "{url} holds another dataset (fingerprint {}..., this one is {}...): pass --overwrite to replace it",
                &theirs[..theirs.len().min(12)],
                &fingerprint[..12]
            ),
        ));
    }
    let mut summary = PushSummary {
        url: url.to_string(),
        dataset_fingerprint: fingerprint.clone(),
        objects: local.len(),
        bytes: total,
        ..Default::default()
    };
    // Unchanged since the last whole publication: nothing to do, and no reader disturbed.
    if let Some(p) = &previous
        && p.dataset_fingerprint == fingerprint
        && p.objects.len() == local.len()
        && p.objects
            .iter()
            .zip(&local)
            .all(|(r, l)| r.path == l.path && r.sha256 == l.sha256 && r.bytes == l.bytes)
    {
        let all_there = local
            .iter()
            .all(|l| store.head(&l.path).is_ok_and(|m| m.size == l.bytes));
        if all_there {
            summary.unchanged = local.len();
            on_bytes(total);
            return Ok(summary);
        }
    }
    // From here until the record is written again, the prefix is not a publication: a
    // reader opening it is refused instead of reading a half-replaced dataset.
    if previous.is_some() {
        store.delete(PUBLICATION_FILE)?;
    }
    let mut published = Vec::with_capacity(local.len());
    for l in &local {
        let there = store.head_with_sha(&l.path)?;
        let same = there
            .as_ref()
            .is_some_and(|(m, sha)| m.size == l.bytes && sha.as_deref() == Some(l.sha256.as_str()));
        let etag = if same {
            summary.unchanged += 1;
            on_bytes(l.bytes);
            there.and_then(|(m, _)| m.e_tag)
        } else {
            summary.uploaded += 1;
            summary.uploaded_bytes += l.bytes;
            if l.bytes >= options.multipart_threshold {
                summary.multipart += 1;
                store.put_multipart(
                    &l.path,
                    &l.file,
                    &l.sha256,
                    options.part_bytes.max(5 << 20),
                    on_bytes,
                )?
            } else {
                let bytes = std::fs::read(&l.file).map_err(|e| Error::io(&l.file, e))?;
                if hex(&Sha256::digest(&bytes)) != l.sha256 {
                    return Err(Error::format(
                        &l.file,
                        "changed while it was being pushed; push again when no writer runs",
                    ));
                }
                let etag = store.put(&l.path, Bytes::from(bytes), &l.sha256)?;
                on_bytes(l.bytes);
                etag
            }
        };
        published.push(PublishedObject {
            path: l.path.clone(),
            bytes: l.bytes,
            sha256: l.sha256.clone(),
            etag,
        });
    }
    let record = Publication {
        format: PUBLICATION_FORMAT,
        tool: "arkit-tool".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        dataset_fingerprint: fingerprint,
        objects: published,
    };
    let text = serde_json::to_vec_pretty(&record).expect("the record serialises");
    let sha = hex(&Sha256::digest(&text));
    store.put(PUBLICATION_FILE, Bytes::from(text), &sha)?;
    Ok(summary)
}

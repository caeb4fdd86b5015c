//! `mirror`: a published dataset opened from its bucket ([`open_remote`]): its
//! publication record read, the small files a reader needs (manifests, Parquet tables)
//! copied into a local mirror and checked against the record, the crop stores' part
//! files left in the bucket to be read by ranges ([`RemoteDataset::open_object`]).

use super::cache::RecordCache;
use super::client::{RemoteObject, RemoteStore};
use super::location::RemoteUrl;
use super::publication::{Publication, PublishedObject};
use crate::crop::RuleSet;
use crate::store::crop_store::CropStore;
use crate::store::manifest::hex;
use crate::store::{Dataset, ReadAt};
use arkit_core::{Error, Result};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// How a remote dataset is read.
#[derive(Clone, Debug, Default)]
pub struct RemoteOptions {
    /// Where the mirror of its tables and the record cache live (default:
    /// `$ARKIT_CACHE_DIR`, else `$XDG_CACHE_HOME/arkit-tool`, else
    /// `~/.cache/arkit-tool`). The record cache is on only when this is given.
    pub cache_dir: Option<PathBuf>,
    /// The record cache's cap in bytes (default 10 GiB when `cache_dir` is given; 0:
    /// no record cache).
    pub cache_bytes: Option<u64>,
    /// Client settings (`object_store`'s keys: `aws_endpoint`, `aws_region`, ...) that
    /// take precedence over the environment's.
    pub settings: Vec<(String, String)>,
}

/// Which objects the mirror copies.
#[derive(Clone, Debug)]
pub enum MirrorSet {
    /// What the loader reads: `dataset.json`, the samples tables, the splits, and the
    /// manifest (`crops.json`) of the crop store at the given relative path.
    Loader {
        /// The crop store's folder relative to the dataset (`crops/official-192`).
        crop_store: Option<String>,
    },
    /// Every object but the crop stores' part files (what the commands read: targets,
    /// predictions, errors tables too).
    Tables,
}

impl MirrorSet {
    fn wants(&self, path: &str) -> bool {
        if is_crop_part(path) {
            return false;
        }
        match self {
            MirrorSet::Tables => true,
            MirrorSet::Loader { crop_store } => {
                path == crate::store::manifest::MANIFEST_FILE
                    || path.starts_with("samples/")
                    || path.starts_with("splits/")
                    || crop_store
                        .as_deref()
                        .is_some_and(|s| path == format!("{}/crops.json", s.trim_end_matches('/')))
            }
        }
    }
}

/// A crop store's part file (`.../part-K.bin`): read by ranges, never mirrored.
fn is_crop_part(path: &str) -> bool {
    let name = path.rsplit('/').next().unwrap_or(path);
    path.contains("crops/") && name.starts_with("part-") && name.ends_with(".bin")
}

/// A published dataset opened from its bucket.
#[derive(Debug)]
pub struct RemoteDataset {
    store: Arc<RemoteStore>,
    publication: Publication,
    mirror: PathBuf,
    cache: Option<Arc<RecordCache>>,
}

/// The default cache folder (see [`RemoteOptions::cache_dir`]).
fn default_cache_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("ARKIT_CACHE_DIR").filter(|d| !d.is_empty()) {
        return PathBuf::from(d);
    }
    if let Some(d) = std::env::var_os("XDG_CACHE_HOME").filter(|d| !d.is_empty()) {
        return PathBuf::from(d).join("arkit-tool");
    }
    match std::env::var_os("HOME").filter(|d| !d.is_empty()) {
        Some(h) => PathBuf::from(h).join(".cache").join("arkit-tool"),
        None => std::env::temp_dir().join("arkit-tool-cache"),
    }
}

/// Opens the dataset published at `url`: reads its publication record (an error naming
/// the URL when there is none), copies the objects `set` names into the local mirror
/// (those already there with the recorded SHA-256 are not fetched again), each checked
/// for its size and SHA-256 against the record.
pub fn open_remote(
    url: &RemoteUrl,
    set: &MirrorSet,
    options: &RemoteOptions,
) -> Result<RemoteDataset> {
    let store = RemoteStore::with_settings(url, &options.settings)?;
    let (publication, _) = Publication::read(&store)?;
    let base = options.cache_dir.clone().unwrap_or_else(default_cache_dir);
    let record = serde_json::to_vec(&publication).expect("the record serialises");
    let mirror = base.join("datasets").join(format!(
        "{}-{}",
        &hex(&Sha256::digest(url.to_string().as_bytes()))[..16],
        &hex(&Sha256::digest(&record))[..16]
    ));
    std::fs::create_dir_all(&mirror).map_err(|e| Error::io(&mirror, e))?;
    let cache = match &options.cache_dir {
        Some(_) if options.cache_bytes == Some(0) => None,
        Some(dir) => Some(Arc::new(RecordCache::new(
            &dir.join("records"),
            options.cache_bytes.unwrap_or(10 << 30),
        )?)),
        None => None,
    };
    let remote = RemoteDataset {
        store,
        publication,
        mirror,
        cache,
    };
    let wanted: Vec<PublishedObject> = remote
        .publication
        .objects
        .iter()
        .filter(|o| set.wants(&o.path))
        .cloned()
        .collect();
    if remote
        .publication
        .object(crate::store::manifest::MANIFEST_FILE)
        .is_none()
    {
        return Err(Error::format(
            url.shown_path(super::PUBLICATION_FILE),
            "names no dataset.json: not a published dataset",
        ));
    }
    for o in &wanted {
        remote.fetch(o)?;
    }
    let manifest = crate::store::manifest::read_manifest(
        &remote.mirror.join(crate::store::manifest::MANIFEST_FILE),
    )?;
    if crate::store::manifest::dataset_fingerprint(&manifest)
        != remote.publication.dataset_fingerprint
    {
        return Err(Error::format(
            url.shown_path(crate::store::manifest::MANIFEST_FILE),
            "is not the dataset its publication record names (another fingerprint): push it again",
        ));
    }
    Ok(remote)
}

impl RemoteDataset {
    /// The mirror's folder: what [`crate::store::Dataset::open`] and the other readers
    /// open in place of the bucket.
    pub fn local_dir(&self) -> &Path {
        &self.mirror
    }

    /// The URL.
    pub fn url(&self) -> &RemoteUrl {
        self.store.url()
    }

    /// The publication record.
    pub fn publication(&self) -> &Publication {
        &self.publication
    }

    /// The record cache, when on.
    pub fn cache(&self) -> Option<&Arc<RecordCache>> {
        self.cache.as_ref()
    }

    /// Copies `relative` into the mirror (if it is not there already) and returns its
    /// local path; an error when the publication does not name it.
    pub fn mirror_file(&self, relative: &str) -> Result<PathBuf> {
        let o = self.publication.object(relative).ok_or_else(|| {
            Error::format(
                self.url().shown_path(relative),
                "not in the dataset's publication record (push it, or make it before pushing)",
            )
        })?;
        self.fetch(&o.clone())
    }

    fn fetch(&self, o: &PublishedObject) -> Result<PathBuf> {
        let local = self.mirror.join(&o.path);
        if std::fs::metadata(&local).is_ok_and(|m| m.len() == o.bytes)
            && crate::store::manifest::sha256_file(&local).is_ok_and(|s| s == o.sha256)
        {
            return Ok(local);
        }
        let shown = self.url().shown_path(&o.path);
        let (bytes, _) = self.store.get(&o.path)?;
        let sha = hex(&Sha256::digest(&bytes));
        if bytes.len() as u64 != o.bytes || sha != o.sha256 {
            return Err(Error::format(
                &shown,
                format!(
                    "{} bytes of SHA-256 {}..., the publication record says {} bytes of {}...: it changed since it was published; push the dataset again",
                    bytes.len(),
                    &sha[..12],
                    o.bytes,
                    &o.sha256[..12]
                ),
            ));
        }
        if let Some(parent) = local.parent() {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        }
        arkit_core::atomic_file::write_bytes(&local, &bytes)?;
        Ok(local)
    }

    /// The crop store of this dataset at `relative` (the store's folder in the
    /// dataset, `crops/official-192`), its manifest read from `dir` (its mirror,
    /// [`RemoteDataset::mirror_file`]), its part files read by ranged GETs, each pinned to
    /// the ETag it was published with: [`CropStore::open`]'s checks, for `dataset`,
    /// crops of rule set `rules` and side `img_size`, meshes of `vertex_count`
    /// vertices.
    pub fn open_crop_store(
        &self,
        dir: &Path,
        relative: &str,
        dataset: &Dataset,
        rules: RuleSet,
        img_size: u32,
        vertex_count: usize,
    ) -> Result<CropStore> {
        let relative = relative.trim_end_matches('/');
        let open_part = |file: &str| -> Result<Box<dyn ReadAt>> {
            Ok(Box::new(self.open_object(&format!("{relative}/{file}"))?))
        };
        CropStore::open_with(dir, &open_part, dataset, rules, img_size, vertex_count)
    }

    /// Opens the object `relative` for ranged reads (one HEAD): its size must be the
    /// recorded one and its ETag, when the store gives them, the recorded one; reads are
    /// then pinned to that ETag.
    pub fn open_object(&self, relative: &str) -> Result<RemoteObject> {
        let shown = self.url().shown_path(relative);
        let o = self
            .publication
            .object(relative)
            .ok_or_else(|| Error::format(&shown, "not in the dataset's publication record"))?;
        let obj = RemoteObject::open(self.store.clone(), relative, self.cache.clone())?;
        if obj.len() != o.bytes {
            return Err(Error::format(
                &shown,
                format!(
                    "{} bytes, the publication record says {}: it changed since it was published",
                    obj.len(),
                    o.bytes
                ),
            ));
        }
        if let (Some(now), Some(was)) = (obj.etag(), o.etag.as_deref())
            && now != was
        {
            return Err(Error::format(
                &shown,
                format!(
                    "ETag {now}, the publication record says {was}: it changed since it was published"
                ),
            ));
        }
        Ok(obj)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_loader_mirrors_its_tables_and_never_a_crop_part() {
        let set = MirrorSet::Loader {
            crop_store: Some("crops/official-192".into()),
        };
        assert!(set.wants("dataset.json"));
        assert!(set.wants("samples/part-0.parquet"));
        assert!(set.wants("crops/official-192/crops.json"));
        assert!(!set.wants("crops/official-192/part-0.bin"));
        assert!(!set.wants("crops/exact-192/crops.json"));
        assert!(!set.wants("targets/part-0.parquet"));
        assert!(MirrorSet::Tables.wants("targets/part-0.parquet"));
        assert!(!MirrorSet::Tables.wants("crops/exact-192/part-3.bin"));
    }
}

//! A converted dataset, opened once: its manifest, its shards (checked against the
//! manifest before they are read), and its samples' images.
//!
//! Every stage after `convert` (render, split, train, predict, augment, eval) opens the
//! folder `convert` wrote through [`Dataset::open`]. It guarantees:
//!
//! - **Shards are the ones the manifest names.** [`Dataset::samples_path`] checks a
//!   shard's size and the SHA-256 of its last 64 KiB (the Parquet footer) against
//!   `dataset.json` before anything reads it: cheap (one `stat` and 64 KiB) and enough to
//!   catch a shard replaced, truncated or rewritten since `convert`. The full SHA-256 of
//!   every file is checked by [`crate::ingest::convert::verify_dataset`] (`arkit-tool inspect
//!   --verify`).
//! - **Images are found or the sample is reported, never substituted.** Images not
//!   embedded in the table are read from the input root that `convert` recorded as an
//!   absolute path (`input_root` in `dataset.json`; older manifests: `input`, as given,
//!   relative to the working directory). `ARKIT_INPUT_ROOT` overrides it for a release
//!   that has moved. [`Dataset::image`] returns an error that names the file, the reason
//!   and where the images were looked for; callers report the sample and skip it.
//!
//! - **A reader serves the generation it opened.** [`Dataset::open`] opens every shard
//!   file it names and keeps it open: rows are read through those files, which keep the
//!   bytes they had even after `convert --overwrite` removed them or renamed new ones
//!   over their names. A shard that could not be held is reopened when it is read and
//!   checked against the opened manifest; one that is not the opened generation's is
//!   refused with [`Dataset::changed`], an error naming the folder.
//!   [`Dataset::confirm_unchanged`] tells a reader whether what it read besides the
//!   shards (split files, targets) belongs to the generation it opened.
//!
//! Tested in `tests/hostile.rs`: a moved release is an error naming the file and the
//! root (no grey image), the override finds it again, a rewritten shard is refused;
//! in `tests/readers.rs`: `train`, `predict --dataset` and `eval` beside
//! `convert --overwrite`, `render --overwrite` and `crops`.

use crate::store::manifest::{
    Manifest, ShardEntry, TAIL_BYTES, check_shard_file, dataset_fingerprint, read_manifest,
};
use crate::store::parquet::HeldFile;
use crate::store::samples_table::{self, SampleRecord};
use arkit_core::SampleKey;
use arkit_core::{Error, Result};
use image::RgbImage;
use std::path::{Path, PathBuf};

use crate::store::manifest::MANIFEST_FILE;

/// The environment variable that overrides the input root recorded in a manifest.
pub(crate) const INPUT_ROOT_ENV: &str = "ARKIT_INPUT_ROOT";

/// A converted dataset (the folder `convert` wrote).
#[derive(Clone, Debug)]
pub struct Dataset {
    dir: PathBuf,
    manifest: Manifest,
    image_root: PathBuf,
    image_root_from: &'static str,
    /// The manifest's [`dataset_fingerprint`]: the generation opened.
    generation: String,
    /// The shard files opened with the manifest, by position in its shards (`None`: not
    /// there, or not the manifest's, when the folder was opened).
    held: std::sync::Arc<Vec<Option<HeldFile>>>,
}

impl Dataset {
    /// The manifest of the dataset in `dir` alone (checked; no file held), for a
    /// command that checks options against it before its reader opens the folder.
    pub fn read_manifest(dir: &Path) -> Result<Manifest> {
        let manifest_path = dir.join(MANIFEST_FILE);
        if !manifest_path.exists() {
            return Err(Error::format(
                dir,
                format!(
                    "not a converted dataset: no {MANIFEST_FILE} here (run `arkit-tool convert`, or `arkit-tool merge` after a sharded conversion)"
                ),
            ));
        }
        read_manifest(&manifest_path)
    }

    /// Opens the dataset in `dir`: reads `dir/dataset.json` and resolves where its
    /// images are.
    pub fn open(dir: &Path) -> Result<Self> {
        let manifest = Self::read_manifest(dir)?;
        let (image_root, image_root_from) = match std::env::var_os(INPUT_ROOT_ENV) {
            Some(root) if !root.is_empty() => (PathBuf::from(root), "ARKIT_INPUT_ROOT"),
            _ if !manifest.input_root.is_empty() => (
                PathBuf::from(&manifest.input_root),
                "input_root in dataset.json",
            ),
            _ => (PathBuf::from(&manifest.input), "input in dataset.json"),
        };
        // Each shard held when it is the manifest's; a kill-torn or replaced folder
        // holds what it can and the rest is refused when it is read.
        let held = manifest
            .shards
            .iter()
            .map(|s| {
                let file = HeldFile::open(&dir.join(&s.samples_file)).ok()?;
                matches_entry(&file, s).then_some(file)
            })
            .collect();
        let generation = dataset_fingerprint(&manifest);
        let data = Self {
            dir: dir.to_path_buf(),
            manifest,
            image_root,
            image_root_from,
            generation,
            held: std::sync::Arc::new(held),
        };
        arkit_core::atomic_file::reader_pause("opened", dir);
        Ok(data)
    }

    /// The generation opened: the [`dataset_fingerprint`] of its manifest.
    pub fn generation(&self) -> &str {
        &self.generation
    }

    /// The refusal of a reader that found the folder changed since it opened it: names
    /// the folder and says what to do. `what` is what it found changed.
    pub fn changed(&self, what: &str) -> Error {
        Error::format(
            &self.dir,
            format!(
                "the dataset changed while this command read it ({what}; another `convert --overwrite` or `render` replaced its files): stopped rather than mix two generations; run the command again"
            ),
        )
    }

    /// Ok when `dataset.json` still names the generation opened: then whatever the
    /// reader read since it opened the folder (split files, targets) is of that
    /// generation, as `convert` removes `dataset.json` first and writes it last.
    /// [`Dataset::changed`] otherwise.
    pub fn confirm_unchanged(&self) -> Result<()> {
        let path = self.dir.join(MANIFEST_FILE);
        match read_manifest(&path) {
            Ok(m) if dataset_fingerprint(&m) == self.generation => Ok(()),
            Ok(_) => Err(self.changed(&format!("{MANIFEST_FILE} is another conversion's now"))),
            Err(_) => Err(self.changed(&format!("{MANIFEST_FILE} is gone or being rewritten"))),
        }
    }

    /// The held file of `shard`, or the file at its path opened now and checked against
    /// the opened manifest (refused as changed when it is another generation's).
    fn with_shard_file<T>(
        &self,
        shard: &ShardEntry,
        read: impl FnOnce(&HeldFile) -> Result<T>,
    ) -> Result<T> {
        let position = self.manifest.shards.iter().position(|s| s == shard);
        if let Some(Some(file)) = position.and_then(|p| self.held.get(p)) {
            arkit_core::atomic_file::reader_pause("reading", &self.dir);
            return read(file);
        }
        let path = self.samples_path(shard).map_err(|e| self.explain(e))?;
        let file = HeldFile::open(&path).map_err(|e| self.explain(Error::io(&path, e)))?;
        if !matches_entry(&file, shard) {
            return Err(self.explain(Error::format(
                &path,
                "not the file the manifest names: it changed after convert wrote it; rerun `arkit-tool convert`",
            )));
        }
        read(&file)
    }

    /// `e`, an error reading a shard, or [`Dataset::changed`] when the folder changed
    /// since it was opened (the likely cause).
    fn explain(&self, e: Error) -> Error {
        match self.confirm_unchanged() {
            Ok(()) => e,
            Err(changed) => changed,
        }
    }

    /// The dataset's folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Its manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Its shards, by index.
    pub fn shards(&self) -> &[ShardEntry] {
        &self.manifest.shards
    }

    /// The folder images that are not embedded are read from.
    pub(crate) fn image_root(&self) -> &Path {
        &self.image_root
    }

    /// The path of a shard's samples file, after checking it against the manifest.
    pub fn samples_path(&self, shard: &ShardEntry) -> Result<PathBuf> {
        let path = self.dir.join(&shard.samples_file);
        check_shard_file(&path, shard.bytes, &shard.tail_sha256)?;
        Ok(path)
    }

    /// The rows of one shard, of the generation opened.
    pub fn read_samples(&self, shard: &ShardEntry) -> Result<Vec<SampleRecord>> {
        self.with_shard_file(shard, |file| {
            samples_table::samples_from_frame(&file.read_frame(None)?, file.path(), None)
        })
    }

    /// The keys and listed splits of one shard (without the meshes), of the generation
    /// opened.
    pub fn read_sample_keys(&self, shard: &ShardEntry) -> Result<Vec<(SampleKey, String)>> {
        self.with_shard_file(shard, |file| {
            let columns = samples_table::SAMPLE_KEY_COLUMNS;
            samples_table::sample_keys_from_frame(&file.read_frame(Some(&columns))?, file.path())
        })
    }

    /// The rows of every shard, in order.
    pub fn read_all_samples(&self) -> Result<Vec<SampleRecord>> {
        let mut out = Vec::new();
        for s in self.shards() {
            out.extend(self.read_samples(s)?);
        }
        Ok(out)
    }

    /// Where the image of `sample` is read from (`None` when it is embedded).
    pub fn image_path(&self, sample: &SampleRecord) -> Option<PathBuf> {
        sample
            .jpeg
            .is_none()
            .then(|| self.image_root.join(&sample.image_path))
    }

    /// The decoded image of `sample`, or an error naming the file, the reason and where
    /// the images are looked for. The image must have the size the table records,
    /// checked from its header before it is decoded
    /// (`crate::picture::image_decode::decode_rgb8_checked`, which also bounds its size).
    pub fn image(&self, sample: &SampleRecord) -> Result<RgbImage> {
        let (path, read);
        let bytes: &[u8] = match &sample.jpeg {
            Some(bytes) => {
                path = self.dir.join(&sample.image_path);
                bytes
            }
            None => {
                path = self.image_root.join(&sample.image_path);
                read =
                    crate::picture::image_decode::read_image_file(&path).map_err(|e| match e {
                        Error::Io { source, .. } => self.not_found(&path, source),
                        other => other,
                    })?;
                &read
            }
        };
        let what = match sample.jpeg {
            Some(_) => format!("the embedded JPEG of {}", sample.key),
            None => "the image".to_string(),
        };
        crate::picture::image_decode::decode_rgb8_checked(bytes, &path, |h| {
            if (h.width, h.height) != (sample.image_width, sample.image_height) {
                return Err(Error::format(
                    &path,
                    format!(
                        "{what} is {}x{}, the samples table says {}x{}: it changed since convert",
                        h.width, h.height, sample.image_width, sample.image_height
                    ),
                ));
            }
            Ok(())
        })
        .map_err(|e| match e {
            Error::Format { message, .. } if sample.jpeg.is_some() && !message.contains(&what) => {
                Error::format(&path, format!("{what}: {message}"))
            }
            other => other,
        })
    }

    /// Checks that the image of `sample` can be found and has the recorded size, from
    /// its header alone (no decoding): what a stage that reads images later checks for
    /// every sample before it starts.
    pub fn check_image(&self, sample: &SampleRecord) -> Result<()> {
        let Some(path) = self.image_path(sample) else {
            return Ok(());
        };
        let reader = image::ImageReader::open(&path)
            .map_err(|e| self.not_found(&path, e))?
            .with_guessed_format()
            .map_err(|e| Error::io(&path, e))?;
        let (w, h) = reader
            .into_dimensions()
            .map_err(|e| Error::format(&path, format!("cannot read the image header: {e}")))?;
        if (w, h) != (sample.image_width, sample.image_height) {
            return Err(Error::format(
                &path,
                format!(
                    "the image is {w}x{h}, the samples table says {}x{}: it changed since convert",
                    sample.image_width, sample.image_height
                ),
            ));
        }
        Ok(())
    }

    fn not_found(&self, path: &Path, e: std::io::Error) -> Error {
        Error::format(
            path,
            format!(
                "cannot read the sample's image ({e}); images are read from {} ({}); if the release moved, set {INPUT_ROOT_ENV} to its new folder",
                self.image_root.display(),
                self.image_root_from
            ),
        )
    }
}

/// Whether the open `file` is the one the manifest entry `shard` names (its size and the
/// SHA-256 of its footer; entries without a size are taken as they are).
fn matches_entry(file: &HeldFile, shard: &ShardEntry) -> bool {
    shard.bytes == 0
        || (file.len().ok() == Some(shard.bytes)
            && file.tail_sha256(TAIL_BYTES).ok().as_deref() == Some(shard.tail_sha256.as_str()))
}

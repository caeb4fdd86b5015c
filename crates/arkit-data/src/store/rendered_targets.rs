//! The targets a reader uses (`DIR/targets/`, what `render` wrote), opened once with the
//! dataset they belong to and served as they were then.
//!
//! [`RenderedTargets::open`] reads `targets/render.json` and opens every shard's targets
//! and errors files, keeping them open: a `render --overwrite` that replaces them later
//! changes nothing this reader serves. Targets rendered from another generation of the
//! dataset than the one opened (their `render.json` names another dataset fingerprint)
//! are refused; a `render.json` rewritten while the files were being opened is refused as
//! a change of the folder. A shard whose file was not there at open is opened when it is
//! read, and refused as a change when `render.json` is no longer the one read at open
//! (a `render` writes `render.json` before any shard of new settings).

use crate::store::dataset::Dataset;
use crate::store::parquet::HeldFile;
use crate::store::samples_table;
use crate::store::targets_table::{self, TargetsRecord, errors_path, shard_path};
use arkit_core::{Error, Result, SampleKey};
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

/// The targets of a dataset's shards under a folder, held open (see the module docs).
#[derive(Debug)]
pub struct RenderedTargets {
    /// The folder holding `targets/`.
    dir: PathBuf,
    /// The bytes of `targets/render.json` at open (`None`: there was none).
    settings: Option<Vec<u8>>,
    /// Per shard index: its targets file and its errors file, when they were there.
    files: HashMap<usize, (Option<HeldFile>, Option<HeldFile>)>,
}

/// The bytes of `path`, `None` when it does not exist.
fn read_if_there(path: &Path) -> Result<Option<Vec<u8>>> {
    match std::fs::read(path) {
        Ok(bytes) => Ok(Some(bytes)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(Error::io(path, e)),
    }
}

impl RenderedTargets {
    /// Opens the targets under `dir` (`dir/targets/`) of the shards of `data`.
    pub fn open(dir: &Path, data: &Dataset) -> Result<RenderedTargets> {
        let settings_path = dir.join("targets").join("render.json");
        let settings = read_if_there(&settings_path)?;
        if let Some(rendered_from) = settings
            .as_deref()
            .and_then(|b| serde_json::from_slice::<serde_json::Value>(b).ok())
            .and_then(|v| {
                v.get("dataset")
                    .and_then(|d| d.as_str())
                    .map(str::to_string)
            })
            && rendered_from != data.generation()
        {
            // The dataset replaced under this reader, or targets left from another
            // conversion.
            data.confirm_unchanged()?;
            return Err(Error::format(
                dir.join("targets"),
                format!(
                    "rendered from another conversion of the dataset than {} holds now (render.json's dataset fingerprint differs): run `arkit-tool render` again",
                    data.dir().display()
                ),
            ));
        }
        let files = data
            .shards()
            .iter()
            .map(|s| {
                let targets = HeldFile::open(&shard_path(dir, s.index)).ok();
                let errors = HeldFile::open(&errors_path(dir, s.index)).ok();
                (s.index, (targets, errors))
            })
            .collect();
        let targets = RenderedTargets {
            dir: dir.to_path_buf(),
            settings,
            files,
        };
        targets.confirm_unchanged()?;
        Ok(targets)
    }

    /// Ok while `render.json` is the one read at open; otherwise the refusal naming
    /// the targets folder as changed.
    pub fn confirm_unchanged(&self) -> Result<()> {
        let path = self.dir.join("targets").join("render.json");
        if read_if_there(&path)? != self.settings {
            return Err(Error::format(
                self.dir.join("targets"),
                "the targets changed while this command read them (render.json was rewritten: another `render` replaced them): stopped rather than mix two generations; run the command again",
            ));
        }
        Ok(())
    }

    /// Whether shard `index` has its targets file (held, or there now).
    pub fn has(&self, index: usize) -> bool {
        matches!(self.files.get(&index), Some((Some(_), _)))
            || shard_path(&self.dir, index).exists()
    }

    /// The targets file of shard `index` (`DIR/targets/part-KKKKK.parquet`), for errors.
    pub fn shard_path(&self, index: usize) -> PathBuf {
        shard_path(&self.dir, index)
    }

    /// Reads through the held file `held`, or the file at `path` opened now (after which
    /// `render.json` must still be the one read at open); `None` when neither exists.
    fn read<T>(
        &self,
        held: Option<&HeldFile>,
        path: &Path,
        read: impl FnOnce(&HeldFile) -> Result<T>,
    ) -> Result<Option<T>> {
        if let Some(file) = held {
            return read(file).map(Some);
        }
        let file = match HeldFile::open(path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Error::io(path, e)),
        };
        self.confirm_unchanged()?;
        read(&file).map(Some)
    }

    /// The rows of shard `index` (empty when its file is absent: callers that need it
    /// check [`RenderedTargets::has`] first).
    pub fn rows(&self, index: usize) -> Result<Vec<TargetsRecord>> {
        let held = self.files.get(&index).and_then(|(t, _)| t.as_ref());
        let rows = self.read(held, &shard_path(&self.dir, index), |f| {
            targets_table::targets_from_frame(&f.read_frame(None)?, f.path())
        })?;
        Ok(rows.unwrap_or_default())
    }

    /// The rows of shard `index` by sample key.
    pub fn by_key(&self, index: usize) -> Result<HashMap<SampleKey, TargetsRecord>> {
        Ok(self
            .rows(index)?
            .into_iter()
            .map(|t| (t.key.clone(), t))
            .collect())
    }

    /// The keys of the samples `render` skipped in shard `index` (none without an
    /// errors file).
    pub fn skipped(&self, index: usize) -> Result<HashSet<SampleKey>> {
        let held = self.files.get(&index).and_then(|(_, e)| e.as_ref());
        let rows = self.read(held, &errors_path(&self.dir, index), |f| {
            samples_table::errors_from_frame(&f.read_frame(None)?, f.path())
        })?;
        Ok(rows
            .unwrap_or_default()
            .into_iter()
            .map(|e| e.key)
            .collect())
    }
}

//! `discover` and `plan_rows`: what a release folder holds and the rows `convert` will
//! validate, in list order (train before test), with the files no list names.

use crate::store::manifest::LayoutKind;
use crate::store::samples_table::ErrorRecord;
use arkit_core::release::{self, ListRow, SampleKey};
use arkit_core::{Error, Result};
use std::collections::{BTreeSet, HashSet};
use std::path::{Path, PathBuf};

/// What [`discover`] found.
#[derive(Clone, Debug)]
pub struct DiscoveredInput {
    /// The input root.
    pub root: PathBuf,
    /// The layout.
    pub kind: LayoutKind,
    /// `(split name, list CSV)` pairs, train first.
    pub lists: Vec<(String, PathBuf)>,
}

impl DiscoveredInput {
    /// Image path of a sample, relative to the root.
    pub fn image_relative(&self, split: &str, key: &SampleKey) -> PathBuf {
        self.data_dir(split, "image")
            .join(&key.subject_id)
            .join(&key.facial_action)
            .join(format!("{}_ar.jpg", key.img_id))
    }

    /// Annotation path of a sample, relative to the root.
    pub fn info_relative(&self, split: &str, key: &SampleKey) -> PathBuf {
        self.data_dir(split, "info")
            .join(&key.subject_id)
            .join(&key.facial_action)
            .join(format!("{}_info.npz", key.img_id))
    }

    fn data_dir(&self, split: &str, kind: &str) -> PathBuf {
        match self.kind {
            LayoutKind::Download => PathBuf::from(format!("ARKitFace_{kind}_{split}")).join(kind),
            LayoutKind::Flat => PathBuf::from(kind),
        }
    }

    /// The folders that hold annotations and images (relative), for the orphan scan.
    pub(crate) fn data_dirs(&self) -> Vec<PathBuf> {
        let splits: BTreeSet<&str> = self.lists.iter().map(|(s, _)| s.as_str()).collect();
        let mut dirs = Vec::new();
        for s in splits {
            dirs.push(self.data_dir(s, "image"));
            dirs.push(self.data_dir(s, "info"));
        }
        dirs.dedup();
        dirs
    }
}

/// Finds the layout of `root`.
pub fn discover(root: &Path) -> Result<DiscoveredInput> {
    if !root.is_dir() {
        return Err(Error::format(root, "input folder does not exist"));
    }
    let list_dir = root.join("ARKitFace_list").join("list");
    if list_dir.is_dir() {
        let mut lists = Vec::new();
        for entry in std::fs::read_dir(&list_dir).map_err(|e| Error::io(&list_dir, e))? {
            let path = entry.map_err(|e| Error::io(&list_dir, e))?.path();
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            if let Some(split) = name
                .strip_prefix("ARKitFace_")
                .and_then(|n| n.strip_suffix(".csv"))
            {
                lists.push((split.to_string(), path));
            }
        }
        if lists.is_empty() {
            return Err(Error::format(
                &list_dir,
                "no ARKitFace_<split>.csv list in this folder",
            ));
        }
        // train first, then test, then any other split, by name.
        lists.sort_by_key(|(s, _)| (s != "train", s != "test", s.clone()));
        return Ok(DiscoveredInput {
            root: root.to_path_buf(),
            kind: LayoutKind::Download,
            lists,
        });
    }
    if root.join("image").is_dir() && root.join("info").is_dir() {
        let mut csvs: Vec<PathBuf> = std::fs::read_dir(root)
            .map_err(|e| Error::io(root, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "csv"))
            .collect();
        csvs.sort();
        if csvs.len() != 1 {
            return Err(Error::format(
                root,
                format!(
                    "a flat layout (image/, info/) needs exactly one list CSV in the folder, found {}",
                    csvs.len()
                ),
            ));
        }
        return Ok(DiscoveredInput {
            root: root.to_path_buf(),
            kind: LayoutKind::Flat,
            lists: vec![("all".into(), csvs.remove(0))],
        });
    }
    Err(Error::format(
        root,
        "not an ARKitFace release: expected ARKitFace_list/list/*.csv (download layout) or image/, info/ and one CSV (flat layout)",
    ))
}

/// One row to convert.
#[derive(Clone, Debug)]
pub struct PlannedRow {
    /// Key.
    pub key: SampleKey,
    /// Split name.
    pub split: String,
    /// Image path relative to the root.
    pub image: PathBuf,
    /// Annotation path relative to the root.
    pub info: PathBuf,
}

/// The rows of every list, in order, and the rows that repeat an earlier key.
pub fn plan_rows(input: &DiscoveredInput) -> Result<(Vec<PlannedRow>, Vec<ErrorRecord>)> {
    let mut rows = Vec::new();
    let mut problems = Vec::new();
    let mut seen = HashSet::new();
    for (split, list) in &input.lists {
        for ListRow { key, line } in release::read_list(list)? {
            let rel_list = relative(&input.root, list);
            if !seen.insert(key.clone()) {
                problems.push(ErrorRecord {
                    key: key.clone(),
                    split: split.clone(),
                    file: rel_list.clone(),
                    reason: format!(
                        "line {line}: {key} is listed again; the first listing is converted"
                    ),
                });
                continue;
            }
            rows.push(PlannedRow {
                image: input.image_relative(split, &key),
                info: input.info_relative(split, &key),
                key,
                split: split.clone(),
            });
        }
    }
    Ok((rows, problems))
}

pub(super) fn relative(root: &Path, path: &Path) -> String {
    let rel = path.strip_prefix(root).unwrap_or(path);
    rel.components()
        .map(|c| c.as_os_str().to_string_lossy())
        .collect::<Vec<_>>()
        .join("/")
}

/// Files under the data folders that no list row names.
pub(super) fn find_orphans(input: &DiscoveredInput, rows: &[PlannedRow]) -> Vec<ErrorRecord> {
    let named: HashSet<PathBuf> = rows
        .iter()
        .flat_map(|r| [r.image.clone(), r.info.clone()])
        .collect();
    let mut out = Vec::new();
    let problem = |f: &Path, reason: String| ErrorRecord {
        key: SampleKey {
            subject_id: String::new(),
            facial_action: String::new(),
            img_id: String::new(),
        },
        split: String::new(),
        file: relative(&input.root, f),
        reason,
    };
    // Each folder is walked once (by its canonical path), so a symbolic link back to
    // an ancestor is reported, not followed round; an entry that cannot be read (a
    // broken or looping link) is reported, not taken for a file or skipped silently.
    let mut walked = HashSet::new();
    for dir in input.data_dirs() {
        let mut stack = vec![input.root.join(&dir)];
        let mut files = Vec::new();
        let top = stack[0].clone();
        while let Some(d) = stack.pop() {
            match std::fs::canonicalize(&d) {
                Ok(c) if !walked.insert(c.clone()) => {
                    out.push(problem(
                        &d,
                        format!(
                            "a folder already walked (a symbolic link to {}): not walked again",
                            c.display()
                        ),
                    ));
                    continue;
                }
                Ok(_) => {}
                Err(e) if d == top && e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => {
                    out.push(problem(&d, format!("folder cannot be read: {e}")));
                    continue;
                }
            }
            let entries = match std::fs::read_dir(&d) {
                Ok(entries) => entries,
                Err(e) => {
                    out.push(problem(&d, format!("folder cannot be read: {e}")));
                    continue;
                }
            };
            for e in entries {
                let p = match e {
                    Ok(e) => e.path(),
                    Err(e) => {
                        out.push(problem(&d, format!("folder cannot be listed: {e}")));
                        continue;
                    }
                };
                match std::fs::metadata(&p) {
                    Ok(m) if m.is_dir() => stack.push(p),
                    Ok(_) => files.push(p),
                    Err(e) => out.push(problem(
                        &p,
                        format!("cannot be read ({e}): a broken or looping symbolic link?"),
                    )),
                }
            }
        }
        files.sort();
        for f in files {
            let rel = f.strip_prefix(&input.root).unwrap_or(&f).to_path_buf();
            if !named.contains(&rel) {
                out.push(problem(&f, "file on disk that no list names".into()));
            }
        }
    }
    out
}

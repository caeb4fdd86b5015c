//! What state each output of a dataset folder is in, for `arkit-tool inspect`: the
//! samples `convert` wrote (complete, torn by an interrupted run, or damaged), the
//! targets of `render` (`targets/`: how many of the shards are finished), the crop
//! stores of `crops` (`crops/*/`), and the temporaries killed writers left behind
//! (`.NAME.tmp-TOKEN`, [`arkit_core::atomic_file::leftovers`]: each with its size and
//! whether its writer is gone, told by its lock).
//!
//! Every writer publishes a file by renaming a complete temporary over it, and writes
//! its folder's record last (`dataset.json`, `targets/`'s shard pairs, `crops.json`),
//! so what is missing is what an interrupted run had not finished; each state says which
//! folder and the command that completes it. Read from the outside: nothing here is
//! trusted by a reader (each checks what it reads itself); it only says what to do.
//!
//! Tested in `tests/kill.rs` (each command killed at seeded points, `inspect` naming
//! the torn output) and `tests/convert.rs`.

use arkit_data::store::{MANIFEST_FILE, Manifest, check_shard_file, read_manifest};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// The state of one output.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum State {
    /// Every file is there and accounted for.
    Complete,
    /// A run was interrupted (or is still running): some files are missing.
    Torn,
    /// Made from another dataset or options: readers refuse it.
    Stale,
    /// A file is there but is not what the record says.
    Damaged,
    /// Not made.
    Absent,
}

/// One output of the folder and its state.
#[derive(Clone, Debug, Serialize)]
pub struct OutputState {
    /// The folder, relative to the dataset (`samples`, `targets`, `crops/exact-192`).
    pub output: String,
    /// Its state.
    pub state: State,
    /// Shards (or part files) finished, when counted.
    pub done: Option<usize>,
    /// Shards there should be, when known.
    pub total: Option<usize>,
    /// The one line `inspect` prints: the state and the way out.
    pub message: String,
}

/// A temporary a writer left (or is filling).
#[derive(Clone, Debug, Serialize)]
pub struct Temporary {
    /// Relative to the dataset.
    pub path: String,
    /// Its size in bytes (a folder's: its files').
    pub bytes: u64,
    /// `true`: its writer is gone (no process holds its lock), and `arkit-tool clean`
    /// (or the next run of the command that writes there) removes it; `false`: a
    /// running writer holds it; `null`: the file system gives no locks to tell.
    pub abandoned: Option<bool>,
}

/// The state of every output of a dataset folder.
#[derive(Clone, Debug, Serialize)]
pub struct FolderState {
    /// `samples/` and `dataset.json` (`convert`, `merge`).
    pub samples: OutputState,
    /// `targets/` (`render`); absent when the samples are not complete.
    pub targets: Option<OutputState>,
    /// Each `crops/*/` store (`crops`).
    pub crop_stores: Vec<OutputState>,
    /// Temporaries in the folder and its sub-folders.
    pub temporaries: Vec<Temporary>,
    /// Why the folder's file system gives no working locks, when it does not: then no
    /// temporary can be told abandoned, and none is removed by the writers.
    pub no_locks: Option<String>,
}

impl FolderState {
    /// Whether every output present is complete and no temporary of a dead writer is
    /// left.
    pub fn all_complete(&self) -> bool {
        let ok = |o: &OutputState| matches!(o.state, State::Complete | State::Absent);
        self.samples.state == State::Complete
            && self.targets.as_ref().is_none_or(ok)
            && self.crop_stores.iter().all(ok)
            && self.temporaries.iter().all(|t| t.abandoned == Some(false))
    }

    /// The lines `inspect` prints (no indentation).
    pub fn lines(&self) -> Vec<String> {
        let mut out = vec![self.samples.message.clone()];
        out.extend(self.targets.iter().map(|t| t.message.clone()));
        out.extend(self.crop_stores.iter().map(|c| c.message.clone()));
        if let Some(why) = &self.no_locks {
            out.push(format!(
                "locks: this file system gives no working locks ({why}): temporaries of killed writers are not removed; `arkit-tool clean --force` when no writer runs"
            ));
        }
        if !self.temporaries.is_empty() {
            let count =
                |v: Option<bool>| self.temporaries.iter().filter(|t| t.abandoned == v).count();
            let (dead, live, unknown) = (count(Some(true)), count(Some(false)), count(None));
            let bytes: u64 = self.temporaries.iter().map(|t| t.bytes).sum();
            let mut line = format!(
                "temporaries: {} ({}): {dead} abandoned by killed runs (`arkit-tool clean` or the next run of the command that writes there removes them), {live} being written by a running one",
                self.temporaries.len(),
                human_bytes(bytes)
            );
            if unknown > 0 {
                line.push_str(&format!(
                    ", {unknown} of unknown state (this file system gives no locks: `arkit-tool clean --force` when no writer runs)"
                ));
            }
            out.push(line);
            for t in &self.temporaries {
                let state = match t.abandoned {
                    Some(true) => "abandoned",
                    Some(false) => "being written",
                    None => "unknown",
                };
                out.push(format!("  {} ({}, {state})", t.path, human_bytes(t.bytes)));
            }
        }
        out
    }
}

/// The state of every output of the dataset folder `dir`.
pub fn folder_state(dir: &Path) -> FolderState {
    folder_state_of(dir, None)
}

/// [`folder_state`] of the local mirror `dir` of a dataset published to a bucket: the
/// crop stores' part files, left in the bucket, are taken at the sizes its publication
/// record names (each is checked again against it when a reader opens it).
pub fn published_folder_state(
    dir: &Path,
    publication: &arkit_data::storage::Publication,
) -> FolderState {
    folder_state_of(dir, Some(publication))
}

fn folder_state_of(
    dir: &Path,
    published: Option<&arkit_data::storage::Publication>,
) -> FolderState {
    let (samples, manifest) = samples_state(dir);
    let targets = manifest.as_ref().map(|m| targets_state(dir, m));
    let fingerprint = manifest
        .as_ref()
        .map(arkit_data::store::dataset_fingerprint);
    let shards = manifest.as_ref().map(|m| m.shards.len());
    FolderState {
        samples,
        targets,
        crop_stores: crop_store_states(dir, fingerprint.as_deref(), shards, published),
        temporaries: temporaries(dir),
        no_locks: match arkit_core::atomic_file::lock_support(dir) {
            arkit_core::atomic_file::LockSupport::Working => None,
            arkit_core::atomic_file::LockSupport::Missing(why) => Some(why),
        },
    }
}

fn state(
    output: &str,
    state: State,
    done: Option<usize>,
    total: Option<usize>,
    message: String,
) -> OutputState {
    OutputState {
        output: output.to_string(),
        state,
        done,
        total,
        message,
    }
}

/// Names in `dir` of the form `PREFIX<digits>SUFFIX`, as their numbers.
fn numbered(dir: &Path, prefix: &str, suffix: &str) -> Vec<usize> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut out: Vec<usize> = entries
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let k = name.strip_prefix(prefix)?.strip_suffix(suffix)?;
            (!k.is_empty() && k.bytes().all(|b| b.is_ascii_digit())).then(|| k.parse().ok())?
        })
        .collect();
    out.sort_unstable();
    out
}

fn samples_state(dir: &Path) -> (OutputState, Option<Manifest>) {
    let manifest_path = dir.join(MANIFEST_FILE);
    if manifest_path.exists() {
        let m = match read_manifest(&manifest_path) {
            Ok(m) => m,
            Err(e) => {
                return (
                    state(
                        "samples",
                        State::Damaged,
                        None,
                        None,
                        format!("samples: damaged: {e}; rerun `arkit-tool convert`"),
                    ),
                    None,
                );
            }
        };
        let total = m.shards.len();
        for s in &m.shards {
            let path = dir.join(&s.samples_file);
            if let Err(e) = check_shard_file(&path, s.bytes, &s.tail_sha256) {
                return (
                    state(
                        "samples",
                        State::Damaged,
                        None,
                        Some(total),
                        format!("samples: damaged: {e}"),
                    ),
                    None,
                );
            }
        }
        let rows: usize = m.shards.iter().map(|s| s.rows).sum();
        return (
            state(
                "samples",
                State::Complete,
                Some(total),
                Some(total),
                format!("samples: complete ({total} shards, {rows} rows, {MANIFEST_FILE})"),
            ),
            Some(m),
        );
    }
    // No dataset.json: an unfinished conversion, the parts of a sharded one, or nothing.
    let records = numbered(&dir.join("samples"), "part-", ".json");
    let parts: Vec<(usize, usize)> = std::fs::read_dir(dir.join("manifest"))
        .map(|entries| {
            entries
                .flatten()
                .filter_map(|e| {
                    let name = e.file_name().to_string_lossy().into_owned();
                    let (i, n) = name
                        .strip_prefix("part-")?
                        .strip_suffix(".json")?
                        .split_once("-of-")?;
                    Some((i.parse().ok()?, n.parse().ok()?))
                })
                .collect()
        })
        .unwrap_or_default();
    let conversion = dir.join(arkit_data::ingest::CONVERSION_FILE).exists();
    if let Some(&(_, n)) = parts.first() {
        let missing: Vec<String> = (0..n)
            .filter(|i| !parts.contains(&(*i, n)))
            .map(|i| format!("{i}/{n}"))
            .collect();
        let message = if missing.is_empty() {
            format!(
                "samples: torn: all {n} parts of a sharded conversion are in manifest/, no {MANIFEST_FILE}; run `arkit-tool merge --dataset {}`",
                dir.display()
            )
        } else {
            format!(
                "samples: torn: {} of {n} parts of a sharded conversion in manifest/, no {MANIFEST_FILE}; run `arkit-tool convert --shard I/N` for the parts missing ({}), then `arkit-tool merge`",
                n - missing.len(),
                missing.join(", ")
            )
        };
        return (
            state(
                "samples",
                State::Torn,
                Some(n - missing.len()),
                Some(n),
                message,
            ),
            None,
        );
    }
    if conversion || !records.is_empty() {
        return (
            state(
                "samples",
                State::Torn,
                Some(records.len()),
                None,
                format!(
                    "samples: torn: {} shards finished and no {MANIFEST_FILE} (a `convert` did not finish, or is running); rerun `arkit-tool convert` with the same options: it keeps the finished shards",
                    records.len()
                ),
            ),
            None,
        );
    }
    (
        state(
            "samples",
            State::Absent,
            None,
            None,
            format!(
                "samples: none: not a converted dataset (no {MANIFEST_FILE}); run `arkit-tool convert`"
            ),
        ),
        None,
    )
}

/// The options `targets/render.json` records, as `render`'s arguments.
fn render_arguments(settings: &serde_json::Value) -> String {
    let mut args = Vec::new();
    for (key, flag) in [
        ("size", "--size"),
        ("uv_size", "--uv-size"),
        ("points", "--points"),
        ("seed", "--seed"),
    ] {
        if let Some(v) = settings.get(key).filter(|v| v.is_number()) {
            args.push(format!("{flag} {v}"));
        }
    }
    if let Some(rules) = settings
        .get("mode")
        .and_then(|m| m.as_str())
        .and_then(|m| arkit_data::crop::RuleSet::parse(m).ok())
        && rules != arkit_data::crop::RuleSet::default()
    {
        args.push(format!("--compat {rules}"));
    }
    if settings.get("full_mask").and_then(|f| f.as_bool()) == Some(true) {
        args.push("--full-mask".into());
    }
    args.join(" ")
}

fn targets_state(dir: &Path, m: &Manifest) -> OutputState {
    use arkit_data::store::parquet_row_count;
    use arkit_data::store::{errors_path, shard_path};
    let targets = dir.join("targets");
    let total = m.shards.len();
    let settings_path = targets.join("render.json");
    let settings: Option<serde_json::Value> = std::fs::read_to_string(&settings_path)
        .ok()
        .map(|t| serde_json::from_str(&t).unwrap_or(serde_json::Value::Null));
    let files = numbered(&targets, "part-", ".parquet");
    let rerun = |extra: &str| {
        format!(
            "`arkit-tool render --dataset {}{}{extra}`",
            dir.display(),
            settings
                .as_ref()
                .map(render_arguments)
                .filter(|a| !a.is_empty())
                .map(|a| format!(" {a}"))
                .unwrap_or_default()
        )
    };
    let Some(settings) = &settings else {
        if files.is_empty() {
            return state(
                "targets",
                State::Absent,
                Some(0),
                Some(total),
                "targets: none (`arkit-tool render` makes them)".into(),
            );
        }
        return state(
            "targets",
            State::Torn,
            None,
            Some(total),
            format!(
                "targets: {} shard files but no targets/render.json says how they were made; rerun {}",
                files.len(),
                rerun(" --overwrite")
            ),
        );
    };
    let fingerprint = arkit_data::store::dataset_fingerprint(m);
    if settings.get("dataset").and_then(|d| d.as_str()) != Some(fingerprint.as_str()) {
        return state(
            "targets",
            State::Stale,
            None,
            Some(total),
            format!(
                "targets: stale: made from other samples than these (targets/render.json); rerun {}",
                rerun(" --overwrite")
            ),
        );
    }
    let mut done = 0;
    for s in &m.shards {
        let (t, e) = (shard_path(dir, s.index), errors_path(dir, s.index));
        if !t.exists() || !e.exists() {
            continue;
        }
        match (parquet_row_count(&t), parquet_row_count(&e)) {
            (Ok(a), Ok(b)) if a + b == s.rows => done += 1,
            (Err(err), _) | (_, Err(err)) => {
                return state(
                    "targets",
                    State::Damaged,
                    Some(done),
                    Some(total),
                    format!("targets: damaged: {err}; remove it and rerun {}", rerun("")),
                );
            }
            (Ok(a), Ok(b)) => {
                return state(
                    "targets",
                    State::Damaged,
                    Some(done),
                    Some(total),
                    format!(
                        "targets: damaged: {} and its errors file hold {} rows, the samples shard {}; rerun {}",
                        t.display(),
                        a + b,
                        s.rows,
                        rerun(" --overwrite")
                    ),
                );
            }
        }
    }
    if done == total {
        state(
            "targets",
            State::Complete,
            Some(done),
            Some(total),
            format!("targets: complete ({total} shards)"),
        )
    } else {
        state(
            "targets",
            State::Torn,
            Some(done),
            Some(total),
            format!(
                "targets: {done} of {total} shards, rerun {} (a `render` did not finish, or is running)",
                rerun("")
            ),
        )
    }
}

/// The crop stores in `dir/crops/*/`, read from the outside: `crops.json` (written last)
/// and the part files it names.
fn crop_store_states(
    dir: &Path,
    fingerprint: Option<&str>,
    shards: Option<usize>,
    published: Option<&arkit_data::storage::Publication>,
) -> Vec<OutputState> {
    let Ok(entries) = std::fs::read_dir(dir.join("crops")) else {
        return Vec::new();
    };
    let mut stores: Vec<PathBuf> = entries
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
        .map(|e| e.path())
        .collect();
    stores.sort();
    stores
        .iter()
        .map(|store| crop_store_state(dir, store, fingerprint, shards, published))
        .collect()
}

fn crop_store_state(
    dir: &Path,
    store: &Path,
    fingerprint: Option<&str>,
    shards: Option<usize>,
    published: Option<&arkit_data::storage::Publication>,
) -> OutputState {
    let name = store.file_name().unwrap_or_default().to_string_lossy();
    let output = format!("crops/{name}");
    // `<compat>-<size>`, as `crops` names its default folders.
    let rerun = match name.rsplit_once('-') {
        Some((compat, size)) if size.parse::<u32>().is_ok() => format!(
            "`arkit-tool crops --dataset {} --compat {compat} --size {size}`",
            dir.display()
        ),
        _ => format!(
            "`arkit-tool crops --dataset {} --output {}`",
            dir.display(),
            store.display()
        ),
    };
    let parts = numbered(store, "part-", ".bin");
    let manifest_path = store.join("crops.json");
    let text = match std::fs::read_to_string(&manifest_path) {
        Ok(t) => t,
        Err(_) => {
            return state(
                &output,
                State::Torn,
                Some(parts.len()),
                shards,
                format!(
                    "{output}: {} of {} part files and no crops.json (a `crops` did not finish, or is running); rerun {rerun}",
                    parts.len(),
                    shards.map_or("?".to_string(), |n| n.to_string())
                ),
            );
        }
    };
    let value: serde_json::Value = match serde_json::from_str(&text) {
        Ok(v) => v,
        Err(e) => {
            return state(
                &output,
                State::Damaged,
                None,
                shards,
                format!(
                    "{output}: damaged: {}: not JSON ({e}); rerun {rerun}",
                    manifest_path.display()
                ),
            );
        }
    };
    if fingerprint
        .is_some_and(|f| value.get("dataset_fingerprint").and_then(|d| d.as_str()) != Some(f))
    {
        return state(
            &output,
            State::Stale,
            None,
            shards,
            format!(
                "{output}: stale: made from other samples than these (crops.json); rerun {rerun}"
            ),
        );
    }
    let named = value
        .get("shards")
        .and_then(|s| s.as_array())
        .cloned()
        .unwrap_or_default();
    for s in &named {
        let (Some(file), Some(bytes)) = (
            s.get("file").and_then(|f| f.as_str()),
            s.get("bytes").and_then(|b| b.as_u64()),
        ) else {
            continue;
        };
        let path = store.join(file);
        let size = match published.and_then(|p| p.object(&format!("{output}/{file}"))) {
            Some(o) => Ok(o.bytes),
            None => std::fs::metadata(&path).map(|m| m.len()),
        };
        match size {
            Ok(len) if len == bytes => {}
            Ok(len) => {
                return state(
                    &output,
                    State::Damaged,
                    None,
                    shards,
                    format!(
                        "{output}: damaged: {} is {len} bytes, crops.json says {bytes}; rerun {rerun}",
                        path.display(),
                    ),
                );
            }
            Err(e) => {
                return state(
                    &output,
                    State::Damaged,
                    None,
                    shards,
                    format!("{output}: damaged: {}: {e}; rerun {rerun}", path.display()),
                );
            }
        }
    }
    let missing = value
        .get("missing")
        .and_then(|m| m.as_array())
        .map_or(0, Vec::len);
    let without = if missing > 0 {
        format!(", {missing} samples without pixels (listed in crops.json)")
    } else {
        String::new()
    };
    state(
        &output,
        State::Complete,
        Some(named.len()),
        shards,
        format!("{output}: complete ({} part files{without})", named.len()),
    )
}

/// The temporaries under `dir` (its sub-folders included), sorted.
fn temporaries(dir: &Path) -> Vec<Temporary> {
    let found = arkit_core::atomic_file::leftovers(dir, true).unwrap_or_default();
    found
        .into_iter()
        .map(|l| Temporary {
            path: l
                .path
                .strip_prefix(dir)
                .unwrap_or(&l.path)
                .display()
                .to_string(),
            bytes: l.bytes,
            abandoned: l.abandoned,
        })
        .collect()
}

/// `bytes` for people: `812 B`, `3.4 MB`, `2.1 GB`.
pub fn human_bytes(bytes: u64) -> String {
    match bytes {
        b if b < 1_000 => format!("{b} B"),
        b if b < 1_000_000 => format!("{:.1} kB", b as f64 / 1e3),
        b if b < 1_000_000_000 => format!("{:.1} MB", b as f64 / 1e6),
        b => format!("{:.1} GB", b as f64 / 1e9),
    }
}

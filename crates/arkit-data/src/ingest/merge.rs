//! `merge`: the part manifests of a sharded `convert` (`--shard I/N` on many machines)
//! joined into the dataset's one `dataset.json`, after checking that every part is there,
//! that the parts agree, and that no key repeats.

use crate::ingest::convert::{
    CONVERSION_FILE, hold_against_overwrite, manifest_name, read_conversion_record, write_manifest,
};
use crate::store::manifest::{
    MANIFEST_FILE, Manifest, ShardEntry, check_shard_file, read_manifest,
};
use crate::store::samples_table;
use arkit_core::{Error, Result};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// What [`merge`] did.
#[derive(Clone, Debug)]
pub struct Merged {
    /// The dataset's manifest, as written to `dataset.json`.
    pub manifest: Manifest,
    /// Files in `manifest/` that are not named like a part (`part-IIII-of-NNNN.json`;
    /// a copy such as `part-0000-of-0002 (copy).json`): not read, left where they are.
    pub ignored: Vec<PathBuf>,
}

/// `(I, N)` of a part manifest's file name `part-IIII-of-NNNN.json`, exactly as
/// [`manifest_name`] writes it (so `part-0-of-2.json` or a copy's name is not one).
fn part_of_name(name: &str) -> Option<(usize, usize)> {
    let (i, n) = name
        .strip_prefix("part-")?
        .strip_suffix(".json")?
        .split_once("-of-")?;
    let digits = |s: &str| s.len() >= 4 && s.bytes().all(|b| b.is_ascii_digit());
    if !digits(i) || !digits(n) {
        return None;
    }
    let (i, n) = (i.parse().ok()?, n.parse().ok()?);
    (i < n && n > 1 && manifest_name(i, n) == format!("manifest/{name}")).then_some((i, n))
}

/// Joins the parts of a `--shard I/N` conversion into `dataset.json`.
///
/// Only the parts the conversion names are read: `manifest/part-IIII-of-NNNN.json` for
/// `I` in `0..N`, each of which must say it is part `I` of `N` and carry the
/// fingerprint of the conversion that `conversion.json` records. Any other file in
/// `manifest/` (a copy made by hand, say) is ignored and listed in [`Merged::ignored`];
/// parts of two different `N` are refused. Errors, naming the file: a part missing, a
/// part of another conversion or renamed, parts that disagree, a shard in two parts or
/// in none (every shard of the conversion's rows must be there once), a samples file
/// that is not the one its part records, and a sample key found twice (the error names
/// both shards).
pub fn merge(dataset: &Path) -> Result<Merged> {
    let record = dataset.join(CONVERSION_FILE);
    let Some(conversion) = read_conversion_record(&record)? else {
        return Err(Error::format(
            dataset,
            format!(
                "no {CONVERSION_FILE}: not a folder that `arkit-tool convert --shard I/N` wrote"
            ),
        ));
    };
    // One merge at a time; a killed merge's temporary goes.
    let _lock = arkit_core::atomic_file::FolderLock::acquire(dataset, "merge", "merge")?;
    let _writers = hold_against_overwrite(dataset)?;
    arkit_core::atomic_file::remove_stale_temporaries(dataset, false)?;
    let digest = conversion.digest();
    let dir = dataset.join("manifest");
    let (named, ignored) = named_parts(&dir)?;
    let n = part_count(&dir, &named)?;
    check_parts_present(dataset, &dir, n)?;
    let parts = read_parts(dataset, n, &digest)?;
    check_parts_agree(&parts)?;
    let first = parts[0].0.clone();
    let shards = collect_shards(&parts, n)?;
    check_unique_keys(dataset, &shards)?;
    let merged = Manifest {
        part: [0, 1],
        converted: shards.iter().map(|s| s.rows).sum(),
        skipped: shards.iter().map(|s| s.error_rows).sum(),
        listing_problems: parts.iter().map(|(p, _)| p.listing_problems).sum(),
        shards,
        ..first
    };
    write_manifest(&dataset.join(MANIFEST_FILE), &merged)?;
    Ok(Merged {
        manifest: merged,
        ignored,
    })
}

/// The `(I, N)` of each part manifest named in a `manifest/` folder, and the other files
/// there.
type PartNames = (Vec<(usize, usize)>, Vec<PathBuf>);

/// The `(I, N)` of each part manifest named in `dir` and, sorted, the other files there
/// (temporaries aside).
fn named_parts(dir: &Path) -> Result<PartNames> {
    let mut named: Vec<(usize, usize)> = Vec::new();
    let mut ignored = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if arkit_core::atomic_file::is_temporary_name(&name) {
            continue;
        }
        match part_of_name(&name) {
            Some(part) => named.push(part),
            None => ignored.push(entry.path()),
        }
    }
    ignored.sort();
    Ok((named, ignored))
}

/// The `N` that all the `named` parts share; an error when there is none or more than
/// one.
fn part_count(dir: &Path, named: &[(usize, usize)]) -> Result<usize> {
    let counts: BTreeSet<usize> = named.iter().map(|p| p.1).collect();
    match counts.len() {
        0 => Err(Error::format(
            dir,
            "no part manifests (part-IIII-of-NNNN.json) to merge: run `convert --shard I/N` first",
        )),
        1 => Ok(*counts.first().expect("one")),
        _ => Err(Error::format(
            dir,
            format!(
                "holds the parts of conversions split {} ways: remove the part manifests of the split you do not want, or convert into a new folder",
                counts
                    .iter()
                    .map(|c| c.to_string())
                    .collect::<Vec<_>>()
                    .join(" and ")
            ),
        )),
    }
}

/// Refuses a merge with any of the `n` part manifests missing, naming every missing part
/// at once (so that a cluster's failed tasks are all seen).
fn check_parts_present(dataset: &Path, dir: &Path, n: usize) -> Result<()> {
    let missing: Vec<usize> = (0..n)
        .filter(|&i| !dataset.join(manifest_name(i, n)).exists())
        .collect();
    if !missing.is_empty() {
        let list = |f: &dyn Fn(usize) -> String| {
            missing.iter().map(|&i| f(i)).collect::<Vec<_>>().join(", ")
        };
        let (parts, verb) = match missing.len() {
            1 => ("part", "is"),
            _ => ("parts", "are"),
        };
        return Err(Error::format(
            dir,
            format!(
                "{parts} {} of {n} {verb} missing ({} of {n} finished): run {}",
                list(&|i| i.to_string()),
                n - missing.len(),
                list(&|i| format!("`convert --shard {i}/{n}`"))
            ),
        ));
    }
    Ok(())
}

/// Reads the `n` part manifests with their paths; each must say it is the part its name
/// says and carry the conversion's fingerprint `digest`.
fn read_parts(dataset: &Path, n: usize, digest: &str) -> Result<Vec<(Manifest, PathBuf)>> {
    let mut parts: Vec<(Manifest, PathBuf)> = Vec::new();
    for i in 0..n {
        let path = dataset.join(manifest_name(i, n));
        let p = read_manifest(&path)?;
        if p.part != [i, n] {
            return Err(Error::format(
                &path,
                format!(
                    "says it is part {} of {}, but its name is part {i} of {n}: renamed or copied by hand; run `convert --shard {i}/{n}` again",
                    p.part[0], p.part[1]
                ),
            ));
        }
        if p.fingerprint != digest {
            return Err(Error::format(
                &path,
                format!(
                    "this part comes from another conversion than the one {CONVERSION_FILE} records (other input, lists or options): run `convert --shard {i}/{n}` again"
                ),
            ));
        }
        parts.push((p, path));
    }
    Ok(parts)
}

/// Refuses parts that disagree with the first on the listed rows, the shard size, the
/// input, the topology or the embedded images.
fn check_parts_agree(parts: &[(Manifest, PathBuf)]) -> Result<()> {
    let (first, first_path) = &parts[0];
    for (p, path) in parts {
        let differs = [
            ("listed rows", p.listed != first.listed),
            ("shard size", p.rows_per_shard != first.rows_per_shard),
            (
                "input",
                p.input_root != first.input_root || p.input != first.input,
            ),
            (
                "topology",
                p.topology != first.topology || p.topology_sha256 != first.topology_sha256,
            ),
            ("embedded images", p.embed_images != first.embed_images),
        ];
        if let Some((what, _)) = differs.iter().find(|(_, d)| *d) {
            return Err(Error::format(
                path,
                format!(
                    "this part comes from a different conversion than {} ({what} differs): rerun every part with the same input and options",
                    first_path.display()
                ),
            ));
        }
    }
    Ok(())
}

/// The shards of all `n` parts, sorted: every shard of the conversion's rows once, in the
/// part that owns it.
fn collect_shards(parts: &[(Manifest, PathBuf)], n: usize) -> Result<Vec<ShardEntry>> {
    let first = &parts[0].0;
    let expected = first.listed.div_ceil(first.rows_per_shard.max(1));
    let mut owner: Vec<Option<usize>> = vec![None; expected];
    let mut shards: Vec<ShardEntry> = Vec::new();
    for (i, (p, path)) in parts.iter().enumerate() {
        for s in &p.shards {
            if s.index >= expected || s.index % n != i {
                return Err(Error::format(
                    path,
                    format!(
                        "lists shard {}, which is not one of part {i} of {n} (shards k < {expected} with k % {n} == {i}): run `convert --shard {i}/{n}` again",
                        s.index
                    ),
                ));
            }
            if owner[s.index].replace(i).is_some() {
                return Err(Error::format(
                    path,
                    format!(
                        "lists shard {} twice: run `convert --shard {i}/{n}` again",
                        s.index
                    ),
                ));
            }
            shards.push(s.clone());
        }
    }
    if let Some(k) = owner.iter().position(|o| o.is_none()) {
        return Err(Error::format(
            &parts[k % n].1,
            format!(
                "does not list shard {k} of the conversion's {expected}: run `convert --shard {}/{n}` again",
                k % n
            ),
        ));
    }
    shards.sort_by_key(|s| s.index);
    Ok(shards)
}

/// Checks each shard's samples file against its entry (size, footer checksum, rows)
/// and that no sample key is in two rows; reads the key columns only.
fn check_unique_keys(dataset: &Path, shards: &[ShardEntry]) -> Result<()> {
    let mut seen: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
    for s in shards {
        let path = dataset.join(&s.samples_file);
        check_shard_file(&path, s.bytes, &s.tail_sha256)?;
        let keys = samples_table::read_sample_keys(&path)?;
        if keys.len() != s.rows {
            return Err(Error::format(
                &path,
                format!(
                    "{} rows, its part manifest says {}: rerun `arkit-tool convert`",
                    keys.len(),
                    s.rows
                ),
            ));
        }
        for (key, _) in keys {
            let name = key.to_string();
            if let Some(other) = seen.insert(name, s.index) {
                return Err(Error::format(
                    &path,
                    format!(
                        "sample {key} is in shard {other} and again in shard {}: a dataset holds each sample once; convert again into a new folder",
                        s.index
                    ),
                ));
            }
        }
    }
    Ok(())
}

//! `split`: subject-disjoint train/test(/val) splits, reproducible from a seed.
//!
//! Subjects are shuffled with the seed ([`arkit_core::Rng`]), then assigned so that the test
//! (and validation) split's share of *images* is as close as subjects allow to the
//! requested share: for `--test-fraction F` subjects are added while that brings the
//! image count closer to `F` of all images; for `--test-subjects N` the first `N`
//! shuffled subjects are taken, then single swaps with train subjects are made while a
//! swap brings the image count closer to `N / subjects` of all images. No subject is
//! ever in two splits.

use arkit_core::Rng;
use arkit_core::SampleKey;
use arkit_core::{Error, Result};
use polars::prelude::*;
use std::collections::BTreeMap;

/// How many subjects, or what share of images, to hold out.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum HoldOut {
    /// Exactly this many subjects.
    Subjects(usize),
    /// About this fraction of the images (whole subjects).
    Fraction(f64),
}

/// A split assignment: split name per subject, and per-split counts.
#[derive(Clone, Debug, PartialEq)]
pub struct SplitAssignment {
    /// `subject_id -> split name` (`train`, `test`, `val`).
    pub subject_split: BTreeMap<String, String>,
}

impl SplitAssignment {
    /// The split of a sample.
    pub(crate) fn split_of(&self, key: &SampleKey) -> &str {
        self.subject_split
            .get(&key.subject_id)
            .map(|s| s.as_str())
            .unwrap_or("train")
    }

    /// `(subjects, images)` per split name, for `images_per_subject`.
    pub fn counts(
        &self,
        images_per_subject: &BTreeMap<String, usize>,
    ) -> BTreeMap<String, (usize, usize)> {
        let mut out = BTreeMap::new();
        for (subject, split) in &self.subject_split {
            let e = out.entry(split.clone()).or_insert((0, 0));
            e.0 += 1;
            e.1 += images_per_subject.get(subject).copied().unwrap_or(0);
        }
        out
    }
}

/// Shuffles a list in place with the seeded generator (Fisher-Yates).
fn shuffle<T>(items: &mut [T], rng: &mut Rng) {
    for i in (1..items.len()).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        items.swap(i, j);
    }
}

/// Picks held-out subjects from `pool` (subject, images) after shuffling.
fn hold_out(
    pool: &mut Vec<(String, usize)>,
    how: HoldOut,
    total_images: usize,
    total_subjects: usize,
) -> Result<Vec<String>> {
    let images = |s: &[(String, usize)]| s.iter().map(|(_, n)| *n).sum::<usize>();
    match how {
        HoldOut::Fraction(f) => {
            if !(0.0..1.0).contains(&f) {
                return Err(Error::invalid(
                    "--test-fraction",
                    format!("{f} is not in [0, 1)"),
                ));
            }
            let target = f * total_images as f64;
            let mut chosen = Vec::new();
            let mut count = 0usize;
            let mut rest = Vec::new();
            for (s, n) in pool.drain(..) {
                if ((count + n) as f64 - target).abs() < (count as f64 - target).abs() {
                    count += n;
                    chosen.push(s);
                } else {
                    rest.push((s, n));
                }
            }
            *pool = rest;
            Ok(chosen)
        }
        HoldOut::Subjects(k) => {
            if k >= pool.len() {
                return Err(Error::invalid(
                    "--test-subjects",
                    format!(
                        "{k} subjects requested but only {} are available (at least one must stay in train)",
                        pool.len()
                    ),
                ));
            }
            let target = k as f64 / total_subjects as f64 * total_images as f64;
            let mut rest = pool.split_off(k);
            let mut chosen = std::mem::take(pool);
            // Improve the balance by single swaps, a bounded number of passes.
            for _ in 0..8 {
                let mut improved = false;
                for i in 0..chosen.len() {
                    let current = images(&chosen) as f64;
                    let best = rest
                        .iter()
                        .enumerate()
                        .map(|(j, (_, n))| {
                            (j, (current - chosen[i].1 as f64 + *n as f64 - target).abs())
                        })
                        .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
                    if let Some((j, d)) = best
                        && d + 1e-9 < (current - target).abs()
                    {
                        std::mem::swap(&mut chosen[i], &mut rest[j]);
                        improved = true;
                    }
                }
                if !improved {
                    break;
                }
            }
            *pool = rest;
            Ok(chosen.into_iter().map(|(s, _)| s).collect())
        }
    }
}

/// Assigns subjects to `train`, `test` and optionally `val`.
pub fn assign(
    images_per_subject: &BTreeMap<String, usize>,
    test: HoldOut,
    val_subjects: usize,
    seed: u64,
) -> Result<SplitAssignment> {
    if images_per_subject.len() < 2 {
        return Err(Error::invalid(
            "dataset",
            "a subject-disjoint split needs at least two subjects",
        ));
    }
    let total_images: usize = images_per_subject.values().sum();
    let total_subjects = images_per_subject.len();
    // Sorted by id (BTreeMap), then shuffled: the same seed gives the same split.
    let mut pool: Vec<(String, usize)> = images_per_subject
        .iter()
        .map(|(s, n)| (s.clone(), *n))
        .collect();
    let mut rng = Rng::new(seed);
    shuffle(&mut pool, &mut rng);
    let test_subjects = hold_out(&mut pool, test, total_images, total_subjects)?;
    let val = if val_subjects > 0 {
        hold_out(
            &mut pool,
            HoldOut::Subjects(val_subjects),
            total_images,
            total_subjects,
        )?
    } else {
        Vec::new()
    };
    let mut subject_split = BTreeMap::new();
    for (s, _) in &pool {
        subject_split.insert(s.clone(), "train".to_string());
    }
    for s in test_subjects {
        subject_split.insert(s, "test".to_string());
    }
    for s in val {
        subject_split.insert(s, "val".to_string());
    }
    Ok(SplitAssignment { subject_split })
}

/// Subjects and images in one split.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct SplitCount {
    /// Distinct subjects.
    pub subjects: usize,
    /// Images.
    pub images: usize,
}

/// Splits the converted dataset in `dataset` (`how`: hold out subjects or a share of
/// images; `None` keeps the release's own lists, refusing a subject listed in two)
/// and writes `out/splits.parquet` and the release-format list CSVs
/// (`out/ARKitFace_list/list/ARKitFace_{split}.csv`). Returns the counts per split.
pub fn split_dataset(
    dataset: &std::path::Path,
    how: Option<HoldOut>,
    val_subjects: usize,
    seed: u64,
    out: &std::path::Path,
) -> Result<BTreeMap<String, SplitCount>> {
    let data = crate::store::dataset::Dataset::open(dataset)?;
    let _lock = arkit_core::atomic_file::FolderLock::acquire(dataset, "split", "split")?;
    let _writers = crate::ingest::convert::hold_against_overwrite(dataset)?;
    arkit_core::atomic_file::remove_stale_temporaries(out, true)?;
    let mut keys: Vec<(SampleKey, String)> = Vec::new();
    for s in data.shards() {
        keys.extend(data.read_sample_keys(s)?);
    }
    let mut per_subject: BTreeMap<String, usize> = BTreeMap::new();
    for (k, _) in &keys {
        *per_subject.entry(k.subject_id.clone()).or_default() += 1;
    }
    let assigned: Vec<String> = if let Some(how) = how {
        let assignment = assign(&per_subject, how, val_subjects, seed)?;
        keys.iter()
            .map(|(k, _)| assignment.split_of(k).to_string())
            .collect()
    } else {
        keys.iter().map(|(_, s)| s.clone()).collect()
    };
    // A subject must not straddle splits (possible only with --keep-release on odd data).
    let mut subject_split: BTreeMap<&str, &str> = BTreeMap::new();
    for ((k, _), s) in keys.iter().zip(&assigned) {
        if let Some(prev) = subject_split.insert(&k.subject_id, s)
            && prev != s
        {
            return Err(Error::invalid(
                "split",
                format!(
                    "subject {} is in both {prev} and {s} in the release lists",
                    k.subject_id
                ),
            ));
        }
    }
    let mut by_split: BTreeMap<String, Vec<SampleKey>> = BTreeMap::new();
    for ((k, _), s) in keys.iter().zip(&assigned) {
        by_split.entry(s.clone()).or_default().push(k.clone());
    }
    // Every list at once: the official code never reads one split's list of this run
    // beside another's of an older one.
    let lists: Vec<(&str, &[SampleKey])> = by_split
        .iter()
        .map(|(s, ks)| (s.as_str(), ks.as_slice()))
        .collect();
    arkit_core::release::write_lists(out, &lists)?;
    let col = |name: &str, f: &dyn Fn(usize) -> String| {
        Column::new(name.into(), (0..keys.len()).map(f).collect::<Vec<String>>())
    };
    let mut df = DataFrame::new(
        keys.len(),
        vec![
            col("subject_id", &|i| keys[i].0.subject_id.clone()),
            col("facial_action", &|i| keys[i].0.facial_action.clone()),
            col("img_id", &|i| keys[i].0.img_id.clone()),
            col("split", &|i| assigned[i].clone()),
        ],
    )
    .map_err(|e| Error::invalid("splits table", e.to_string()))?;
    crate::store::parquet::write_parquet(&out.join("splits.parquet"), &mut df)?;
    let mut counts: BTreeMap<String, SplitCount> = BTreeMap::new();
    for (s, ks) in &by_split {
        let subjects: std::collections::BTreeSet<&str> =
            ks.iter().map(|k| k.subject_id.as_str()).collect();
        counts.insert(
            s.clone(),
            SplitCount {
                subjects: subjects.len(),
                images: ks.len(),
            },
        );
    }
    Ok(counts)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn subjects(n: usize) -> BTreeMap<String, usize> {
        (0..n)
            .map(|i| (format!("{i:05}"), 50 + (i * 37) % 200))
            .collect()
    }

    #[test]
    fn disjoint_reproducible_and_balanced() {
        let s = subjects(100);
        let a = assign(&s, HoldOut::Subjects(20), 10, 7).unwrap();
        assert_eq!(a, assign(&s, HoldOut::Subjects(20), 10, 7).unwrap());
        assert_ne!(a, assign(&s, HoldOut::Subjects(20), 10, 8).unwrap());
        let c = a.counts(&s);
        assert_eq!((c["test"].0, c["val"].0, c["train"].0), (20, 10, 70));
        // Every subject in exactly one split (a map cannot hold two).
        assert_eq!(a.subject_split.len(), 100);
        // Balanced: 20% of subjects hold close to 20% of the images.
        let total: usize = s.values().sum();
        let share = c["test"].1 as f64 / total as f64;
        assert!((share - 0.2).abs() < 0.01, "{share}");
    }

    #[test]
    fn fraction_of_images() {
        let s = subjects(50);
        let a = assign(&s, HoldOut::Fraction(0.3), 0, 1).unwrap();
        let c = a.counts(&s);
        let total: usize = s.values().sum();
        assert!((c["test"].1 as f64 / total as f64 - 0.3).abs() < 0.03);
        assert!(!c.contains_key("val"));
    }

    #[test]
    fn refuses_what_cannot_be_done() {
        assert!(assign(&subjects(1), HoldOut::Fraction(0.2), 0, 0).is_err());
        assert!(assign(&subjects(5), HoldOut::Subjects(5), 0, 0).is_err());
        assert!(assign(&subjects(5), HoldOut::Fraction(1.5), 0, 0).is_err());
    }
}

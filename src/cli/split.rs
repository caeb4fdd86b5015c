//! `arkit-tool split`.

use arkit_tool::convert::read_manifest;
use arkit_tool::release::{self, SampleKey};
use arkit_tool::samples_table;
use arkit_tool::split::{self, HoldOut};
use arkit_tool::{Error, Result};
use clap::{ArgGroup, Args};
use polars::prelude::*;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;

/// Make subject-disjoint train/test (and val) splits of a converted dataset.
///
/// No subject is in two splits; the test share of images is as close to the request
/// as whole subjects allow; the same --seed gives the same split. Writes list CSVs in
/// the release's format (ARKitFace_list/list/ARKitFace_{train,test,val}.csv, usable by
/// the official code) and splits.parquet (subject_id, facial_action, img_id, split).
///
/// Example (the paper's 400/100 subjects): arkit-tool split --dataset data/parquet --test-subjects 100 --seed 0
#[derive(Args, Debug)]
#[command(group(ArgGroup::new("how").required(true).args(["test_subjects", "test_fraction", "keep_release"])))]
pub struct SplitArgs {
    /// A folder written by `convert` (with dataset.json).
    #[arg(long)]
    dataset: PathBuf,
    /// Hold out this many subjects for test.
    #[arg(long)]
    test_subjects: Option<usize>,
    /// Hold out about this fraction of the images (whole subjects) for test.
    #[arg(long)]
    test_fraction: Option<f64>,
    /// Keep the release's own train/test lists.
    #[arg(long)]
    keep_release: bool,
    /// Also hold out this many subjects for validation (from the train side).
    #[arg(long, default_value_t = 0)]
    val_subjects: usize,
    /// Seed of the subject shuffle.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where to write (default: DATASET/splits).
    #[arg(long)]
    output: Option<PathBuf>,
    /// Print the counts as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: SplitArgs) -> Result<ExitCode> {
    let manifest = read_manifest(&a.dataset.join("dataset.json"))?;
    let mut keys: Vec<(SampleKey, String)> = Vec::new();
    for s in &manifest.shards {
        let path = a.dataset.join(&s.samples_file);
        keys.extend(samples_table::read_sample_keys(&path)?);
    }
    let mut per_subject: BTreeMap<String, usize> = BTreeMap::new();
    for (k, _) in &keys {
        *per_subject.entry(k.subject_id.clone()).or_default() += 1;
    }
    let assigned: Vec<String> = if a.keep_release {
        keys.iter().map(|(_, s)| s.clone()).collect()
    } else {
        let how = match (a.test_subjects, a.test_fraction) {
            (Some(n), _) => HoldOut::Subjects(n),
            (None, Some(f)) => HoldOut::Fraction(f),
            _ => unreachable!("clap requires one"),
        };
        let assignment = split::assign(&per_subject, how, a.val_subjects, a.seed)?;
        keys.iter()
            .map(|(k, _)| assignment.split_of(k).to_string())
            .collect()
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
    let out = a.output.clone().unwrap_or_else(|| a.dataset.join("splits"));
    let mut by_split: BTreeMap<String, Vec<SampleKey>> = BTreeMap::new();
    for ((k, _), s) in keys.iter().zip(&assigned) {
        by_split.entry(s.clone()).or_default().push(k.clone());
    }
    for (s, ks) in &by_split {
        release::write_list(
            &out.join("ARKitFace_list")
                .join("list")
                .join(format!("ARKitFace_{s}.csv")),
            ks,
        )?;
    }
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
    samples_table::write_parquet(&out.join("splits.parquet"), &mut df)?;
    let mut counts: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    for (s, ks) in &by_split {
        let subjects: std::collections::BTreeSet<&str> =
            ks.iter().map(|k| k.subject_id.as_str()).collect();
        counts.insert(s.clone(), (subjects.len(), ks.len()));
    }
    if a.json {
        let v: BTreeMap<&String, serde_json::Value> = counts
            .iter()
            .map(|(s, (n, m))| (s, serde_json::json!({"subjects": n, "images": m})))
            .collect();
        println!("{}", serde_json::to_string_pretty(&v).expect("json"));
    } else {
        println!(
            "{:<8} {:>9} {:>9} {:>7}",
            "split", "subjects", "images", "share"
        );
        for (s, (n, m)) in &counts {
            println!(
                "{:<8} {:>9} {:>9} {:>6.1}%",
                s,
                n,
                m,
                100.0 * *m as f64 / keys.len().max(1) as f64
            );
        }
        println!("wrote {}", out.display());
    }
    Ok(ExitCode::SUCCESS)
}

//! `arkit-tool split`.

use arkit_core::Result;
use arkit_data::ingest::{self, HoldOut};
use clap::{ArgGroup, Args};
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
    /// Hold out this many subjects for test (at least 1, fewer than the dataset has).
    #[arg(long, allow_negative_numbers = true, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    test_subjects: Option<usize>,
    /// Hold out about this fraction of the images (whole subjects) for test, in (0, 1).
    #[arg(long, allow_negative_numbers = true, value_parser = super::values::open_unit_interval)]
    test_fraction: Option<f64>,
    /// Keep the release's own train/test lists.
    #[arg(long)]
    keep_release: bool,
    /// Also hold out this many subjects for validation (from the train side; fewer
    /// than remain there).
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
    let how = match (a.keep_release, a.test_subjects, a.test_fraction) {
        (true, _, _) => None,
        (false, Some(n), _) => Some(HoldOut::Subjects(n)),
        (false, None, Some(f)) => Some(HoldOut::Fraction(f)),
        _ => unreachable!("clap requires one"),
    };
    let out = a.output.clone().unwrap_or_else(|| a.dataset.join("splits"));
    let counts = ingest::split_dataset(&a.dataset, how, a.val_subjects, a.seed, &out)?;
    let total: usize = counts.values().map(|c| c.images).sum();
    if a.json {
        let v: BTreeMap<&String, serde_json::Value> = counts
            .iter()
            .map(|(s, c)| {
                (
                    s,
                    serde_json::json!({"subjects": c.subjects, "images": c.images}),
                )
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&v).expect("json"));
    } else {
        println!(
            "{:<8} {:>9} {:>9} {:>7}",
            "split", "subjects", "images", "share"
        );
        for (s, c) in &counts {
            println!(
                "{:<8} {:>9} {:>9} {:>6.1}%",
                s,
                c.subjects,
                c.images,
                100.0 * c.images as f64 / total.max(1) as f64
            );
        }
        println!("wrote {}", out.display());
    }
    Ok(ExitCode::SUCCESS)
}

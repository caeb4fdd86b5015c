//! `arkit-tool eval`.

use arkit_core::Error;
use arkit_data::eval::EulerDifference;
use arkit_data::eval::EvalOptions;
use arkit_data::store::read_predictions;

use arkit_core::Result;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Score pose predictions with the paper's metrics.
///
/// Every sample of --split is scored: yaw, pitch, roll and MAE_r (degrees); tx, ty, tz
/// and MAE_t (mm); ADD (mm); geodesic rotation error; the 5deg5cm rate and the
/// official code's second rate (rotation < 10 deg, translation < 5 cm, printed there as
/// "5°10cm"); 3D reconstruction error when the predictions carry verts; mask accuracy,
/// IoU and precision when they carry masks (needs `render`'s targets). A sample with no
/// prediction, a null R_t, tz > 0 or tz < -100 m counts as a PnP failure and is scored
/// as the identity pose, as the official evaluation does. Predictions for unknown
/// samples and repeated ones are reported.
///
/// Predictions: Parquet or CSV (schemas/predictions.json) keyed by subject_id,
/// facial_action, img_id with R_t (16 numbers, the release's row-vector form).
///
/// ADD is the mean over the sample's own vertices: ARKit's 1,220, or for a BIWI
/// dataset (convert --format biwi) the subject's own head mesh. --exclude leaves
/// listed frames out (the paper's BIWI table with a detected box: 13,219 of 15,678).
///
/// Example: arkit-tool eval --dataset data/pq --predictions pred.parquet --split test --report report/
/// BIWI:    arkit-tool eval --dataset data/biwi-pq --predictions pred.parquet --split all --exclude no_box.csv
#[derive(Args, Debug)]
pub struct EvalArgs {
    /// A folder written by `convert`. Or a dataset published with `arkit-tool push`: s3://BUCKET/PREFIX (its tables
    /// are mirrored in the cache folder, $ARKIT_CACHE_DIR or ~/.cache/arkit-tool).
    #[arg(long)]
    dataset: PathBuf,
    /// The predictions file (.parquet, or .csv).
    #[arg(long)]
    predictions: PathBuf,
    /// Only this split (`splits/splits.parquet` if `split` wrote one, else the
    /// release's lists); `all` for every sample.
    #[arg(long, default_value = "test")]
    split: String,
    /// Euler differences: `official` (|a - b|, no wrap-around at +/-180) or `wrapped`
    /// (the shortest angle).
    #[arg(long, value_enum, default_value = "official")]
    euler: EulerDifference,
    /// Whose yaw, pitch and roll the per-axis errors use: `official` (the release's and
    /// the paper's: SciPy 'yxz' of R_t[:3,:3]^T), `wcpa` (the same angles), `trg` (its
    /// frame flipped: the same errors, the yaw and roll signs reversed), `6drepnet` or
    /// `img2pose` (their own decomposition, another order: other numbers). Rotation,
    /// translation, ADD and 3D errors do not depend on it. docs/conventions.md.
    #[arg(long, default_value = "official", value_name = "CONVENTION")]
    angles: arkit_core::conventions::AngleConvention,
    /// Where `render` wrote targets/ (for mask scores; default: the dataset).
    #[arg(long)]
    targets: Option<PathBuf>,
    /// Write the per-sample errors here (Parquet, schemas/eval_samples.json).
    #[arg(long)]
    per_sample: Option<PathBuf>,
    /// Write a report folder: error plots by pose and distance, the worst samples drawn
    /// (true mesh green, predicted red), the summary.
    #[arg(long)]
    report: Option<PathBuf>,
    /// The release's resource folder (real topology, to draw the meshes).
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Print the summary and the matching problems as JSON.
    #[arg(long)]
    json: bool,
    /// Leave these samples out of the scores: a list CSV with the columns subject_id,
    /// facial_action, img_id (the release's list format), for example the BIWI frames
    /// where a face detector finds no face (the paper's 13,219-frame protocol). The
    /// count left out is printed; listed keys the split does not have are reported.
    #[arg(long, value_name = "LIST.csv")]
    exclude: Option<PathBuf>,
}

pub fn run(mut a: EvalArgs) -> Result<ExitCode> {
    let (dir, _remote) = super::remote::dataset_folder(&a.dataset)?;
    a.dataset = dir;
    let predictions = read_predictions(&a.predictions)?;
    let options = EvalOptions {
        split: (a.split != "all").then(|| a.split.clone()),
        euler: a.euler,
        angles: a.angles,
        targets: a.targets.clone(),
        keep_worst: if a.report.is_some() { 8 } else { 0 },
        exclude: match &a.exclude {
            None => Default::default(),
            Some(path) => arkit_core::release::read_list(path)?
                .into_iter()
                .map(|r| r.key)
                .collect(),
        },
    };
    let ev = arkit_data::eval::evaluate(&a.dataset, &predictions, &options)?;
    if let Some(path) = &a.per_sample {
        let mut df = arkit_data::eval::per_sample_frame(&ev.samples)?;
        arkit_data::store::write_parquet(path, &mut df)?;
    }
    let mut written = Vec::new();
    if let Some(dir) = &a.report {
        let topology = super::setup::load_topology(a.resources.as_deref())?;
        written = arkit_data::eval::write_report(dir, &ev, &topology)?.files;
    }
    let p = &ev.problems;
    if a.json {
        let out = serde_json::json!({
            "angles": a.angles.name(),
            "summary": ev.summary,
            "problems": {
                "unknown": p.unknown.len(),
                "duplicates": p.duplicates.len(),
                "missing": p.missing,
                "unscored_masks": p.unscored_masks.len(),
                "non_rotations": p.non_rotations.len(),
                "excluded": p.excluded,
                "unscored_verts": p.unscored_verts,
                "exclude_unknown": p.exclude_unknown.len(),
                "first_exclude_unknown": p.exclude_unknown.iter().take(10).map(|k| k.to_string()).collect::<Vec<_>>(),
                "first_non_rotations": p.non_rotations.iter().take(10).map(|(k, why)| format!("{k}: {why}")).collect::<Vec<_>>(),
                "first_unknown": p.unknown.iter().take(10).map(|k| k.to_string()).collect::<Vec<_>>(),
                "first_duplicates": p.duplicates.iter().take(10).map(|k| k.to_string()).collect::<Vec<_>>(),
            },
        });
        println!("{}", serde_json::to_string_pretty(&out).expect("json"));
    } else {
        print!("{}", ev.summary.table());
        if a.angles != arkit_core::conventions::AngleConvention::Official {
            eprintln!(
                "note: yaw, pitch and roll are {}'s (docs/conventions.md)",
                a.angles
            );
        }
        if p.unscored_verts > 0 {
            eprintln!(
                "note: {} predicted meshes not scored for 3D reconstruction: the dataset's head mesh is another topology",
                p.unscored_verts
            );
        }
        if a.exclude.is_some() {
            eprintln!("left out {} samples named by --exclude", p.excluded);
        }
        if let Some(k) = p.exclude_unknown.first() {
            eprintln!(
                "warning: {} keys of --exclude are not samples of this split (first: {k})",
                p.exclude_unknown.len()
            );
        }
        for (what, keys) in [("unknown", &p.unknown), ("repeated", &p.duplicates)] {
            if !keys.is_empty() {
                eprintln!(
                    "warning: {} predictions for {what} samples (first: {})",
                    keys.len(),
                    keys[0]
                );
            }
        }
        if p.missing > 0 {
            eprintln!(
                "warning: {} samples have no prediction; scored as PnP failures",
                p.missing
            );
        }
        if let Some((k, why)) = p.non_rotations.first() {
            eprintln!(
                "warning: {} predicted R_t are not rotations, scored as the official evaluation scores them but meaningless (first: {k}: {why})",
                p.non_rotations.len()
            );
        }
        if let Some((k, why)) = p.unscored_masks.first() {
            eprintln!(
                "warning: {} predicted masks not scored (first: {k}: {why})",
                p.unscored_masks.len()
            );
        }
        for w in &written {
            println!("wrote {}", w.display());
        }
    }
    if ev.summary.samples == 0 {
        return Err(Error::invalid("eval", "nothing to evaluate"));
    }
    Ok(ExitCode::SUCCESS)
}

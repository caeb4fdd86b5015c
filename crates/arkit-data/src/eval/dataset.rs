//! Scoring a predictions file against a converted dataset: matching rows to samples,
//! the per-sample table, and the report folder (plots and the worst samples drawn).
//!
//! Every sample of the chosen split is scored: one with no prediction counts as a PnP
//! failure (see [`crate::eval::metrics`]). Predictions for samples the dataset does not have (or
//! not in the split) and repeated predictions are reported in [`MatchProblems`]; a
//! repeated key keeps its first row.

use crate::eval::metrics::{EulerDifference, PoseFailure, SampleErrors, Summary};
use crate::mesh::topology::FaceTopology;
use crate::picture::overlay::{MeshStyle, draw_mesh};
use crate::picture::plot::{Bars, bars_svg, sheet_labels_svg};
use crate::store::dataset::Dataset;
use crate::store::samples_table::SampleRecord;
use crate::store::splits::SplitLookup;
use arkit_core::PredictionRecord;
use arkit_core::SampleKey;
use arkit_core::conventions::Pose;
use arkit_core::{Error, Result};
use image::{Rgb, RgbImage};
use nalgebra::Point3;
use polars::prelude::*;
use serde::Serialize;
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

/// What to evaluate and how.
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// Only samples of this split (`None`: all). The split comes from
    /// `DATASET/splits/splits.parquet` when `split` has written one, else from the
    /// release lists recorded by `convert`.
    pub split: Option<String>,
    /// Euler difference rule.
    pub euler: EulerDifference,
    /// Whose yaw, pitch and roll are scored (the release's by default).
    pub angles: arkit_core::conventions::AngleConvention,
    /// Folder holding `targets/part-*.parquet` (for mask scores); default the dataset.
    pub targets: Option<PathBuf>,
    /// How many of the worst samples to keep for drawing.
    pub keep_worst: usize,
    /// Samples left out of the scores (for example the BIWI frames where a face
    /// detector fails, as the paper's 13,219 of 15,678); predictions for them are
    /// neither scored nor reported as unknown.
    pub exclude: HashSet<SampleKey>,
}

impl Default for EvalOptions {
    fn default() -> Self {
        EvalOptions {
            split: None,
            euler: EulerDifference::Official,
            angles: arkit_core::conventions::AngleConvention::Official,
            targets: None,
            keep_worst: 8,
            exclude: HashSet::new(),
        }
    }
}

/// Prediction rows that do not match the dataset one to one.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct MatchProblems {
    /// Keys predicted that are not samples of the evaluated split.
    pub unknown: Vec<SampleKey>,
    /// Keys predicted more than once (first row kept).
    pub duplicates: Vec<SampleKey>,
    /// Samples of the split with no prediction (scored as failures).
    pub missing: usize,
    /// Predicted masks that could not be scored, with the reason.
    pub unscored_masks: Vec<(SampleKey, String)>,
    /// Predicted `R_t`s whose upper 3x3 is not a rotation (not orthonormal, or a
    /// reflection), with the reason. They are scored as the official evaluation scores
    /// them (its Euler angles of the nearest rotation), so the figures match it, but the
    /// scores of such a prediction mean little: a matrix scaled by 1000 scores MAE_r 0.
    pub non_rotations: Vec<(SampleKey, String)>,
    /// Predicted meshes not scored because the dataset's head mesh is another
    /// topology (BIWI's): 3D reconstruction needs vertex-to-vertex correspondence.
    pub unscored_verts: usize,
    /// Samples of the split left out by [`EvalOptions::exclude`].
    pub excluded: usize,
    /// Keys of [`EvalOptions::exclude`] that are not samples of the evaluated split.
    pub exclude_unknown: Vec<SampleKey>,
}

/// One scored sample.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ScoredSample {
    /// The sample.
    pub key: SampleKey,
    /// Ground-truth yaw, pitch, roll (degrees) and distance `-tz` (metres).
    pub gt_yaw_deg: f64,
    /// Ground-truth pitch, degrees.
    pub gt_pitch_deg: f64,
    /// Ground-truth roll, degrees.
    pub gt_roll_deg: f64,
    /// Ground-truth camera distance `-tz`, metres.
    pub gt_distance_m: f64,
    /// The errors.
    pub errors: SampleErrors,
}

/// The result of [`evaluate`].
#[derive(Clone, Debug)]
pub struct Evaluation {
    /// Per sample, in dataset order.
    pub samples: Vec<ScoredSample>,
    /// The summary table.
    pub summary: Summary,
    /// Rows that did not match.
    pub problems: MatchProblems,
    /// The worst samples by geodesic rotation error (worst first), with their
    /// predictions, for drawing.
    pub worst: Vec<(SampleRecord, Option<PredictionRecord>, f64)>,
    /// The dataset (to read the worst samples' images for the report).
    pub dataset: Dataset,
}

/// The rendered masks of the samples `wanted`, read from the targets files of the
/// dataset's shards under `dir` (`targets/part-KKKKK.parquet` for each shard `K` of
/// `data`; none when absent): only those files, never another `*.parquet` found there
/// (a copy made by hand would otherwise be read too).
fn target_masks(
    dir: &Path,
    data: &Dataset,
    wanted: &HashSet<&SampleKey>,
) -> Result<HashMap<SampleKey, Vec<bool>>> {
    let mut out = HashMap::new();
    // Opened with the dataset and checked to be of its generation.
    let rendered = crate::store::RenderedTargets::open(dir, data)?;
    for shard in data.shards() {
        for r in rendered.rows(shard.index)? {
            if wanted.contains(&r.key) {
                let m = r.mask()?;
                out.insert(r.key, m);
            }
        }
    }
    Ok(out)
}

/// Scores `predictions` against the samples of `dataset` (a `convert` output).
pub fn evaluate(
    dataset: &Path,
    predictions: &[PredictionRecord],
    options: &EvalOptions,
) -> Result<Evaluation> {
    let data = Dataset::open(dataset)?;
    let splits = SplitLookup::read(dataset)?;
    let mut problems = MatchProblems::default();
    let by_key = index_predictions(predictions, &mut problems);
    let masks = prediction_masks(dataset, &data, predictions, options)?;
    // What was read besides the shards (split files, targets) is of the generation
    // opened; the shards are read through the files opened with it.
    data.confirm_unchanged()?;
    // A dataset of another head mesh than ARKit's (`convert --format biwi`).
    let other_mesh = data
        .manifest()
        .topology
        .starts_with(crate::ingest::biwi::TOPOLOGY_PREFIX);
    let mut seen: HashSet<SampleKey> = HashSet::new();
    let mut scored = Vec::new();
    let mut worst: Vec<(SampleRecord, Option<PredictionRecord>, f64)> = Vec::new();
    let mut splits_found: HashSet<String> = HashSet::new();
    for shard in data.shards() {
        let rows = data.read_samples(shard)?;
        for r in rows {
            let split = splits.of(&r);
            splits_found.insert(split.clone());
            if options.split.as_ref().is_some_and(|s| *s != split) {
                continue;
            }
            seen.insert(r.key.clone());
            if options.exclude.contains(&r.key) {
                problems.excluded += 1;
                continue;
            }
            let pred = by_key.get(&r.key).copied();
            let errors = score_sample(&r, pred, other_mesh, &masks, options, &mut problems)?;
            let rot = errors.rotation_deg;
            if options.keep_worst > 0 {
                keep_worst(&mut worst, options.keep_worst, &r, pred, rot);
            }
            scored.push(ScoredSample {
                key: r.key.clone(),
                gt_yaw_deg: r.yaw_deg,
                gt_pitch_deg: r.pitch_deg,
                gt_roll_deg: r.roll_deg,
                gt_distance_m: -r.translation_m[2],
                errors,
            });
        }
    }
    if scored.is_empty() {
        let mut found: Vec<String> = splits_found.into_iter().collect();
        found.sort();
        return Err(Error::invalid(
            "--split",
            format!(
                "no samples in split '{}' of {} (splits there: {})",
                options.split.as_deref().unwrap_or("all"),
                dataset.display(),
                found.join(", ")
            ),
        ));
    }
    for p in predictions {
        if !seen.contains(&p.key) {
            problems.unknown.push(p.key.clone());
        }
    }
    let mut exclude_unknown: Vec<SampleKey> = options
        .exclude
        .iter()
        .filter(|k| !seen.contains(*k))
        .cloned()
        .collect();
    exclude_unknown.sort();
    problems.exclude_unknown = exclude_unknown;
    let errors: Vec<SampleErrors> = scored.iter().map(|s| s.errors.clone()).collect();
    Ok(Evaluation {
        summary: crate::eval::metrics::summarize(&errors, options.euler),
        samples: scored,
        problems,
        worst,
        dataset: data,
    })
}

/// The predictions by sample key: the first of each key (a later one with the same key
/// is listed in `problems.duplicates`).
fn index_predictions<'a>(
    predictions: &'a [PredictionRecord],
    problems: &mut MatchProblems,
) -> HashMap<&'a SampleKey, &'a PredictionRecord> {
    let mut by_key: HashMap<&SampleKey, &PredictionRecord> = HashMap::new();
    for p in predictions {
        if by_key.contains_key(&p.key) {
            problems.duplicates.push(p.key.clone());
        } else {
            by_key.insert(&p.key, p);
        }
    }
    by_key
}

/// The rendered masks of the samples whose prediction has a mask, from `options.targets`
/// (or the dataset's own targets); none read when no prediction has one.
fn prediction_masks(
    dataset: &Path,
    data: &Dataset,
    predictions: &[PredictionRecord],
    options: &EvalOptions,
) -> Result<HashMap<SampleKey, Vec<bool>>> {
    let with_masks: HashSet<&SampleKey> = predictions
        .iter()
        .filter(|p| p.mask_rle.is_some())
        .map(|p| &p.key)
        .collect();
    if with_masks.is_empty() {
        Ok(HashMap::new())
    } else {
        target_masks(
            options.targets.as_deref().unwrap_or(dataset),
            data,
            &with_masks,
        )
    }
}

/// The errors of sample `r` against its prediction `pred` (none: missing), noting in
/// `problems` a missing prediction, a prediction that is not a rotation, vertices that
/// cannot be scored against another head mesh and a mask that cannot be scored. Vertices
/// of the wrong size against the ARKit mesh are an error.
fn score_sample(
    r: &SampleRecord,
    pred: Option<&PredictionRecord>,
    other_mesh: bool,
    masks: &HashMap<SampleKey, Vec<bool>>,
    options: &EvalOptions,
    problems: &mut MatchProblems,
) -> Result<SampleErrors> {
    let checked = match pred {
        None => Err(PoseFailure::Missing),
        Some(p) => crate::eval::metrics::check_prediction(p.rt.as_ref()),
    };
    if let Ok(rt) = &checked
        && let Err(e) = arkit_core::conventions::Pose::check_release_rt(rt)
    {
        let why = match e {
            Error::Invalid { message, .. } => message,
            other => other.reason(),
        };
        problems.non_rotations.push((r.key.clone(), why));
    }
    if pred.is_none() {
        problems.missing += 1;
    }
    let mut pred_verts = pred.and_then(|p| p.verts.as_deref());
    if other_mesh
        && let Some(v) = pred_verts
        && v.len() != r.verts.len()
    {
        // A network's 1,220-vertex face against another head mesh (BIWI's): no
        // vertex correspondence, so no 3D reconstruction error; counted.
        problems.unscored_verts += 1;
        pred_verts = None;
    }
    if let Some(v) = pred_verts
        && v.len() != r.verts.len()
    {
        return Err(Error::invalid(
            "predictions",
            format!(
                "{}: verts has {} values, the sample has {}",
                r.key,
                v.len(),
                r.verts.len()
            ),
        ));
    }
    let mut errors = crate::eval::metrics::sample_errors_in(
        &r.rt,
        checked,
        &r.verts,
        pred_verts,
        options.euler,
        options.angles,
    );
    if let Some(rle) = pred.and_then(|p| p.mask_rle.as_ref()) {
        match masks.get(&r.key) {
            None => problems
                .unscored_masks
                .push((r.key.clone(), "no target mask (run render)".into())),
            Some(target) => match arkit_core::rle_decode(rle, target.len()) {
                Ok(m) => errors.mask = Some(crate::eval::metrics::mask_scores(&m, target)),
                Err(e) => problems.unscored_masks.push((r.key.clone(), e.to_string())),
            },
        }
    }
    Ok(errors)
}

/// Keeps sample `r` (rotation error `rot`) among the `keep` worst, worst first.
fn keep_worst(
    worst: &mut Vec<(SampleRecord, Option<PredictionRecord>, f64)>,
    keep: usize,
    r: &SampleRecord,
    pred: Option<&PredictionRecord>,
    rot: f64,
) {
    if worst.len() < keep || worst.last().is_some_and(|w| w.2 < rot) {
        let mut r2 = r.clone();
        r2.verts.shrink_to_fit();
        worst.push((r2, pred.cloned(), rot));
        worst.sort_by(|a, b| b.2.total_cmp(&a.2));
        worst.truncate(keep);
    }
}

/// The per-sample table as a DataFrame (columns as `schemas/eval_samples.json`).
pub fn per_sample_frame(samples: &[ScoredSample]) -> Result<DataFrame> {
    let s = |n: &str, f: &dyn Fn(&ScoredSample) -> String| {
        Column::new(n.into(), samples.iter().map(f).collect::<Vec<String>>())
    };
    let f = |n: &str, g: &dyn Fn(&ScoredSample) -> f64| {
        Column::new(n.into(), samples.iter().map(g).collect::<Vec<f64>>())
    };
    let o = |n: &str, g: &dyn Fn(&ScoredSample) -> Option<f64>| {
        Column::new(
            n.into(),
            samples.iter().map(g).collect::<Vec<Option<f64>>>(),
        )
    };
    let columns = vec![
        s("subject_id", &|r| r.key.subject_id.clone()),
        s("facial_action", &|r| r.key.facial_action.clone()),
        s("img_id", &|r| r.key.img_id.clone()),
        s("failure", &|r| {
            r.errors.failure.map(|f| f.name()).unwrap_or("").to_string()
        }),
        f("gt_yaw_deg", &|r| r.gt_yaw_deg),
        f("gt_pitch_deg", &|r| r.gt_pitch_deg),
        f("gt_roll_deg", &|r| r.gt_roll_deg),
        f("gt_distance_m", &|r| r.gt_distance_m),
        f("yaw_err_deg", &|r| r.errors.yaw_deg),
        f("pitch_err_deg", &|r| r.errors.pitch_deg),
        f("roll_err_deg", &|r| r.errors.roll_deg),
        f("tx_err_mm", &|r| r.errors.tx_mm),
        f("ty_err_mm", &|r| r.errors.ty_mm),
        f("tz_err_mm", &|r| r.errors.tz_mm),
        f("add_mm", &|r| r.errors.add_mm),
        f("rotation_err_deg", &|r| r.errors.rotation_deg),
        f("translation_err_mm", &|r| r.errors.translation_mm),
        o("recon_mm", &|r| r.errors.recon_mm),
        o("mask_iou", &|r| r.errors.mask.map(|m| m.iou)),
    ];
    DataFrame::new(samples.len(), columns)
        .map_err(|e| Error::invalid("per-sample table", e.to_string()))
}

/// Column names of the per-sample table, in order.
pub const PER_SAMPLE_COLUMNS: [&str; 19] = [
    "subject_id",
    "facial_action",
    "img_id",
    "failure",
    "gt_yaw_deg",
    "gt_pitch_deg",
    "gt_roll_deg",
    "gt_distance_m",
    "yaw_err_deg",
    "pitch_err_deg",
    "roll_err_deg",
    "tx_err_mm",
    "ty_err_mm",
    "tz_err_mm",
    "add_mm",
    "rotation_err_deg",
    "translation_err_mm",
    "recon_mm",
    "mask_iou",
];

/// Draws `verts` at `pose`: the topology's outline when the mesh is the topology's,
/// else (another head mesh, such as BIWI's) every vertex as a point, so no mesh is
/// drawn with another mesh's triangles.
fn draw_outline_or_points(
    img: &mut RgbImage,
    topology: &FaceTopology,
    verts: &[Point3<f64>],
    pose: &Pose,
    colour: Rgb<u8>,
) -> Result<()> {
    if verts.len() == topology.vertex_count {
        return draw_mesh(img, topology, verts, pose, &MeshStyle::outline(colour));
    }
    let camera = arkit_core::conventions::Camera::release(img.width(), img.height());
    for q in camera.project_all(pose, verts) {
        let (x, y) = (q.u.floor(), q.v.floor());
        if x >= 0.0 && y >= 0.0 && x < img.width() as f64 && y < img.height() as f64 {
            img.put_pixel(x as u32, y as u32, colour);
        }
    }
    Ok(())
}

/// What [`write_report`] wrote.
#[derive(Clone, Debug, Default)]
pub struct ReportFiles {
    /// The files, in order.
    pub files: Vec<PathBuf>,
    /// The captions of `worst.png`'s cells (key and rotation error), as an SVG to lay
    /// over the picture; None when no sample was drawn.
    pub worst_labels: Option<String>,
}

/// Writes the report folder: `errors_by_pose.svg` (charts of the mean errors per
/// |yaw|, |pitch| and distance bin, labelled axes), `worst.png` (the worst samples, true
/// mesh green, predicted red), `worst.svg` (the same picture with each sample's key and
/// error as captions) and `summary.txt`.
pub fn write_report(dir: &Path, ev: &Evaluation, topology: &FaceTopology) -> Result<ReportFiles> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let rot = |f: &dyn Fn(&ScoredSample) -> f64| -> Vec<(f64, f64)> {
        ev.samples
            .iter()
            .map(|s| (f(s), s.errors.rotation_deg))
            .collect()
    };
    let (dmin, dmax) = ev.samples.iter().fold((f64::MAX, f64::MIN), |(a, b), s| {
        (a.min(s.gt_distance_m), b.max(s.gt_distance_m))
    });
    let (dlo, dhi) = (
        (dmin * 10.0).floor() / 10.0,
        (dmax * 10.0).ceil() / 10.0 + 0.1,
    );
    let n = ev.samples.len();
    let panels = [
        Bars::binned_mean(
            &format!("Rotation error by |yaw| ({n} samples)"),
            "|yaw| (deg)",
            "mean rotation error (deg)",
            rot(&|s| s.gt_yaw_deg.abs()),
            0.0,
            90.0,
            9,
        )
        .with_x_step(10.0),
        Bars::binned_mean(
            &format!("Rotation error by |pitch| ({n} samples)"),
            "|pitch| (deg)",
            "mean rotation error (deg)",
            rot(&|s| s.gt_pitch_deg.abs()),
            0.0,
            90.0,
            9,
        )
        .with_x_step(10.0),
        Bars::binned_mean(
            &format!("Translation error by distance ({n} samples)"),
            "distance to the camera (m)",
            "mean translation error (mm)",
            ev.samples
                .iter()
                .map(|s| (s.gt_distance_m, s.errors.translation_mm)),
            dlo,
            dhi,
            8,
        ),
    ];
    let mut written = Vec::new();
    let plot_path = dir.join("errors_by_pose.svg");
    let chart = bars_svg("Errors by pose", &panels, 3);
    arkit_core::atomic_file::write_bytes(&plot_path, chart.as_bytes())?;
    written.push(plot_path);
    let mut cells = Vec::new();
    let mut labels = Vec::new();
    let mut unreadable = Vec::new();
    for (sample, pred, err) in &ev.worst {
        // A sample whose image cannot be read is left out of the picture and named in
        // the summary, not drawn over a placeholder.
        let mut img = match ev.dataset.image(sample) {
            Ok(img) => img,
            Err(e) => {
                unreadable.push(e.to_string());
                continue;
            }
        };
        let gt_verts: Vec<Point3<f64>> = sample
            .verts
            .chunks_exact(3)
            .map(|c| Point3::new(c[0] as f64, c[1] as f64, c[2] as f64))
            .collect();
        if let Ok(pose) = Pose::from_release_rt(&sample.rt) {
            draw_outline_or_points(&mut img, topology, &gt_verts, &pose, Rgb([40, 240, 90]))?;
        }
        if let Some(p) = pred
            && let Some(rt) = p.rt
            && let Ok(pose) = Pose::from_release_rt(&rt)
        {
            let pv: Vec<Point3<f64>> = match &p.verts {
                Some(v) => v
                    .chunks_exact(3)
                    .map(|c| Point3::new(c[0] as f64, c[1] as f64, c[2] as f64))
                    .collect(),
                None => gt_verts.clone(),
            };
            draw_outline_or_points(&mut img, topology, &pv, &pose, Rgb([250, 60, 60]))?;
        }
        labels.push(format!(
            "{} {}\n{}: {:.1} deg",
            sample.key.subject_id, sample.key.facial_action, sample.key.img_id, err
        ));
        cells.push(img);
    }
    let mut worst_labels = None;
    if !cells.is_empty() {
        let (columns, cell) = (4, 320);
        let sheet = crate::picture::encode::contact_sheet(&cells, columns, cell);
        let cell_h = (cell as f64 * cells[0].height() as f64 / cells[0].width() as f64).round();
        let p = dir.join("worst.png");
        arkit_core::atomic_file::write_bytes(&p, &png_bytes(&sheet)?)?;
        written.push(p);
        let geometry = (sheet.dimensions(), (cell, cell_h as u32));
        let title = "The worst predictions: key and rotation error";
        let p = dir.join("worst.svg");
        let svg = sheet_labels_svg(
            title,
            Some("worst.png"),
            geometry.0,
            geometry.1,
            columns,
            &labels,
        );
        arkit_core::atomic_file::write_bytes(&p, svg.as_bytes())?;
        written.push(p);
        worst_labels = Some(sheet_labels_svg(
            title, None, geometry.0, geometry.1, columns, &labels,
        ));
    }
    let p = dir.join("summary.txt");
    let mut text = ev.summary.table();
    if !labels.is_empty() {
        text.push_str("\nworst.png, left to right, top to bottom:\n");
        for l in &labels {
            text.push_str(&format!("  {}\n", l.replace('\n', " ")));
        }
    }
    if !unreadable.is_empty() {
        text.push_str(&format!(
            "\nworst.png leaves out {} sample(s) whose image could not be read:\n",
            unreadable.len()
        ));
        for why in &unreadable {
            text.push_str(&format!("  {why}\n"));
        }
    }
    arkit_core::atomic_file::write_bytes(&p, text.as_bytes())?;
    written.push(p);
    Ok(ReportFiles {
        files: written,
        worst_labels,
    })
}

/// PNG bytes of an image.
pub fn png_bytes(img: &RgbImage) -> Result<Vec<u8>> {
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .map_err(|e| Error::invalid("png", e.to_string()))?;
    Ok(out.into_inner())
}

//! `arkit-tool predict`.

use arkit_core::error::Result;
#[cfg(feature = "model")]
use arkit_data::crop::CropRule;
use arkit_data::pose::pnp::RansacParams;
use arkit_data::pose::predict::{self, OracleOptions};
use arkit_data::store::predictions_table::write_predictions;
use clap::{ArgGroup, Args};
use std::path::PathBuf;
use std::process::ExitCode;

/// Predict poses and write a predictions file for `eval`.
///
/// --oracle: the ground-truth correspondences that `render` stored (sampled face
/// pixels and the canonical points under them), with optional pixel noise and
/// outliers, through our PnP (P3P + MSAC RANSAC, 8 px threshold, 100 iterations,
/// confidence 0.99, then Levenberg-Marquardt on the inliers). With no noise every
/// metric is ~0: a check of render, crop transform, PnP and eval together; with
/// --noise-px 1 it is the floor any model meets.
///
/// --model DIR: a network trained by `train`: the crop box from the sample's
/// landmarks (as the official evaluation does), the predicted face mask, --points
/// pixels sampled from it, their predicted 3D points through the same PnP; the
/// predictions also carry the predicted mesh and crop mask, for `eval`'s 3D
/// reconstruction and mask scores. A direct baseline (`train --architecture direct`)
/// gives its regressed pose instead: no points, no PnP, no mesh or mask (`eval` then
/// prints '-' for 3DRecon). models/tiny-synthetic is a trained tiny PerspNet shipped
/// with arkit-tool (for the built-in synthetic face).
///
/// --mean-pose: the training split's mean pose for every sample, the baseline a model
/// must beat (no mesh or mask, so `eval` scores the pose only).
///
/// Example: arkit-tool predict --oracle --dataset data/pq --noise-px 1 --output oracle.parquet
///          arkit-tool predict --model model/ --dataset data/pq --output pred.parquet
///          arkit-tool predict --mean-pose --dataset data/pq --output baseline.parquet
#[derive(Args, Debug)]
#[command(group(ArgGroup::new("predictor").required(true).args(["oracle", "model", "mean_pose"])))]
pub struct PredictArgs {
    /// A folder written by `convert` (and `render`).
    #[arg(long)]
    dataset: PathBuf,
    /// With --model: exit with status 1 if any sample's image could not be read (the
    /// predictions of the others are still written; without it such samples are
    /// reported and left out, and `eval` counts them missing).
    #[arg(long)]
    strict: bool,
    /// Use the stored ground-truth correspondences.
    #[arg(long)]
    oracle: bool,
    /// Use a network trained by `train` (its checkpoint folder; PerspNet or the direct
    /// baseline, as its perspnet.json says).
    #[arg(long)]
    model: Option<PathBuf>,
    /// The trivial baseline: the training split's mean pose (chordal mean rotation,
    /// mean translation) for every sample.
    #[arg(long)]
    mean_pose: bool,
    /// The release's resource folder (real topology), as given to `train`.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Where `render` wrote targets/ (default: the dataset).
    #[arg(long)]
    targets: Option<PathBuf>,
    /// Gaussian pixel noise added to each point (standard deviation, pixels), in
    /// [0, 100].
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0, value_parser = super::noise_px)]
    noise_px: f64,
    /// Share of points replaced by random image points, in [0, 1).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0, value_parser = super::unit_interval_open)]
    outliers: f64,
    /// Only this split (as `eval` chooses it); `all` for every sample.
    #[arg(long, default_value = "test")]
    split: String,
    /// Seed of the noise and of RANSAC.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// RANSAC reprojection threshold, pixels, in (0, 1000].
    #[arg(long, allow_negative_numbers = true, default_value_t = 8.0, value_parser = super::threshold_px)]
    threshold_px: f64,
    /// The predictions file to write (Parquet, schemas/predictions.json).
    #[arg(long)]
    output: PathBuf,
    /// Worker threads, 1..=1024 (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::jobs)]
    jobs: Option<usize>,
    /// With --model: sample the points from the `predicted` face mask, or from the
    /// `truth` that `render` stored (at the network's input size, in --targets), to
    /// tell segmentation errors from correspondence errors.
    #[arg(long, value_enum, default_value = "predicted")]
    mask: MaskSource,
    /// With --model: whose crop box the network sees: `ours` (the square box, pixel
    /// centres) or `official` (the official loader's integer box through
    /// cv2.warpAffine), as the model was trained (`render --compat official` targets
    /// train on the official crop). With --mask truth, the targets' own crop is used.
    #[arg(long, value_enum, default_value = "ours")]
    crop: CropChoice,
    /// With --model: also write, for each predicted sample, the network's inputs (the
    /// normalised crop, the chosen pixel indices) and raw outputs (segmentation logits,
    /// UV map, assignment matrix, M X, X) to this .npz, keyed `subject/action/image/NAME`
    /// (see docs/train.md; about 1.4 MB a sample for `tiny`, 6 MB for `paper`, held in
    /// memory until written).
    #[arg(long, value_name = "FILE.npz")]
    dump: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

/// `--crop` values.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum CropChoice {
    Ours,
    Official,
}

/// `--mask` values.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum MaskSource {
    Predicted,
    Truth,
}

pub fn run(a: PredictArgs) -> Result<ExitCode> {
    if !(0.0..1.0).contains(&a.outliers) || a.noise_px < 0.0 || !a.noise_px.is_finite() {
        return Err(arkit_core::error::Error::invalid(
            "--noise-px/--outliers",
            "noise must be >= 0 and the outlier share in [0, 1)",
        ));
    }
    if a.dump.is_some() && a.model.is_none() {
        return Err(arkit_core::error::Error::invalid(
            "--dump",
            "dumps a network's inputs and outputs: it needs --model",
        ));
    }
    let manifest = arkit_data::store::dataset::Dataset::open(&a.dataset)?
        .manifest()
        .clone();
    let ransac = RansacParams {
        reprojection_threshold_px: a.threshold_px,
        seed: a.seed,
        ..RansacParams::default()
    };
    let split = (a.split != "all").then_some(a.split.as_str());
    if a.mean_pose {
        let (rows, summary) = predict::mean_pose_predictions(&a.dataset, Some("train"), split)?;
        write_predictions(&a.output, &rows)?;
        if a.json {
            println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
        } else {
            let e = summary.euler_deg;
            println!(
                "mean pose of {} training samples (yaw {:.2}, pitch {:.2}, roll {:.2} deg; t {:.1}, {:.1}, {:.1} mm) for {} samples -> {}",
                summary.fitted_on,
                e[0],
                e[1],
                e[2],
                summary.rt[12] * 1e3,
                summary.rt[13] * 1e3,
                summary.rt[14] * 1e3,
                summary.samples,
                a.output.display()
            );
        }
        return Ok(ExitCode::SUCCESS);
    }
    #[cfg(not(feature = "model"))]
    if a.model.is_some() {
        return Err(arkit_core::error::Error::invalid(
            "--model",
            "this arkit-tool was built without the `model` feature (candle); rebuild with default features to run a trained network",
        ));
    }
    #[cfg(feature = "model")]
    if let Some(dir) = &a.model {
        let topology = super::load_topology(a.resources.as_deref())?;
        let model = arkit_perspnet::load(dir, &topology)?;
        let bar = super::progress_bar(manifest.converted as u64, "predict", "samples");
        let targets = a.targets.clone().unwrap_or_else(|| a.dataset.clone());
        let mut dump = Vec::new();
        let (rows, summary) = arkit_perspnet::model_predictions_dump(
            &a.dataset,
            &model,
            split,
            match a.crop {
                CropChoice::Ours => CropRule::Ours,
                CropChoice::Official => CropRule::Official,
            },
            matches!(a.mask, MaskSource::Truth).then_some(targets.as_path()),
            a.seed,
            &ransac,
            &|n| bar.inc(n as u64),
            a.dump.is_some().then_some(&mut dump),
        )?;
        bar.finish_and_clear();
        write_predictions(&a.output, &rows)?;
        if let Some(path) = &a.dump {
            arkit_perspnet::write_dump(path, &model.checkpoint.config, &topology, &dump)?;
            if !a.json {
                eprintln!(
                    "dumped {} samples' network inputs and outputs -> {}",
                    dump.len(),
                    path.display()
                );
            }
        }
        if a.json {
            println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
        } else {
            println!(
                "model {}: {} samples, {} PnP failures -> {}",
                dir.display(),
                summary.samples,
                summary.failures,
                a.output.display()
            );
            if summary.without_true_mask > 0 {
                eprintln!(
                    "left out {} samples that render could not render (no true mask; see the targets' errors/)",
                    summary.without_true_mask
                );
            }
        }
        super::report_unreadable(&summary.unreadable, "predict");
        if a.strict && !summary.unreadable.is_empty() {
            return Ok(ExitCode::FAILURE);
        }
        return Ok(ExitCode::SUCCESS);
    }
    let options = OracleOptions {
        noise_px: a.noise_px,
        outliers: a.outliers,
        seed: a.seed,
        split: (a.split != "all").then(|| a.split.clone()),
        ransac,
    };
    let bar = super::progress_bar(manifest.converted as u64, "predict", "samples");
    let pool = super::thread_pool(a.jobs)?;
    let targets = a.targets.clone().unwrap_or_else(|| a.dataset.clone());
    let (rows, summary) = pool.install(|| {
        predict::oracle_predictions(&a.dataset, &targets, &options, &|n| bar.inc(n as u64))
    })?;
    bar.finish_and_clear();
    write_predictions(&a.output, &rows)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
    } else {
        println!(
            "oracle: {} samples ({:.0} distinct points each on average), {} PnP failures, {} without targets -> {}",
            summary.samples,
            summary.mean_points,
            summary.failures,
            summary.without_targets,
            a.output.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}

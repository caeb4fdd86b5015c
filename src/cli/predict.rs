//! `arkit-tool predict`.

use arkit_core::Result;
#[cfg(feature = "model")]
use arkit_data::crop::RuleSet;
use arkit_data::pose::RansacParams;
use arkit_data::pose::{self, OracleOptions};
use arkit_data::store::write_predictions;
use arkit_data::video::OneEuroParams;
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
/// --image PHOTO --model DIR: the faces of photos (files or folders), as the official
/// demo.py finds them: the photo padded to a square and resized to 800 px, each face
/// box (--box, --boxes FILE, or the built-in detector when none is given) cut by the
/// 0.75 x max(w, h) rule into the network's crop, the network, our PnP in the demo's
/// camera (or the photo's own: --focal-px, --fov-deg). Prints JSON (R_t in the
/// release's convention, yaw/pitch/roll in --angles' convention, the translation,
/// OpenCV's rvec/tvec, the inlier count), or writes it to --output (.json, or .csv
/// with one row per face); --draw pictures the mesh on the photo; --mesh DIR writes
/// each face's mesh (.obj, .ply) and landmarks. Photos are turned upright by their
/// EXIF orientation first: boxes and outputs are in the pixels people see. A truncated
/// or corrupt photo is refused by name (skipped when found in a folder). docs/photos.md.
///
/// --video FILE --model DIR: the faces of a video (an H.264 MP4 or MOV, or a folder of
/// numbered frames), frame by frame as with --image: the detector every frame (or
/// every --detect-every N, boxes carried between; or the boxes of a --boxes JSON-lines
/// file), faces matched across frames into tracks, each track's pose smoothed by a
/// One-Euro filter on SO(3) (--no-smooth for the raw poses). Writes one row per frame
/// and track to --output (.jsonl, .csv or .parquet; JSON lines on the standard output
/// without it); --draw writes an .mp4 or a folder of frames; --mesh DIR each frame's
/// meshes and landmarks. A Rerun recording of the rows: python -m arkit_tool.video_view.
/// docs/video.md.
///
/// Example: arkit-tool predict --oracle --dataset data/pq --noise-px 1 --output oracle.parquet
///          arkit-tool predict --model model/ --dataset data/pq --output pred.parquet
///          arkit-tool predict --mean-pose --dataset data/pq --output baseline.parquet
///          arkit-tool predict --model model/ --image group.jpg --draw result.jpg
///          arkit-tool predict --model model/ --image photo.jpg --box "120 80 260 240" --fov-deg 70
///          arkit-tool predict --model model/ --image trip1/ trip2/ --mesh meshes/ --draw drawn/
///          arkit-tool predict --model model/ --video clip.mp4 --output poses.jsonl --draw drawn.mp4
#[derive(Args, Debug)]
#[command(group(ArgGroup::new("predictor").required(true).args(["oracle", "model", "mean_pose"])))]
#[command(group(ArgGroup::new("input").required(true).args(["dataset", "image", "video"])))]
pub struct PredictArgs {
    /// A folder written by `convert` (and `render`). Or a dataset published with `arkit-tool push`: s3://BUCKET/PREFIX (its tables
    /// are mirrored in the cache folder, $ARKIT_CACHE_DIR or ~/.cache/arkit-tool).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Photos to find head poses in (PNG, JPEG or WebP files, or folders of them; repeat
    /// for several), with --model (a PerspNet).
    #[arg(long, value_name = "PHOTO", num_args = 1..)]
    image: Vec<PathBuf>,
    /// A video to find head poses in: an MP4 or MOV with H.264 video (as phones and
    /// webcams record them), or a folder of numbered frames (PNG, JPEG or WebP), with
    /// --model (a PerspNet). docs/video.md.
    #[arg(long, value_name = "FILE_OR_FOLDER", conflicts_with = "image")]
    video: Option<PathBuf>,
    /// --video's options.
    #[command(flatten)]
    video_options: Box<VideoOptions>,
    /// With --image (one photo): a face box "x0 y0 x1 y1" in the photo's pixels, as the
    /// official demo takes it; repeat for several faces.
    #[arg(long = "box", value_name = "X0 Y0 X1 Y1", allow_hyphen_values = true)]
    boxes: Vec<String>,
    /// With --image: face boxes from a file: JSON (`[[x0, y0, x1, y1], ...]` for one
    /// photo, or `{"PHOTO": [[...], ...]}`) or CSV (header `image,x0,y0,x1,y1`), photos
    /// named as given or by file name. A photo with no box is given to the detector.
    /// With --video: JSON lines, `{"frame": N, "boxes": [[x0, y0, x1, y1], ...]}`, used
    /// instead of the detector (as `synth --video` writes them).
    #[arg(long = "boxes", value_name = "FILE")]
    boxes_file: Option<PathBuf>,
    /// With --image: the detector's smallest face, pixels (at least 20).
    #[arg(long, default_value_t = 40)]
    min_face_px: u32,
    /// With --image: the detector's score a face needs (default 2.0; lower finds more
    /// faces, and more false ones).
    #[arg(long, default_value_t = 2.0, allow_negative_numbers = true)]
    detector_score: f64,
    /// With --image: the photo's focal length in its pixels (principal point at its
    /// centre); the pose is then in that camera's metres. Default: the demo's camera.
    #[arg(long)]
    focal_px: Option<f64>,
    /// With --image: the photo's horizontal field of view, degrees (instead of
    /// --focal-px).
    #[arg(long)]
    fov_deg: Option<f64>,
    /// With --image: whose yaw, pitch and roll to print: official (default), wcpa, trg,
    /// 6drepnet or img2pose (docs/conventions.md).
    #[arg(long, default_value = "official", value_name = "CONVENTION")]
    angles: arkit_core::conventions::AngleConvention,
    /// With --image: also print each face's 1,220 vertices in camera space (the
    /// release's frame, metres).
    #[arg(long)]
    vertices: bool,
    /// With --image: draw each face's mesh and box on the photo into this JPEG (a folder
    /// of NAME.jpg for several photos, NAME the photo's path under the deepest folder
    /// holding them all: trip1/face.jpg and trip2/face.jpg stay apart), as the official
    /// demo's result.jpg. With --video: an .mp4 (H.264), or a folder of
    /// frame-NNNNNN.jpg (a path with no extension).
    #[arg(long, value_name = "OUT.jpg")]
    draw: Option<PathBuf>,
    /// With --image: write each face's crop as the network saw it (before
    /// normalisation) into this folder, as NAME-faceK.png.
    #[arg(long, value_name = "DIR")]
    dump_crops: Option<PathBuf>,
    /// Write each posed face's predicted mesh in camera space (the release's frame,
    /// metres) into this folder as .obj and .ply (the model's triangles and UVs), and its
    /// 68 landmarks (the topology's, kpt_ind.npy for the release) as .landmarks.json: 3D
    /// points and pixels. With --image: NAME-faceK.*. With --video:
    /// frame-NNNNNN-track-K.* for each frame and track posed, the mesh at the smoothed
    /// pose (the raw one with --no-smooth); about 300 kB a face a frame (--mesh-every N
    /// keeps every Nth frame).
    #[arg(long, value_name = "DIR")]
    mesh: Option<PathBuf>,
    /// With --model: exit with status 1 if any sample's image could not be read (the
    /// predictions of the others are still written; without it such samples are
    /// reported and left out, and `eval` counts them missing). With --image: exit 1 if
    /// any photo found in a folder was skipped (unreadable, truncated, a bad box); a
    /// photo named on the command line that cannot be posed always exits 1.
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
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0, value_parser = super::values::noise_px)]
    noise_px: f64,
    /// Share of points replaced by random image points, in [0, 1).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0, value_parser = super::values::unit_interval_open)]
    outliers: f64,
    /// Only this split (as `eval` chooses it); `all` for every sample.
    #[arg(long, default_value = "test")]
    split: String,
    /// Seed of the noise and of RANSAC.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// RANSAC reprojection threshold, pixels, in (0, 1000].
    #[arg(long, allow_negative_numbers = true, default_value_t = 8.0, value_parser = super::values::threshold_px)]
    threshold_px: f64,
    /// The predictions file to write (Parquet, schemas/predictions.json). With --image:
    /// .json or .csv (default: JSON on the standard output). With --video: .jsonl, .csv
    /// or .parquet, a row per frame and track (default: JSON lines on the standard
    /// output).
    #[arg(long)]
    output: Option<PathBuf>,
    /// Worker threads, 1..=1024 (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::values::jobs)]
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

/// A folder of frames' frames a second without `--fps`.
const FOLDER_FPS: f64 = 30.0;

/// Detector runs a track survives without its face, without `--max-missed`.
const MAX_MISSED: u32 = 2;

/// `predict --video`'s options (boxed: they are read once).
#[derive(Args, Debug)]
#[cfg_attr(not(feature = "model"), allow(dead_code))]
struct VideoOptions {
    /// With --video (a folder of frames): its frames a second, in (0, 1000].
    #[arg(long, allow_negative_numbers = true, default_value_t = FOLDER_FPS, value_parser = super::values::frame_rate)]
    fps: f64,
    /// With --video: run the detector on every Nth frame only (1: every frame), 1..=10000;
    /// the boxes are carried between, moved by each track's speed.
    #[arg(long, value_name = "N", allow_negative_numbers = true, default_value_t = 1,
          value_parser = clap::builder::RangedU64ValueParser::<u32>::new().range(1..=10_000))]
    detect_every: u32,
    /// With --video: detector runs a track survives without its face before it ends,
    /// 0..=1000.
    #[arg(long, allow_negative_numbers = true, default_value_t = MAX_MISSED,
          value_parser = clap::builder::RangedU64ValueParser::<u32>::new().range(0..=1000))]
    max_missed: u32,
    /// With --video: the One-Euro filter's cutoff at rest, Hz, in (0, 1000] (lower:
    /// smoother, more lag). Measured defaults: docs/video.md.
    #[arg(long, allow_negative_numbers = true, default_value_t = OneEuroParams::default().min_cutoff_hz, value_parser = super::values::cutoff_hz)]
    smooth_min_cutoff: f64,
    /// With --video: how fast the cutoff rises with the head's turning speed, Hz per
    /// rad/s, in [0, 1000] (higher: less lag when moving).
    #[arg(long, allow_negative_numbers = true, default_value_t = OneEuroParams::default().beta_rotation, value_parser = super::values::smoothing_beta)]
    smooth_beta: f64,
    /// With --video: how fast the cutoff rises with the head's speed, Hz per m/s, in
    /// [0, 1000].
    #[arg(long, allow_negative_numbers = true, default_value_t = OneEuroParams::default().beta_translation, value_parser = super::values::smoothing_beta)]
    smooth_beta_translation: f64,
    /// With --video: write the raw per-frame poses, unsmoothed.
    #[arg(long)]
    no_smooth: bool,
    /// With --video --mesh: write the meshes of every Nth frame only (frames 0, N, 2N,
    /// ...), 1..=10000.
    #[arg(long, value_name = "N", allow_negative_numbers = true, default_value_t = 1, requires = "mesh", requires = "video",
          value_parser = clap::builder::RangedU64ValueParser::<u32>::new().range(1..=10_000))]
    mesh_every: u32,
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

pub fn run(mut a: PredictArgs) -> Result<ExitCode> {
    let _remote = match a.dataset.take() {
        Some(d) => {
            let (dir, remote) = super::remote::dataset_folder(&d)?;
            a.dataset = Some(dir);
            remote
        }
        None => None,
    };
    let ransac = RansacParams {
        reprojection_threshold_px: a.threshold_px,
        seed: a.seed,
        ..RansacParams::default()
    };
    if a.video.is_some() {
        return run_video(&a, ransac);
    }
    if !a.image.is_empty() {
        return run_image(&a, ransac);
    }
    let image_only = [
        (!a.boxes.is_empty(), "--box"),
        (a.boxes_file.is_some(), "--boxes"),
        (a.focal_px.is_some(), "--focal-px"),
        (a.fov_deg.is_some(), "--fov-deg"),
        (a.vertices, "--vertices"),
        (a.draw.is_some(), "--draw"),
        (a.dump_crops.is_some(), "--dump-crops"),
        (a.mesh.is_some(), "--mesh"),
    ];
    if let Some((_, flag)) = image_only.iter().find(|(given, _)| *given) {
        return Err(arkit_core::Error::invalid(
            *flag,
            "is for photos: it needs --image",
        ));
    }
    let dataset = a.dataset.clone().expect("clap: --dataset or --image");
    let Some(output) = a.output.clone() else {
        return Err(arkit_core::Error::invalid(
            "--output",
            "predict --dataset writes a predictions file: give --output FILE.parquet",
        ));
    };
    let a = DatasetArgs {
        dataset,
        output,
        args: a,
    };
    if !(0.0..1.0).contains(&a.outliers) || a.noise_px < 0.0 || !a.noise_px.is_finite() {
        return Err(arkit_core::Error::invalid(
            "--noise-px/--outliers",
            "noise must be >= 0 and the outlier share in [0, 1)",
        ));
    }
    if a.dump.is_some() && a.model.is_none() {
        return Err(arkit_core::Error::invalid(
            "--dump",
            "dumps a network's inputs and outputs: it needs --model",
        ));
    }
    let manifest = arkit_data::store::Dataset::read_manifest(&a.dataset)?;
    let split = (a.split != "all").then_some(a.split.as_str());
    if a.mean_pose {
        return mean_pose(&a, split);
    }
    #[cfg(not(feature = "model"))]
    if a.model.is_some() {
        return Err(arkit_core::Error::invalid(
            "--model",
            "this arkit-tool was built without the `model` feature (candle); rebuild with default features to run a trained network",
        ));
    }
    #[cfg(feature = "model")]
    if let Some(dir) = &a.model {
        return model(&a, dir, split, &manifest, &ransac);
    }
    let options = OracleOptions {
        noise_px: a.noise_px,
        outliers: a.outliers,
        seed: a.seed,
        split: (a.split != "all").then(|| a.split.clone()),
        ransac,
    };
    let bar = super::console::progress_bar(manifest.converted as u64, "predict", "samples");
    let pool = super::setup::thread_pool(a.jobs)?;
    let targets = a.targets.clone().unwrap_or_else(|| a.dataset.clone());
    let (rows, summary) = pool.install(|| {
        pose::oracle_predictions(&a.dataset, &targets, &options, &|n| bar.inc(n as u64))
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

/// `predict --mean-pose`.
fn mean_pose(a: &DatasetArgs, split: Option<&str>) -> Result<ExitCode> {
    let (rows, summary) = pose::mean_pose_predictions(&a.dataset, Some("train"), split)?;
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
    Ok(ExitCode::SUCCESS)
}

/// `predict --model DIR --dataset`.
#[cfg(feature = "model")]
fn model(
    a: &DatasetArgs,
    dir: &std::path::Path,
    split: Option<&str>,
    manifest: &arkit_data::store::Manifest,
    ransac: &RansacParams,
) -> Result<ExitCode> {
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    let model = arkit_perspnet::load(dir, &topology)?;
    let bar = super::console::progress_bar(manifest.converted as u64, "predict", "samples");
    let targets = a.targets.clone().unwrap_or_else(|| a.dataset.clone());
    let mut dump = Vec::new();
    let (rows, summary) = arkit_perspnet::model_predictions_dump(
        &a.dataset,
        &model,
        split,
        match a.crop {
            CropChoice::Ours => RuleSet::Exact,
            CropChoice::Official => RuleSet::Official,
        },
        matches!(a.mask, MaskSource::Truth).then_some(targets.as_path()),
        a.seed,
        ransac,
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
    super::console::report_unreadable(&summary.unreadable, "predict");
    if a.strict && !summary.unreadable.is_empty() {
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}

/// `predict --dataset`'s arguments, with the dataset and the output given.
struct DatasetArgs {
    dataset: PathBuf,
    output: PathBuf,
    args: PredictArgs,
}

impl std::ops::Deref for DatasetArgs {
    type Target = PredictArgs;
    fn deref(&self) -> &PredictArgs {
        &self.args
    }
}

#[cfg(feature = "model")]
fn run_image(a: &PredictArgs, ransac: RansacParams) -> Result<ExitCode> {
    let Some(model) = a.model.as_deref() else {
        return Err(arkit_core::Error::invalid(
            "--image",
            "poses faces with a trained PerspNet: give --model DIR (models/tiny-synthetic is shipped)",
        ));
    };
    refuse_given(
        &dataset_only_flags(a),
        "is for --dataset; with --image use --dump-crops, --draw or --vertices",
    )?;
    refuse_given(
        &video_only_flags(&a.video_options),
        "is for --video (a photo has no frames, tracks or smoothing)",
    )?;
    super::predict_image::run(super::predict_image::ImageRequest {
        images: &a.image,
        model,
        resources: a.resources.as_deref(),
        boxes: &a.boxes,
        boxes_file: a.boxes_file.as_deref(),
        min_face_px: a.min_face_px,
        detector_score: a.detector_score,
        focal_px: a.focal_px,
        fov_deg: a.fov_deg,
        angles: a.angles,
        vertices: a.vertices,
        draw: a.draw.as_deref(),
        dump_crops: a.dump_crops.as_deref(),
        mesh: a.mesh.as_deref(),
        output: a.output.as_deref(),
        seed: a.seed,
        ransac,
        strict: a.strict,
        json: a.json,
    })
}

/// The options of `--dataset` alone, each with whether it was given.
#[cfg(feature = "model")]
fn dataset_only_flags(a: &PredictArgs) -> [(bool, &'static str); 4] {
    [
        (a.dump.is_some(), "--dump"),
        (a.targets.is_some(), "--targets"),
        (
            a.noise_px != 0.0 || a.outliers != 0.0,
            "--noise-px/--outliers",
        ),
        (matches!(a.mask, MaskSource::Truth), "--mask truth"),
    ]
}

/// The options of `--video` alone, each with whether it was given (its value is not
/// the default: clap cannot refuse them by `requires`, as `--video` conflicts with
/// `--image` and clap then counts it as satisfied).
#[cfg(feature = "model")]
fn video_only_flags(v: &VideoOptions) -> [(bool, &'static str); 7] {
    let euro = OneEuroParams::default();
    [
        (v.fps != FOLDER_FPS, "--fps"),
        (v.detect_every != 1, "--detect-every"),
        (v.max_missed != MAX_MISSED, "--max-missed"),
        (
            v.smooth_min_cutoff != euro.min_cutoff_hz,
            "--smooth-min-cutoff",
        ),
        (v.smooth_beta != euro.beta_rotation, "--smooth-beta"),
        (
            v.smooth_beta_translation != euro.beta_translation,
            "--smooth-beta-translation",
        ),
        (v.no_smooth, "--no-smooth"),
    ]
}

/// The first of `flags` that was given, refused with `why`.
#[cfg(feature = "model")]
fn refuse_given(flags: &[(bool, &'static str)], why: &str) -> Result<()> {
    match flags.iter().find(|(given, _)| *given) {
        Some((_, flag)) => Err(arkit_core::Error::invalid(*flag, why)),
        None => Ok(()),
    }
}

#[cfg(feature = "model")]
fn run_video(a: &PredictArgs, ransac: RansacParams) -> Result<ExitCode> {
    let video = a.video.as_deref().expect("checked by the caller");
    let Some(model) = a.model.as_deref() else {
        return Err(arkit_core::Error::invalid(
            "--video",
            "poses faces with a trained PerspNet: give --model DIR (models/tiny-synthetic is shipped)",
        ));
    };
    let photo_only = [
        (!a.boxes.is_empty(), "--box"),
        (a.vertices, "--vertices"),
        (a.dump_crops.is_some(), "--dump-crops"),
    ];
    refuse_given(
        &[dataset_only_flags(a).as_slice(), &photo_only].concat(),
        "is not for --video (docs/video.md lists its options)",
    )?;
    super::predict_video::run(super::predict_video::VideoRequest {
        video,
        model,
        resources: a.resources.as_deref(),
        boxes_file: a.boxes_file.as_deref(),
        fps: a.video_options.fps,
        detect_every: a.video_options.detect_every,
        tracker: arkit_data::video::TrackerOptions {
            max_missed: a.video_options.max_missed,
            ..Default::default()
        },
        smooth: (!a.video_options.no_smooth).then_some(OneEuroParams {
            min_cutoff_hz: a.video_options.smooth_min_cutoff,
            beta_rotation: a.video_options.smooth_beta,
            beta_translation: a.video_options.smooth_beta_translation,
            ..OneEuroParams::default()
        }),
        min_face_px: a.min_face_px,
        detector_score: a.detector_score,
        focal_px: a.focal_px,
        fov_deg: a.fov_deg,
        angles: a.angles,
        draw: a.draw.as_deref(),
        mesh: a.mesh.as_deref(),
        mesh_every: a.video_options.mesh_every,
        output: a.output.as_deref(),
        seed: a.seed,
        ransac,
        strict: a.strict,
        json: a.json,
    })
}

#[cfg(not(feature = "model"))]
fn run_video(_: &PredictArgs, _: RansacParams) -> Result<ExitCode> {
    Err(arkit_core::Error::invalid(
        "--video",
        "this arkit-tool was built without the `model` feature (candle); rebuild with default features",
    ))
}

#[cfg(not(feature = "model"))]
fn run_image(_: &PredictArgs, _: RansacParams) -> Result<ExitCode> {
    Err(arkit_core::Error::invalid(
        "--image",
        "this arkit-tool was built without the `model` feature (candle); rebuild with default features",
    ))
}

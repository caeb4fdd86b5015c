//! `arkit-tool convert` and `arkit-tool merge`.

use arkit_core::Result;
use arkit_core::conventions::Camera;
use arkit_data::ingest::{self, ConvertOptions, ValidationContext};
use clap::{Args, ValueEnum};

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum InputFormat {
    /// The ARKitFace release (or synth / augment / import-arkit output).
    Arkit,
    /// The BIWI Kinect Head Pose database (hpdb/).
    Biwi,
}
use std::path::PathBuf;
use std::process::ExitCode;

/// Convert the release (or data shaped like it) into validated, sharded Parquet.
///
/// Reads the download layout (ARKitFace_image_{split}/image/..., ARKitFace_info_{split}/info/...,
/// ARKitFace_list/list/*.csv) or the flat one (image/, info/, one CSV). Every sample is
/// validated (annotation keys, shapes and values, R_t, the JPEG decodes, landmarks land
/// inside the image); a bad sample is skipped and recorded with its reason in
/// errors/part-K.parquet, and files no list names in errors/listing.parquet.
/// Writes samples/part-K.parquet and dataset.json (counts, shards, SHA-256 checksums).
/// A rerun of the same conversion keeps finished shards; a folder holding another
/// conversion is refused (--overwrite replaces it). The output is byte-identical
/// whatever --jobs.
///
/// With --format biwi, --input is the BIWI Kinect Head Pose database's hpdb/ folder
/// (01/frame_00003_rgb.png, 01/frame_00003_pose.txt, 01/rgb.cal, 01.obj, ...): each
/// posed frame is first written as a release sample into --staging (pose in the RGB
/// camera, OpenGL axes, metres, row-vector R_t; image resampled into the release camera;
/// verts = the sequence's own head mesh), then converted as above with the BIWI head's
/// topology. Images without a pose file are listed, not guessed. See docs/biwi.md.
///
/// When one check skips more than half of the first 1,000 samples, the input is in
/// another convention rather than full of bad samples: convert stops with the check's
/// name and what to do (--skip-check points2d, or fix the input; --allow-systematic-skips
/// to skip them one by one instead). See docs/convert.md, "Systematic refusals".
///
/// Example: arkit-tool convert --input data/synth --output data/synth-parquet
/// Example: arkit-tool convert --format biwi --input BIWI/hpdb --output data/biwi-pq
/// Cluster: run `convert --shard I/N` for I in 0..N (same --output), then `arkit-tool merge`.
#[derive(Args, Debug)]
pub struct ConvertArgs {
    /// The release folder (or, with --format biwi, BIWI's hpdb folder).
    #[arg(long)]
    input: PathBuf,
    /// What --input holds: the ARKitFace release layout, or the BIWI database.
    #[arg(long, value_enum, default_value = "arkit")]
    format: InputFormat,
    /// With --format biwi: where the frames are written in the release's layout
    /// (default: OUTPUT/biwi-release).
    #[arg(long)]
    staging: Option<PathBuf>,
    /// With --format biwi: side of the square images written into the release camera,
    /// 32..=16384 (the official preprocessing uses 800).
    #[arg(long, allow_negative_numbers = true, default_value_t = 800, value_parser = clap::value_parser!(u32).range(32..=16384))]
    biwi_size: u32,
    /// Output folder (samples/, errors/, dataset.json).
    #[arg(long)]
    output: PathBuf,
    /// Release resource folder (triangles.npy, kpt_ind.npy, ...; projection_matrix.txt
    /// if present). Needed for the real release: its 68 landmark indices place the face
    /// box. Without it, the built-in synthetic topology's landmarks are used.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Rows per Parquet shard, 1..=100000 (memory is bounded by one shard).
    #[arg(long, allow_negative_numbers = true, default_value_t = 4096, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100_000))]
    rows_per_shard: usize,
    /// Worker threads, 1..=1024 (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::values::jobs)]
    jobs: Option<usize>,
    /// Store each JPEG's bytes in the samples table.
    #[arg(long)]
    embed_images: bool,
    /// Convert only part I of N (shards k with k % N == I), for job arrays.
    #[arg(long, value_name = "I/N", value_parser = super::values::parse_shard)]
    shard: Option<(usize, usize)>,
    /// Replace the output of another conversion found in --output (its samples, errors,
    /// manifests, splits and targets) instead of refusing. Without it, a folder that
    /// holds a conversion of other input or options is refused, and a rerun of the same
    /// conversion keeps its finished shards.
    #[arg(long)]
    overwrite: bool,
    /// Exit with status 1 if any sample was skipped (after converting everything else);
    /// with --format biwi also if a frame had no pose file or a sequence was skipped.
    #[arg(long)]
    strict: bool,
    /// Turn a per-sample check off (repeatable). `points2d`: the annotation's points2d
    /// must lie on verts projected at R_t into the image; turn it off when a release
    /// stores points2d in another convention (the pose and image are still checked
    /// against each other by the 68 landmarks). Other checks cannot be turned off: a
    /// sample that fails them would be wrong.
    #[arg(long, value_enum, value_name = "NAME")]
    skip_check: Vec<SkipCheck>,
    /// Do not stop when one check skips more than half of the first 1,000 samples (the
    /// sign of an input in another convention; the message names the check and what to
    /// do): skip them one by one, each reported. Inputs of fewer than 1,000 samples are
    /// never stopped.
    #[arg(long)]
    allow_systematic_skips: bool,
    /// The systematic rule's window (tests).
    #[arg(long, hide = true, default_value_t = arkit_data::ingest::SYSTEMATIC_WINDOW)]
    systematic_window: usize,
    /// Print the manifest as JSON.
    #[arg(long)]
    json: bool,
}

/// A check `--skip-check` turns off.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum SkipCheck {
    /// The annotation's points2d against verts at R_t projected into the image.
    Points2d,
}

impl ConvertArgs {
    fn window(&self) -> usize {
        if self.allow_systematic_skips {
            0
        } else {
            self.systematic_window
        }
    }
}

pub fn run(a: ConvertArgs) -> Result<ExitCode> {
    if a.format == InputFormat::Biwi {
        return run_biwi(a);
    }
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    let projection = match &a.resources {
        Some(dir) if dir.join("projection_matrix.txt").exists() => {
            Camera::read_projection_txt(&dir.join("projection_matrix.txt"))?
        }
        _ => Camera::release_projection(),
    };
    if a.resources.is_none() && a.format == InputFormat::Arkit {
        eprintln!(
            "note: no --resources: landmarks and face boxes use the built-in synthetic topology (right for `synth` data, not for the real release)"
        );
    }
    convert_with(a, topology, projection, None)
}

/// `convert --format biwi`: stage the frames in the release layout, then convert.
fn run_biwi(a: ConvertArgs) -> Result<ExitCode> {
    if a.resources.is_some() {
        return Err(arkit_core::Error::invalid(
            "--resources",
            "not used with --format biwi (the BIWI head mesh is the topology)",
        ));
    }
    if a.shard.is_some() {
        return Err(arkit_core::Error::invalid(
            "--shard",
            "not used with --format biwi (BIWI's 15,678 frames convert on one machine)",
        ));
    }
    let staging = a
        .staging
        .clone()
        .unwrap_or_else(|| a.output.join("biwi-release"));
    let total = arkit_data::ingest::biwi::count_frames(&a.input);
    let bar = super::console::progress_bar(total as u64, "biwi", "frames");
    let pool = super::setup::thread_pool(a.jobs)?;
    let (summary, topology) = pool.install(|| {
        arkit_data::ingest::biwi::stage_with(&a.input, &staging, a.biwi_size, a.window(), &|| {
            bar.inc(1)
        })
    })?;
    bar.finish_and_clear();
    eprintln!(
        "BIWI: {} sequences, {} frames, {} staged in {} ({} without a pose file, {} problems; head mesh of {} vertices)",
        summary.sequences,
        summary.frames_found,
        summary.staged,
        staging.display(),
        summary.without_pose.len(),
        summary.problems.len(),
        summary.vertex_count
    );
    for f in summary.without_pose.iter().take(10) {
        eprintln!("  no pose file for {f}: not converted");
    }
    if summary.without_pose.len() > 10 {
        eprintln!(
            "  ... and {} more without a pose",
            summary.without_pose.len() - 10
        );
    }
    for p in summary.problems.iter().take(10) {
        eprintln!("  {}: {}", p.file, p.reason);
    }
    let mut a = a;
    a.input = staging;
    let strict_fail = a.strict && !(summary.problems.is_empty() && summary.without_pose.is_empty());
    let code = convert_with(a, topology, Camera::release_projection(), Some(&summary))?;
    if strict_fail {
        return Ok(ExitCode::from(1));
    }
    Ok(code)
}

fn convert_with(
    a: ConvertArgs,
    topology: arkit_data::mesh::FaceTopology,
    projection: nalgebra::Matrix4<f64>,
    biwi: Option<&arkit_data::ingest::biwi::StageSummary>,
) -> Result<ExitCode> {
    let (shard_index, shard_count) = a.shard.unwrap_or((0, 1));
    let options = ConvertOptions {
        input: a.input.clone(),
        output: a.output.clone(),
        resources: a.resources.clone(),
        rows_per_shard: a.rows_per_shard,
        embed_images: a.embed_images,
        shard_index,
        shard_count,
        overwrite: a.overwrite,
    };
    let ctx = ValidationContext {
        projection,
        topology,
        embed_images: a.embed_images,
    };
    let checks = ingest::ConvertChecks {
        skip: a
            .skip_check
            .iter()
            .map(|c| match c {
                SkipCheck::Points2d => arkit_data::ingest::Check::Points2d,
            })
            .collect(),
        window: a.window(),
    };
    let input = ingest::discover(&a.input)?;
    let plan = ingest::plan_rows(&input)?;
    let rows = &plan.0;
    eprintln!(
        "found the {} layout in {}: {} listed samples in {}",
        match input.kind {
            arkit_data::store::LayoutKind::Download => "download",
            arkit_data::store::LayoutKind::Flat => "flat",
        },
        a.input.display(),
        rows.len(),
        input
            .lists
            .iter()
            .map(|(s, _)| s.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    );
    let bar = super::console::progress_bar(rows.len() as u64, "convert", "samples");
    let pool = super::setup::thread_pool(a.jobs)?;
    let manifest = pool.install(|| {
        ingest::convert_planned_with(&options, &ctx, &checks, &input, plan, &|n| {
            bar.inc(n as u64)
        })
    })?;
    bar.finish_and_clear();
    if a.json {
        match biwi {
            None => println!("{}", serde_json::to_string_pretty(&manifest).expect("json")),
            Some(b) => println!(
                "{}",
                serde_json::to_string_pretty(&serde_json::json!({"biwi": b, "manifest": manifest}))
                    .expect("json")
            ),
        }
    }
    let manifest_file = a
        .output
        .join(ingest::manifest_name(shard_index, shard_count));
    eprintln!(
        "converted {} samples, skipped {} (reasons in {}), {} listing problems; manifest {}",
        manifest.converted,
        manifest.skipped,
        a.output.join("errors").display(),
        manifest.listing_problems,
        manifest_file.display()
    );
    if a.strict && (manifest.skipped > 0 || manifest.listing_problems > 0) {
        return Ok(ExitCode::from(1));
    }
    Ok(ExitCode::SUCCESS)
}

/// Join the parts of a `convert --shard I/N` run into dataset.json.
///
/// Reads exactly the part manifests the conversion names,
/// manifest/part-IIII-of-NNNN.json for I in 0..N, each checked against conversion.json
/// (the conversion's fingerprint) and against its name. Other files in manifest/ (a
/// copy such as `part-0000-of-0002 (copy).json`) are not read: they are listed on
/// stderr and left alone. Fails, naming the file, when a part is missing, renamed or
/// of another conversion, when parts of two different N are there, when a shard is in
/// two parts or in none, or when a sample key is in two shards.
///
/// Example: arkit-tool merge --dataset data/parquet
#[derive(Args, Debug)]
pub struct MergeArgs {
    /// The output folder all parts wrote to.
    #[arg(long)]
    dataset: PathBuf,
}

pub fn run_merge(a: MergeArgs) -> Result<ExitCode> {
    let merged = ingest::merge(&a.dataset)?;
    for path in &merged.ignored {
        eprintln!(
            "ignored {}: not a part manifest's name (part-IIII-of-NNNN.json), not read",
            path.display()
        );
    }
    let m = &merged.manifest;
    println!(
        "merged {} shards: {} samples converted, {} skipped -> {}",
        m.shards.len(),
        m.converted,
        m.skipped,
        a.dataset.join(arkit_data::store::MANIFEST_FILE).display()
    );
    Ok(ExitCode::SUCCESS)
}

//! `arkit-tool augment`.

use arkit_core::Result;
use arkit_data::augment::{AugmentOptions, AxisChoice, ProfilingRule};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Enlarge the pose range: face profiling to +/-90 degrees, roll, and mirroring.
///
/// Profiling turns a face out of plane through its mesh (yaw or pitch): the mesh, four
/// rings around its contour and fixed anchors on a box and the image border are
/// triangulated, and the image is re-rendered at the new pose with a depth test, so the
/// face, the hair and the background near it move together while the rest of the
/// image stays. Roll rotates the image about its centre; --flip mirrors image, mesh
/// (vertex i stays the same anatomical point) and pose. The new verts, R_t,
/// euler_angles, translation, points2d and the other keys are written consistently in
/// the release's layout with list CSVs, ready for `convert` and the official loader.
///
/// Which samples and how much (--axis auto): yaw is enlarged for faces already turned
/// (|yaw| >= 20, |pitch| <= 25), pitch for moderately pitched near-frontal ones
/// (8..25 or -35..-20, |yaw| <= 15), roll for any; by 5 to 30 degrees away from zero,
/// never past --max-angle. docs/augment.md gives the probabilities.
///
/// Example: arkit-tool augment --input data/pq --output data/aug --per-sample 2 --flip --preview aug.png
#[derive(Args, Debug)]
pub struct AugmentArgs {
    /// A folder written by `convert` (images are read from the input it names, or from
    /// the Parquet when converted with --embed-images).
    #[arg(long)]
    input: PathBuf,
    /// Output root; the release's download layout is written under it.
    #[arg(long)]
    output: PathBuf,
    /// Which axis: auto (the rule), or always yaw, pitch or roll.
    #[arg(long, value_enum, default_value = "auto")]
    axis: AxisChoice,
    /// No angle goes past +/- this (degrees), in (0, 90].
    #[arg(long, allow_negative_numbers = true, default_value_t = 90.0, value_parser = super::values::degrees_up_to_90)]
    max_angle: f64,
    /// Smallest change (degrees), in (0, 90]; at most --max-change and --max-angle.
    #[arg(long, allow_negative_numbers = true, default_value_t = 5.0, value_parser = super::values::degrees_up_to_90)]
    min_change: f64,
    /// Largest change (degrees), in (0, 90].
    #[arg(long, allow_negative_numbers = true, default_value_t = 30.0, value_parser = super::values::degrees_up_to_90)]
    max_change: f64,
    /// Augmentations drawn per sample, 0..=100 (0: only --flip and/or
    /// --with-originals).
    #[arg(long, allow_negative_numbers = true, default_value_t = 1, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(0..=100))]
    per_sample: usize,
    /// Also write a mirrored copy of every sample.
    #[arg(long)]
    flip: bool,
    /// Also write the original samples (a complete training set in one folder).
    #[arg(long)]
    with_originals: bool,
    /// Seed of every random draw.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// JPEG quality of the written images, 1..=100.
    #[arg(long, allow_negative_numbers = true, default_value_t = 95, value_parser = clap::value_parser!(u8).range(1..=100))]
    jpeg_quality: u8,
    /// Write a PNG grid of originals beside their augmentations, meshes drawn.
    #[arg(long)]
    preview: Option<PathBuf>,
    /// The release's resource folder (real topology); the built-in face without it.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Worker threads, 1..=1024 (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::values::jobs)]
    jobs: Option<usize>,
    /// Exit with status 1 if any source sample could not be read (after augmenting
    /// everything else).
    #[arg(long)]
    strict: bool,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: AugmentArgs) -> Result<ExitCode> {
    let options = AugmentOptions {
        output: a.output.clone(),
        axis: a.axis,
        rule: ProfilingRule {
            min_change: a.min_change,
            max_change: a.max_change,
            max_angle: a.max_angle,
            ..ProfilingRule::default()
        },
        per_sample: a.per_sample,
        flip: a.flip,
        with_originals: a.with_originals,
        seed: a.seed,
        jpeg_quality: a.jpeg_quality,
        preview_pairs: if a.preview.is_some() { 6 } else { 0 },
    };
    // Every check between options, before anything is read.
    options.validate()?;
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    let manifest = arkit_data::store::Dataset::read_manifest(&a.input)?;
    let bar = super::console::progress_bar(manifest.converted as u64, "augment", "samples");
    let pool = super::setup::thread_pool(a.jobs)?;
    let (summary, previews) = pool.install(|| {
        arkit_data::augment::augment_dataset(&a.input, &topology, &options, &|n| bar.inc(n as u64))
    })?;
    bar.finish_and_clear();
    if let Some(path) = &a.preview {
        let cells: Vec<image::RgbImage> = previews.into_iter().flat_map(|(o, n)| [o, n]).collect();
        let sheet = arkit_data::picture::contact_sheet(&cells, 4, 320);
        arkit_core::atomic_file::write_bytes(path, &arkit_data::eval::png_bytes(&sheet)?)?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
    } else {
        let count = |op: &str| summary.written.iter().filter(|w| w.operation == op).count();
        println!(
            "{} sources -> {} samples written to {} (yaw {}, pitch {}, roll {}, flip {}, originals {}); {} skipped, {} left alone by the rule",
            summary.sources,
            summary.written.len(),
            a.output.display(),
            count("yaw"),
            count("pitch"),
            count("roll"),
            count("flip"),
            count("original"),
            summary.skipped.len(),
            summary.not_chosen
        );
        for (k, why) in summary.skipped.iter().take(5) {
            eprintln!("skipped {k}: {why}");
        }
        if let Some(p) = &a.preview {
            println!("wrote {}", p.display());
        }
    }
    super::console::report_unreadable(&summary.unreadable, "augment");
    if a.strict && !summary.unreadable.is_empty() {
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}

//! `arkit-tool render`.

use arkit_core::Result;
use arkit_core::conventions::Camera;
use arkit_data::crop::RuleSet;
use arkit_data::render::FaceRenderer;
use arkit_data::render::RenderOptions;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Render PerspNet's training targets for a converted dataset, once.
///
/// For each sample: the official 192x192 crop box, the face mask (eye and mouth
/// openings excluded, but they still hide what is behind them), for every face pixel the
/// visible triangle's vertex ids and perspective-correct barycentric weights (the
/// correspondence matrix row), a UV position map (one per distinct mesh), and
/// --points pixels sampled from --seed. Stored compactly in targets/part-K.parquet
/// (schemas/targets.json), row for row with samples/part-K.parquet.
///
/// A rerun keeps the shards an earlier run finished with the same options, topology
/// and dataset (targets/render.json records them with a fingerprint of the dataset's
/// samples); when targets/ holds shards made otherwise, render refuses and names what
/// differs: remove targets/, choose another --output, or pass --overwrite. Options are
/// checked before anything is written, and a run that wrote no shard does not block a
/// rerun with other options. A dataset converted with --resources must be rendered
/// with --resources (the built-in face has as many vertices as the release's mesh).
///
/// Example: arkit-tool render --dataset data/pq
///          arkit-tool render --dataset data/pq --shard 3/50   (one task of a job array)
#[derive(Args, Debug)]
pub struct RenderArgs {
    /// A folder written by `convert`.
    #[arg(long)]
    dataset: PathBuf,
    /// Where to write targets/ (default: the dataset folder).
    #[arg(long)]
    output: Option<PathBuf>,
    /// Crop side in pixels, 16..=1024.
    #[arg(long, allow_negative_numbers = true, default_value_t = 192, value_parser = clap::value_parser!(u32).range(16..=1024))]
    size: u32,
    /// UV position map side in texels, 16..=512.
    #[arg(long, allow_negative_numbers = true, default_value_t = 192, value_parser = clap::value_parser!(u32).range(16..=512))]
    uv_size: u32,
    /// Pixels sampled per sample (repeated cyclically when the face has fewer),
    /// 1..=65536 and at most --size squared.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1024, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=65_536))]
    points: usize,
    /// Seed of the sampling.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The release's resource folder (real topology); the built-in face without it.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Render only part I of N (shards k with k % N == I), for job arrays: run I =
    /// 0..N with the same --output (no merge needed; the files equal a single run's).
    #[arg(long, value_name = "I/N", value_parser = super::values::parse_shard)]
    shard: Option<(usize, usize)>,
    /// Worker threads, 1..=1024 (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::values::jobs)]
    jobs: Option<usize>,
    /// Whose targets: `exact` (ours: the box around the landmarks, pixel centres, the
    /// top-left rule, perspective-correct weights, rendered at the crop's resolution) or
    /// `official` (the official loader's pipeline: its integer box and cv2 affine map,
    /// pixel corners, its rasterizer over the whole image, the mask and image warped into
    /// the crop as cv2.warpAffine does, screen-space weights).
    #[arg(long, value_enum, default_value = "exact")]
    compat: RuleSet,
    /// Also render the face mask over the whole image (`full_mask_rle`, run lengths;
    /// about 0.5 KiB more per 800x800 sample), with the same rules as the crop's.
    #[arg(long)]
    full_mask: bool,
    /// Replace targets made with other options, another topology or from another
    /// dataset (delete targets/part-*.parquet and targets/errors/part-*.parquet, then
    /// render) instead of refusing; finished shards made the same way are still kept.
    /// Not with --shard: remove the targets folder before starting the parts instead.
    #[arg(long, conflicts_with = "shard")]
    overwrite: bool,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: RenderArgs) -> Result<ExitCode> {
    let options = RenderOptions {
        size: a.size,
        uv_size: a.uv_size,
        points: a.points,
        seed: a.seed,
        output: a.output.clone().unwrap_or_else(|| a.dataset.clone()),
        shard: a.shard.unwrap_or((0, 1)),
        full_mask: a.full_mask,
    };
    // The checks between options (--points at most --size squared), before any reading.
    options.validate()?;
    let manifest = arkit_data::store::Dataset::read_manifest(&a.dataset)?;
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    arkit_data::store::check_topology(&manifest, &topology)?;
    let renderer = FaceRenderer::new(topology, Camera::release_projection())?.with_rules(a.compat);
    let (part, parts) = options.shard;
    let mine: usize = manifest
        .shards
        .iter()
        .filter(|s| s.index % parts == part)
        .map(|s| s.rows)
        .sum();
    let bar = super::console::progress_bar(mine as u64, "render", "samples");
    let pool = super::setup::thread_pool(a.jobs)?;
    let render = if a.overwrite {
        arkit_data::render::render_dataset_replacing
    } else {
        arkit_data::render::render_dataset
    };
    let summary =
        pool.install(|| render(&a.dataset, &renderer, &options, &|n| bar.inc(n as u64)))?;
    bar.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
    } else {
        println!(
            "rendered {} samples ({:?} rules) in {} shards: {:.1} KiB per sample ({} distinct meshes) -> {}",
            summary.samples - summary.skipped,
            summary.rules,
            summary.shards,
            summary.bytes_per_sample / 1024.0,
            summary.distinct_meshes,
            options.output.join("targets").display()
        );
    }
    if summary.skipped > 0 {
        eprintln!(
            "skipped {} samples that could not be rendered (all listed in {}):",
            summary.skipped,
            options.output.join("targets").join("errors").display()
        );
        for line in &summary.skipped_examples {
            eprintln!("  {line}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

//! `arkit-tool convert` and `arkit-tool merge`.

use arkit_tool::Result;
use arkit_tool::conventions::Camera;
use arkit_tool::convert::{self, ConvertOptions, ValidationContext};
use clap::Args;
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
/// Example: arkit-tool convert --input data/synth --output data/synth-parquet
/// Cluster: run `convert --shard I/N` for I in 0..N (same --output), then `arkit-tool merge`.
#[derive(Args, Debug)]
pub struct ConvertArgs {
    /// The release folder.
    #[arg(long)]
    input: PathBuf,
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
    #[arg(long, allow_negative_numbers = true, value_parser = super::jobs)]
    jobs: Option<usize>,
    /// Store each JPEG's bytes in the samples table.
    #[arg(long)]
    embed_images: bool,
    /// Convert only part I of N (shards k with k % N == I), for job arrays.
    #[arg(long, value_name = "I/N", value_parser = super::parse_shard)]
    shard: Option<(usize, usize)>,
    /// Replace the output of another conversion found in --output (its samples, errors,
    /// manifests, splits and targets) instead of refusing. Without it, a folder that
    /// holds a conversion of other input or options is refused, and a rerun of the same
    /// conversion keeps its finished shards.
    #[arg(long)]
    overwrite: bool,
    /// Exit with status 1 if any sample was skipped (after converting everything else).
    #[arg(long)]
    strict: bool,
    /// Print the manifest as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: ConvertArgs) -> Result<ExitCode> {
    let topology = super::load_topology(a.resources.as_deref())?;
    let projection = match &a.resources {
        Some(dir) if dir.join("projection_matrix.txt").exists() => {
            Camera::read_projection_txt(&dir.join("projection_matrix.txt"))?
        }
        _ => Camera::release_projection(),
    };
    if a.resources.is_none() {
        eprintln!(
            "note: no --resources: landmarks and face boxes use the built-in synthetic topology (right for `synth` data, not for the real release)"
        );
    }
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
    let input = convert::discover(&a.input)?;
    let plan = convert::plan_rows(&input)?;
    let rows = &plan.0;
    eprintln!(
        "found the {} layout in {}: {} listed samples in {}",
        match input.kind {
            convert::LayoutKind::Download => "download",
            convert::LayoutKind::Flat => "flat",
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
    let bar = super::progress_bar(rows.len() as u64, "convert", "samples");
    let pool = super::thread_pool(a.jobs)?;
    let manifest = pool.install(|| {
        convert::convert_planned(&options, &ctx, &input, plan, &|n| bar.inc(n as u64))
    })?;
    bar.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&manifest).expect("json"));
    }
    let manifest_file = a
        .output
        .join(convert::manifest_name(shard_index, shard_count));
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
/// Example: arkit-tool merge --dataset data/parquet
#[derive(Args, Debug)]
pub struct MergeArgs {
    /// The output folder all parts wrote to.
    #[arg(long)]
    dataset: PathBuf,
}

pub fn run_merge(a: MergeArgs) -> Result<ExitCode> {
    let m = convert::merge(&a.dataset)?;
    println!(
        "merged {} shards: {} samples converted, {} skipped -> {}",
        m.shards.len(),
        m.converted,
        m.skipped,
        a.dataset.join(arkit_tool::dataset::MANIFEST_FILE).display()
    );
    Ok(ExitCode::SUCCESS)
}

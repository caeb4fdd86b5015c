//! `arkit-tool crops`.

use arkit_core::Result;
use arkit_data::crop::RuleSet;
use arkit_data::loader;
use arkit_data::loader::{FaceLoader, LoaderMode, LoaderOptions};
use arkit_data::store::crop_store::WindowCodec;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Store every sample's crop pixels and mesh once, for the Python loader.
///
/// `arkit_tool.ARKitFaceDataset` otherwise decodes each sample's full-resolution JPEG
/// and reads its `_info.npz` in every epoch. With a store it reads one record per
/// sample instead: the mesh, the evaluation crop's box, and the crop pixels of a window
/// around that box, margin S/8 + 2 pixels on each side, wide enough for the training
/// jitter (centre +/- 0.15 of the face's size, scale 0.95-1.05). It decodes only what
/// the crop needs: the window's centre in evaluation, the parts a jittered box reaches
/// in training.
///
/// In evaluation the loader's crops from the store are bit for bit those it cuts from
/// the JPEG; in training the jittered crop is resampled from the window (a second
/// bilinear pass, slightly smoother; the mask, points and correspondences are the
/// same). One store serves one rule set (--compat) and one crop side (--size): about
/// 45 KiB per sample for 192 pixels and 1,220 vertices with the default codec, about
/// the size of the release's JPEGs (188.8 KiB raw).
///
/// A sample whose image or annotation cannot be read is stored without pixels and
/// listed with the reason in crops.json (the loader raises that reason for it); the
/// run goes on, and exits 1. The store is tied to the dataset: after `convert` runs
/// again the loader refuses it until `crops` runs again. Every part file and record
/// carries the dataset's fingerprint, its shard and its sample's key, checked on every
/// read in both modes: parts of another store or swapped by hand are refused by name,
/// never served as other samples.
///
/// One `crops` per store folder: the run holds its lock (.crops.lock), so a second
/// run into the same folder is refused at once; the temporaries of killed runs are
/// removed when it starts.
///
/// Example: arkit-tool crops --dataset data/pq --resources ../arkitface-resources
///          (writes data/pq/crops/exact-192/, which ARKitFaceDataset finds by itself)
#[derive(Args, Debug)]
pub struct CropsArgs {
    /// A folder written by `convert`.
    #[arg(long)]
    dataset: PathBuf,
    /// Where to write the store (default: DATASET/crops/<compat>-<size>, where the
    /// Python loader looks for it).
    #[arg(long)]
    output: Option<PathBuf>,
    /// Crop side in pixels (the loader's img_size), 16..=1024.
    #[arg(long, allow_negative_numbers = true, default_value_t = 192, value_parser = clap::value_parser!(u32).range(16..=1024))]
    size: u32,
    /// Whose box and resampling: `exact` (ours) or `official` (the official loader's
    /// integer box and cv2.warpAffine), as the loader's `compat`.
    #[arg(long, value_enum, default_value = "exact")]
    compat: RuleSet,
    /// How the windows are stored, all lossless: `pred-zstd` (the default: each pixel
    /// predicted from its neighbours, the errors compressed by zstd, the window's centre
    /// and the four parts of the ring around it apart so that a crop decodes only what
    /// it reaches; about a fifth of the raw bytes), `png` (a quarter, slower to read) or
    /// `raw` (the bytes as they are: no decoding, about four times the disk, the
    /// fastest).
    #[arg(long, value_enum, default_value = "pred-zstd")]
    codec: WindowCodec,
    /// The release's resource folder (real topology); the built-in face without it.
    /// Needed when the dataset was converted with it.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Worker threads, 1..=1024 (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::values::jobs)]
    jobs: Option<usize>,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: CropsArgs) -> Result<ExitCode> {
    let rules = a.compat;
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    let options = LoaderOptions {
        split: None,
        mode: LoaderMode::Eval,
        rules,
        img_size: a.size,
        n_pts: 1,
        seed: 0,
    };
    let loader = FaceLoader::open(&a.dataset, topology, None, options)?;
    let output = a
        .output
        .clone()
        .unwrap_or_else(|| FaceLoader::default_crop_store(&a.dataset, rules, a.size));
    let bar = super::console::progress_bar(loader.len() as u64, "crops", "samples");
    let pool = super::setup::thread_pool(a.jobs)?;
    let codec = a.codec;
    let summary = pool.install(|| {
        loader::write_crop_store_with(&loader, &output, codec, &|n| bar.inc(n as u64))
    })?;
    bar.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
    } else {
        println!(
            "stored {} of {} samples ({} rules, {}x{} crops in {}x{} {} windows): {:.1} KiB per sample, {:.1} MiB -> {}",
            summary.samples - summary.missing,
            summary.samples,
            summary.rules,
            summary.img_size,
            summary.img_size,
            summary.window,
            summary.window,
            summary.codec.name(),
            summary.bytes_per_sample / 1024.0,
            summary.bytes as f64 / (1024.0 * 1024.0),
            summary.output.display()
        );
    }
    if summary.missing > 0 {
        eprintln!(
            "{} samples stored without pixels (listed with the reason in {}):",
            summary.missing,
            summary.output.join("crops.json").display()
        );
        for line in &summary.missing_examples {
            eprintln!("  {line}");
        }
        return Ok(ExitCode::from(1));
    }
    Ok(ExitCode::SUCCESS)
}

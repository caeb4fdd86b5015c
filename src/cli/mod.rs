//! Argument parsing and dispatch. Subcommand files parse, call the library, report
//! progress and errors; they hold no geometry.

mod augment;
mod clean;
mod convert;
mod crops;
#[cfg(feature = "model")]
mod demo;
mod eval;
#[cfg(feature = "model")]
mod export_onnx;
mod import_arkit;
mod info;
mod inspect;
mod predict;
#[cfg(feature = "model")]
mod predict_image;
#[cfg(feature = "model")]
mod predict_video;
mod push;
mod remote;
mod render;
mod split;
mod synth;
mod topology;
#[cfg(feature = "model")]
mod train;
#[cfg(feature = "model")]
mod weights;

use arkit_core::Result;
use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// Fast, validated tooling for the ARKitFace 6DoF face-pose dataset.
///
/// Conventions (see the README): poses are the release's row-vector `R_t`
/// (`[x y z 1] @ R_t`, tz < 0), Euler angles are SciPy's `as_euler('yxz')` of
/// `R_t[:3,:3]^T` in degrees, images are projected with the release's OpenGL matrix and
/// y flip, and pixel (i, j) has its centre at (i + 0.5, j + 0.5).
#[derive(Parser, Debug)]
#[command(name = "arkit-tool", version, about, long_about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    #[cfg(feature = "model")]
    Demo(demo::DemoArgs),
    Synth(synth::SynthArgs),
    Convert(convert::ConvertArgs),
    ImportArkit(import_arkit::ImportArkitArgs),
    Merge(convert::MergeArgs),
    Split(split::SplitArgs),
    Inspect(inspect::InspectArgs),
    Render(render::RenderArgs),
    Crops(crops::CropsArgs),
    #[cfg(feature = "model")]
    Train(train::TrainArgs),
    #[cfg(feature = "model")]
    ImportWeights(weights::ImportWeightsArgs),
    #[cfg(feature = "model")]
    ExportWeights(weights::ExportWeightsArgs),
    #[cfg(feature = "model")]
    HalfModel(weights::HalfModelArgs),
    #[cfg(feature = "model")]
    ExportOnnx(export_onnx::ExportOnnxArgs),
    Predict(Box<predict::PredictArgs>),
    Eval(eval::EvalArgs),
    Push(push::PushArgs),
    Clean(clean::CleanArgs),
    Augment(augment::AugmentArgs),
    Topology(topology::TopologyArgs),
    Info(info::InfoArgs),
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        #[cfg(feature = "model")]
        Command::Demo(a) => demo::run(a),
        Command::Synth(a) => synth::run(a),
        Command::Convert(a) => convert::run(a),
        Command::ImportArkit(a) => import_arkit::run(a),
        Command::Merge(a) => convert::run_merge(a),
        Command::Split(a) => split::run(a),
        Command::Inspect(a) => inspect::run(a),
        Command::Render(a) => render::run(a),
        Command::Crops(a) => crops::run(a),
        #[cfg(feature = "model")]
        Command::Train(a) => train::run(a),
        #[cfg(feature = "model")]
        Command::ImportWeights(a) => weights::run_import(a),
        #[cfg(feature = "model")]
        Command::ExportWeights(a) => weights::run_export(a),
        #[cfg(feature = "model")]
        Command::HalfModel(a) => weights::run_half(a),
        #[cfg(feature = "model")]
        Command::ExportOnnx(a) => export_onnx::run(a),
        Command::Predict(a) => predict::run(*a),
        Command::Eval(a) => eval::run(a),
        Command::Push(a) => push::run(a),
        Command::Clean(a) => clean::run(a),
        Command::Augment(a) => augment::run(a),
        Command::Topology(a) => topology::run(a),
        Command::Info(a) => info::run(a),
    }
}

/// Parses `WxH` (each side 32..=8192 pixels, as `synth` draws them).
pub fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("'{s}' is not WIDTHxHEIGHT (for example 800x800)"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("'{v}' in '{s}' is not a whole number of pixels"))
    };
    let (w, h) = (parse(w)?, parse(h)?);
    if !(32..=8192).contains(&w) || !(32..=8192).contains(&h) {
        return Err(format!("{w}x{h} is outside 32..8192 pixels a side"));
    }
    Ok((w, h))
}

/// Parses `--shard I/N` (0 <= I < N, N <= 100000).
pub fn parse_shard(s: &str) -> std::result::Result<(usize, usize), String> {
    let (i, n) = s
        .split_once('/')
        .ok_or_else(|| format!("'{s}' is not I/N (for example 0/8)"))?;
    let (i, n): (usize, usize) = (
        i.trim()
            .parse()
            .map_err(|_| format!("'{i}' is not a number"))?,
        n.trim()
            .parse()
            .map_err(|_| format!("'{n}' is not a number"))?,
    );
    if n == 0 || i >= n {
        return Err(format!("shard {i}/{n}: need 0 <= I < N"));
    }
    if n > 100_000 {
        return Err(format!("shard {i}/{n}: N is at most 100000"));
    }
    Ok((i, n))
}

/// A float in a range, for options: `lo`/`hi` with whether each end is included.
/// The error names the range (clap adds the option's name and value).
fn float_in(s: &str, lo: f64, lo_in: bool, hi: f64, hi_in: bool) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("'{s}' is not a number"))?;
    let above = if lo_in { v >= lo } else { v > lo };
    let below = if hi_in { v <= hi } else { v < hi };
    if v.is_finite() && above && below {
        Ok(v)
    } else {
        Err(format!(
            "must be in {}{lo}, {hi}{}",
            if lo_in { '[' } else { '(' },
            if hi_in { ']' } else { ')' }
        ))
    }
}

/// A share in [0, 1] (`--lr-hold`, `--test-fraction`, `--colour-jitter`).
pub fn unit_interval(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, true, 1.0, true)
}

/// A share in [0, 1) (`--outliers`: some points must stay).
pub fn unit_interval_open(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, true, 1.0, false)
}

/// A share strictly inside (0, 1) (`split --test-fraction`: both sides non-empty).
pub fn open_unit_interval(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, false, 1.0, false)
}

/// A learning rate in (0, 1].
#[cfg(feature = "model")]
pub fn learning_rate(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, false, 1.0, true)
}

/// An angle in degrees in (0, 90] (`augment --max-angle`, `--min-change`, `--max-change`).
pub fn degrees_up_to_90(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, false, 90.0, true)
}

/// A pixel noise level in [0, 100].
pub fn noise_px(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, true, 100.0, true)
}

/// A pixel threshold in (0, 1000].
pub fn threshold_px(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, false, 1000.0, true)
}

/// `--jobs`: 1..=1024 worker threads.
pub fn jobs(s: &str) -> Result<usize, String> {
    let n: usize = s
        .trim()
        .parse()
        .map_err(|_| format!("'{s}' is not a whole number"))?;
    if (1..=1024).contains(&n) {
        Ok(n)
    } else {
        Err("must be in 1..=1024 (leave --jobs out for all cores)".into())
    }
}

/// Reads the topology named by `--resources` (or the built-in face without it).
pub fn load_topology(
    resources: Option<&std::path::Path>,
) -> Result<arkit_data::mesh::FaceTopology> {
    match resources {
        Some(dir) => arkit_data::mesh::FaceTopology::from_resources(dir),
        None => Ok(arkit_data::mesh::builtin().topology.clone()),
    }
}

/// A progress bar for `len` items of `label` work (`{label} [=====>   ] 10/200 ...`).
pub fn progress_bar(len: u64, label: &str, unit: &str) -> indicatif::ProgressBar {
    indicatif::ProgressBar::new(len).with_style(
        indicatif::ProgressStyle::with_template(&format!(
            "{{spinner}} {label} [{{bar:30}}] {{pos}}/{{len}} {unit} {{per_sec}} eta {{eta}}"
        ))
        .expect("valid progress template")
        .progress_chars("=> "),
    )
}

/// A rayon pool of `jobs` threads (all cores when `None`; `--jobs` is 1..=1024).
pub fn thread_pool(jobs: Option<usize>) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(jobs.unwrap_or(0))
        .build()
        .map_err(|e| arkit_core::Error::invalid("--jobs", e.to_string()))
}

/// Prints, on stderr, how many samples a command could not read and why (the first
/// ten, each naming its file), so a moved release or a damaged image is never silent.
pub fn report_unreadable(unreadable: &[(arkit_core::SampleKey, String)], command: &str) {
    if unreadable.is_empty() {
        return;
    }
    eprintln!(
        "{command}: skipped {} sample(s) whose image or annotation could not be read:",
        unreadable.len()
    );
    for (key, why) in unreadable.iter().take(10) {
        eprintln!("  {key}: {why}");
    }
    if unreadable.len() > 10 {
        eprintln!("  ... and {} more", unreadable.len() - 10);
    }
}

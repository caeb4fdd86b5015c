//! Argument parsing and dispatch. Subcommand files parse, call the library, report
//! progress and errors; they hold no geometry.

mod augment;
mod convert;
mod demo;
mod eval;
mod info;
mod inspect;
mod predict;
mod render;
mod split;
mod synth;
mod topology;
mod train;

use arkit_tool::Result;
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
    Demo(demo::DemoArgs),
    Synth(synth::SynthArgs),
    Convert(convert::ConvertArgs),
    Merge(convert::MergeArgs),
    Split(split::SplitArgs),
    Inspect(inspect::InspectArgs),
    Render(render::RenderArgs),
    Train(train::TrainArgs),
    Predict(predict::PredictArgs),
    Eval(eval::EvalArgs),
    Augment(augment::AugmentArgs),
    Topology(topology::TopologyArgs),
    Info(info::InfoArgs),
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Demo(a) => demo::run(a),
        Command::Synth(a) => synth::run(a),
        Command::Convert(a) => convert::run(a),
        Command::Merge(a) => convert::run_merge(a),
        Command::Split(a) => split::run(a),
        Command::Inspect(a) => inspect::run(a),
        Command::Render(a) => render::run(a),
        Command::Train(a) => train::run(a),
        Command::Predict(a) => predict::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Augment(a) => augment::run(a),
        Command::Topology(a) => topology::run(a),
        Command::Info(a) => info::run(a),
    }
}

/// Parses `WxH`.
pub fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("'{s}' is not WIDTHxHEIGHT (for example 800x800)"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("'{v}' in '{s}' is not a whole number of pixels"))
    };
    Ok((parse(w)?, parse(h)?))
}

/// Parses `--shard I/N` (0 <= I < N).
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
    Ok((i, n))
}

/// Reads the topology named by `--resources` (or the built-in face without it).
pub fn load_topology(resources: Option<&std::path::Path>) -> Result<arkit_tool::FaceTopology> {
    match resources {
        Some(dir) => arkit_tool::FaceTopology::from_resources(dir),
        None => Ok(arkit_tool::synthetic_face::builtin().topology.clone()),
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

/// A rayon pool of `jobs` threads (all cores when `None`).
pub fn thread_pool(jobs: Option<usize>) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(jobs.unwrap_or(0))
        .build()
        .map_err(|e| arkit_tool::Error::invalid("--jobs", e.to_string()))
}

/// Prints, on stderr, how many samples a command could not read and why (the first
/// ten, each naming its file), so a moved release or a damaged image is never silent.
pub fn report_unreadable(unreadable: &[(arkit_tool::release::SampleKey, String)], command: &str) {
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

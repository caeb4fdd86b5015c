//! Argument parsing and dispatch: this file only names the subcommands and runs the one
//! asked for. Each subcommand file parses its options, calls the library, reports
//! progress and errors, and holds no geometry; what they share they import from
//! `values` (option parsers), `console` (progress, skipped samples), `setup` (topology,
//! threads, network settings) and `remote` (a dataset named by URL).

mod augment;
mod clean;
mod console;
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
mod setup;
mod split;
mod synth;
mod topology;
#[cfg(feature = "model")]
mod train;
mod values;
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

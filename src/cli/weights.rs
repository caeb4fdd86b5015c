//! `import-weights` and `export-weights`: the network's weights to and from PyTorch.

use arkit_core::Result;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Read a PyTorch state_dict of the official PerspNet into a model folder.
///
/// FILE is what `torch.save(net.state_dict(), FILE)` writes (PyTorch's zip format, as
/// the official checkpoint `latest_net_R.pth`; a `module.` prefix from DataParallel is
/// removed), or a safetensors file written by `export-weights`. Every tensor is matched
/// by name and shape with the network of --config, the batch norms' running statistics
/// and `num_batches_tracked` included; a missing, extra or misshapen tensor is an error
/// that lists all of them, and nothing is written. The folder is read by `predict
/// --model` like one written by `train`.
///
/// The model is tied to the topology it is imported with: `predict --model` later needs
/// the same --resources (or none, for the built-in face), and says so if it is given
/// another. The official checkpoint was trained on the release's topology, so import
/// it with --resources (the folder given to `convert`); `--config paper` without
/// --resources prints a warning saying what `predict` will need. --json prints the
/// same as JSON.
///
/// The zip's pickle is read by a bounded reader of what torch.save writes for a
/// state_dict: no code from the file is run, any class or function other than
/// OrderedDict and the tensor rebuilders is refused, nesting, memo and size are
/// bounded, and an entry that is not a tensor is refused by name. Names and shapes
/// (from the pickle, or a safetensors header) are checked before any tensor is read.
///
/// Example: arkit-tool import-weights checkpoint/run1/latest_net_R.pth --config paper --resources ../shared/arkitface-resources --output official-model/
#[derive(Args, Debug)]
pub struct ImportWeightsArgs {
    /// The state_dict file (torch.save zip or safetensors).
    file: PathBuf,
    /// The network the weights belong to: `paper` (the official shapes), `tiny`, or a
    /// JSON file of settings (as `train --config`).
    #[arg(long, default_value = "paper")]
    config: String,
    /// The model folder to write.
    #[arg(long)]
    output: PathBuf,
    /// The release's resource folder (real topology: its vertex UVs, which `predict`
    /// reads the UV map at); the built-in face without it. `predict --model` needs the
    /// same folder.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Print what was imported and what `predict` will need as JSON.
    #[arg(long)]
    json: bool,
}

/// Write a model folder's weights as the official PerspNet's PyTorch state_dict.
///
/// Writes a safetensors file with the official names and shapes (the per-point layers'
/// weights as Conv1d's `c_out x c_in x 1`) and every buffer that a strict
/// `load_state_dict` asks for, batch norm's `num_batches_tracked` included (206 entries
/// for `paper`). In Python:
///   from safetensors.torch import load_file
///   net = DeformNetUV2(grid)   # models/network.py of the official code
///   net.load_state_dict(load_file("weights.safetensors"), strict=True)
///
/// Example: arkit-tool export-weights model/ --output weights.safetensors
#[derive(Args, Debug)]
pub struct ExportWeightsArgs {
    /// A model folder written by `train` or `import-weights`.
    model: PathBuf,
    /// The safetensors file to write.
    #[arg(long)]
    output: PathBuf,
}

/// Copy a model folder with its weights stored as float16 (half the size).
///
/// Writes OUTPUT/perspnet.json and OUTPUT/loss.csv as they are and
/// OUTPUT/model.safetensors with every tensor rounded to float16. `predict --model`,
/// `eval` and `demo` read such a folder like any other (the weights are turned back
/// into float32 on load); the rounding changes each weight by at most 1 part in 2048.
/// The optimiser's state (adam.safetensors) is left out: a half model is for
/// predicting, not for `train --resume`. This is how models/tiny-synthetic was made
/// (docs/train.md).
///
/// Example: arkit-tool half-model model/ --output model-f16/
#[derive(Args, Debug)]
pub struct HalfModelArgs {
    /// A model folder written by `train` or `import-weights`.
    model: PathBuf,
    /// The model folder to write.
    #[arg(long)]
    output: PathBuf,
}

pub fn run_half(a: HalfModelArgs) -> Result<ExitCode> {
    let bytes = arkit_perspnet::write_half_model(&a.model, &a.output)?;
    eprintln!(
        "wrote {} with float16 weights ({:.2} MB)",
        a.output.display(),
        bytes as f64 / 1e6
    );
    Ok(ExitCode::SUCCESS)
}

pub fn run_import(a: ImportWeightsArgs) -> Result<ExitCode> {
    let config = super::setup::config_named(&a.config)?;
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    let c = arkit_perspnet::import_weights(&a.file, &config, &topology, &a.output)?;
    let out = a.output.display();
    let needs = match &a.resources {
        Some(r) => format!(
            "`predict --model {out}` needs --resources {} (the topology imported with)",
            r.display()
        ),
        None => format!(
            "`predict --model {out}` needs no --resources (the model is tied to the built-in stand-in face) and a dataset converted without --resources"
        ),
    };
    // The official network was trained on the release's topology: without it, the
    // model predicts with the stand-in's vertex UVs and cannot predict on the release.
    let warning = (a.config == "paper" && a.resources.is_none()).then(|| {
        format!(
            "--config paper without --resources: the model was imported with the built-in stand-in face, not the release's topology the official network was trained on, so `predict --model {out} --resources DIR` will refuse it; to predict on the release, import again with --resources DIR (the folder given to convert)"
        )
    });
    if a.json {
        let v = serde_json::json!({
            "file": a.file.display().to_string(),
            "output": out.to_string(),
            "config": a.config,
            "batch_norm_steps": c.steps,
            "topology": c.topology,
            "predict_resources": a.resources.as_ref().map(|r| r.display().to_string()),
            "predict_needs": needs,
            "warning": warning,
        });
        println!("{}", serde_json::to_string_pretty(&v).expect("json"));
    } else {
        eprintln!(
            "imported {} ({} batch-norm steps) -> {out}",
            a.file.display(),
            c.steps,
        );
        eprintln!("{needs}");
    }
    if let Some(w) = &warning {
        eprintln!("warning: {w}");
    }
    Ok(ExitCode::SUCCESS)
}

pub fn run_export(a: ExportWeightsArgs) -> Result<ExitCode> {
    let n = arkit_perspnet::export_weights(&a.model, &a.output)?;
    eprintln!("wrote {} state_dict entries -> {}", n, a.output.display());
    Ok(ExitCode::SUCCESS)
}

//! `arkit-tool export-onnx`: a trained PerspNet as ONNX graphs.

use arkit_core::{Error, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Write a trained PerspNet as ONNX (opset 17, float32, any batch size) for other runtimes.
///
/// Writes three files into OUTPUT (created if missing; each file written atomically).
/// dense.onnx: input `image` [batch, 3, S, S], the crop ImageNet-normalised; outputs
/// `seg_logits` [batch, 2, S, S], `uv_map` [batch, 3, S, S] (9 x canonical metres),
/// `image_features` and `uv_features` [batch, F, S, S]. points.onnx: inputs those three
/// maps and `choose` [batch, M] (int64 pixel indices y * S + x); outputs `assignment`
/// [batch, M, V], `points` [batch, M, 3] and `vertices` [batch, V, 3], both in 9 x
/// canonical metres. onnx.json: the config, S, M, V, the normalisation, every input and
/// output with its units, and the rule that picks `choose`.
///
/// The network is cut in two because the pixels it reads are chosen from its own
/// predicted mask by our seeded sampler, which no ONNX operator reproduces: run
/// dense.onnx, take the mask (logit 1 >= logit 0), choose M of its pixels as onnx.json
/// says, run points.onnx. In Python, arkit_tool.onnx.OnnxPerspNet(OUTPUT) does the three
/// steps with onnxruntime, without torch. With the same crop and seed, the chosen pixels
/// are `predict --model`'s and the outputs equal its `--dump` (the measured differences
/// are in docs/onnx.md). The direct baseline (`train --architecture direct`) is refused.
///
/// --resources must be the folder the model was trained or imported with (none for the
/// built-in face): points.onnx reads the UV map at that topology's vertex UVs. --json
/// prints the manifest (onnx.json) on stdout.
///
/// Example: arkit-tool export-onnx --model models/tiny-synthetic --output tiny-onnx/
///          arkit-tool export-onnx --model official-model/ --resources ../shared/arkitface-resources --output paper-onnx/
#[derive(Args, Debug)]
pub struct ExportOnnxArgs {
    /// A PerspNet model folder written by `train` or `import-weights` (with
    /// perspnet.json and model.safetensors), for example models/tiny-synthetic.
    #[arg(long)]
    model: PathBuf,
    /// The release's resource folder the model was trained or imported with (its
    /// topology's vertex UVs); the built-in face without it.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// The folder to write dense.onnx, points.onnx and onnx.json into.
    #[arg(long)]
    output: PathBuf,
    /// Print the manifest (onnx.json) as JSON on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(a: ExportOnnxArgs) -> Result<ExitCode> {
    let config = a.model.join("perspnet.json");
    if !config.is_file() {
        return Err(Error::invalid(
            "--model",
            format!(
                "{} has no perspnet.json: give a model folder written by `train` or `import-weights`",
                a.model.display()
            ),
        ));
    }
    // The config first: a direct baseline is refused before its weights are read.
    let text = std::fs::read_to_string(&config).map_err(|e| Error::io(&config, e))?;
    let checkpoint: arkit_perspnet::Checkpoint =
        serde_json::from_str(&text).map_err(|e| Error::format(&config, e.to_string()))?;
    if checkpoint.config.architecture != arkit_perspnet::Architecture::PerspNet {
        return Err(Error::invalid(
            "--model",
            format!(
                "{} holds the paper's direct baseline (\"architecture\": \"direct\" in perspnet.json), which has no mask or correspondences; export-onnx exports PerspNet models only",
                a.model.display()
            ),
        ));
    }
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    let model = arkit_perspnet::load(&a.model, &topology)?;
    let export = arkit_perspnet::export_onnx(&model, &topology, &a.output)?;
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&export.manifest).expect("json")
        );
    } else {
        let m = &export.manifest;
        eprintln!(
            "exported {} (S = {}, M = {}, V = {}, opset {}) -> {}: dense.onnx ({:.2} MB), points.onnx ({:.2} MB), onnx.json",
            a.model.display(),
            m.input_size,
            m.points,
            m.vertices,
            m.opset,
            a.output.display(),
            m.dense.bytes as f64 / 1e6,
            m.points_graph.bytes as f64 / 1e6,
        );
    }
    Ok(ExitCode::SUCCESS)
}

//! The official network's PyTorch `state_dict` into a model folder and out of one.

use crate::candle_error::candle_err;
use crate::config::{Architecture, PerspNetConfig};
use crate::model::PerspNet;
use crate::network::vertex_uv;
use crate::training::checkpoint::{
    Checkpoint, MODEL_FILES, save_renamed, verify_model, write_record,
};
use crate::training::data::Augmentation;
use crate::weights::{load_weights, open_weights};
use arkit_core::{Error, Result};
use arkit_data::mesh::FaceTopology;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use std::collections::HashMap;
use std::path::Path;

/// Reads a PyTorch `state_dict` (a `torch.save` zip, or the safetensors file
/// [`export_weights`] writes) of the official network with `config`'s shapes into a new
/// model folder `output` (`perspnet.json` and `model.safetensors`, which `predict
/// --model` reads). Every tensor must match by name and shape; otherwise nothing is
/// written and the error lists the missing, extra and misshapen ones.
pub fn import_weights(
    file: &Path,
    config: &PerspNetConfig,
    topology: &FaceTopology,
    output: &Path,
) -> Result<Checkpoint> {
    use crate::weights::state_dict::{WeightError, WeightFile};
    if config.architecture == Architecture::Direct {
        return Err(Error::invalid(
            "--config",
            "the direct baseline is not the official network: its weights have no PyTorch counterpart to import",
        ));
    }
    let weights = WeightFile::open(file).map_err(|e| Error::format(file, e.to_string()))?;
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    PerspNet::new(config, &vertex_uv(topology, &device)?, vb)
        .map_err(|e| candle_err("network", e))?;
    let steps = weights.load_into(&varmap).map_err(|e| match e {
        WeightError::Mismatch(m) => Error::format(
            file,
            format!("does not match the network of this --config: {m}"),
        ),
        WeightError::Read(m) => Error::format(file, m),
    })?;
    let checkpoint = Checkpoint {
        config: config.clone(),
        topology: topology.source.clone(),
        epochs: 0,
        batch: 0,
        learning_rate: 0.0,
        lr_hold: 1.0,
        augmentation: Augmentation::NONE,
        lowered_start: false,
        max_steps: None,
        seed: 0,
        loss_weights: None,
        epochs_done: 0,
        examples: 0,
        example_shards: 1,
        steps: steps.max(0) as usize,
        first_loss: f32::NAN,
        last_loss: f32::NAN,
        imported_from: Some(file.display().to_string()),
    };
    std::fs::create_dir_all(output).map_err(|e| Error::io(output, e))?;
    save_renamed(&output.join("model.safetensors"), &|p| varmap.save(p))?;
    let json = serde_json::to_string_pretty(&checkpoint).expect("checkpoint json");
    arkit_core::atomic_file::write_bytes(&output.join("perspnet.json"), json.as_bytes())?;
    // Last, the record of the two files: it replaces a record an earlier run left in
    // `output`, which would otherwise describe other weights.
    write_record(output, &MODEL_FILES)?;
    Ok(checkpoint)
}

/// Writes a model folder's weights as the official network's `state_dict` in a
/// safetensors file (official names and shapes, with every batch norm's
/// `num_batches_tracked`, set to the model's training steps), which PyTorch loads with
/// `load_state_dict(safetensors.torch.load_file(path), strict=True)`. Returns the
/// number of entries written.
pub fn export_weights(model_dir: &Path, output: &Path) -> Result<usize> {
    verify_model(model_dir)?;
    let p = model_dir.join("perspnet.json");
    let text = std::fs::read_to_string(&p).map_err(|e| Error::io(&p, e))?;
    let checkpoint: Checkpoint =
        serde_json::from_str(&text).map_err(|e| Error::format(&p, e.to_string()))?;
    let cfg = &checkpoint.config;
    if cfg.architecture == Architecture::Direct {
        return Err(Error::format(
            &p,
            "a direct-baseline model: the official network has no such head, so there is no state_dict to export",
        ));
    }
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    // The vertex UV table is not a weight: any table of the right size builds the network.
    let uv = crate::model::synthetic_vertex_uv(cfg.vertices, &device)
        .map_err(|e| candle_err("network", e))?;
    PerspNet::new(cfg, &uv, vb).map_err(|e| candle_err("network", e))?;
    let w = model_dir.join("model.safetensors");
    load_weights(&varmap, &mut open_weights(&w)?, &w)?;
    let entries = crate::weights::state_dict::export_state_dict(&varmap, checkpoint.steps as i64)
        .map_err(|e| candle_err("export", e))?;
    let n = entries.len();
    let map: HashMap<String, Tensor> = entries.into_iter().collect();
    if let Some(dir) = output.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        // A killed export's temporary goes.
        arkit_core::atomic_file::remove_stale_temporaries(dir, false)?;
    }
    save_renamed(output, &|p| candle_core::safetensors::save(&map, p))?;
    Ok(n)
}

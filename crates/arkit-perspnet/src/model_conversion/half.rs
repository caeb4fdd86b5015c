//! Model folders with their weights stored as float16.

use crate::candle_error::candle_err;
use crate::network::Network;
use crate::training::checkpoint::{
    Checkpoint, MODEL_FILES, save_renamed, verify_model, write_record,
};
use crate::weights::{load_weights, open_weights};
use arkit_core::{Error, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use std::collections::HashMap;
use std::path::Path;

/// Copies the model folder `model_dir` (`perspnet.json`, `model.safetensors` and
/// `loss.csv` when there is one) to `output` with its weights stored as float16: half
/// the bytes, read back as float32 by [`crate::load`] (each weight then differs from the
/// original by at most its float16 rounding, a relative 2^-11). Returns the bytes of
/// the weights file written.
pub fn write_half_model(model_dir: &Path, output: &Path) -> Result<u64> {
    verify_model(model_dir)?;
    let p = model_dir.join("perspnet.json");
    let json = std::fs::read_to_string(&p).map_err(|e| Error::io(&p, e))?;
    let checkpoint =
        serde_json::from_str::<Checkpoint>(&json).map_err(|e| Error::format(&p, e.to_string()))?;
    // The weights are read into the network of the checkpoint's config, so that their
    // names and shapes are checked before any data is read.
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    let uv = crate::model::synthetic_vertex_uv(checkpoint.config.vertices, &device)
        .map_err(|e| candle_err("network", e))?;
    Network::new(&checkpoint.config, &uv, vb).map_err(|e| candle_err("network", e))?;
    let w = model_dir.join("model.safetensors");
    load_weights(&varmap, &mut open_weights(&w)?, &w)?;
    let half = varmap
        .data()
        .lock()
        .expect("varmap lock")
        .iter()
        .map(|(k, v)| Ok((k.clone(), v.as_tensor().to_dtype(DType::F16)?)))
        .collect::<candle_core::Result<HashMap<String, Tensor>>>()
        .map_err(|e| Error::format(&w, e.to_string()))?;
    std::fs::create_dir_all(output).map_err(|e| Error::io(output, e))?;
    let out = output.join("model.safetensors");
    save_renamed(&out, &|p| candle_core::safetensors::save(&half, p))?;
    let csv = model_dir.join("loss.csv");
    let mut written = MODEL_FILES.to_vec();
    if csv.exists() {
        let text = std::fs::read(&csv).map_err(|e| Error::io(&csv, e))?;
        arkit_core::atomic_file::write_bytes(&output.join("loss.csv"), &text)?;
        written.push("loss.csv");
    }
    arkit_core::atomic_file::write_bytes(&output.join("perspnet.json"), json.as_bytes())?;
    // Last, the record of the files written (see [`crate::verify_model`]).
    write_record(output, &written)?;
    std::fs::metadata(&out)
        .map(|m| m.len())
        .map_err(|e| Error::io(&out, e))
}

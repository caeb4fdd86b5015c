//! Weight files: a model folder's `model.safetensors` read into the network
//! ([`load_weights`], float32 or float16), PyTorch `state_dict`s of the official network
//! read and written by name ([`state_dict`]), and safetensors files read without trusting
//! them ([`safetensors_file`]). The conversions of whole model folders built on them are
//! `model_conversion`'s.

pub mod safetensors_file;
pub mod state_dict;

use arkit_core::{Error, Result};
use candle_core::DType;
use candle_nn::VarMap;
use safetensors_file::SafetensorsFile;
use std::collections::HashMap;
use std::path::Path;

/// Opens the safetensors file `path` (`safetensors_file`): its header is read
/// and checked against the file's length; no tensor data is read yet.
pub fn open_weights(path: &Path) -> Result<SafetensorsFile<std::io::BufReader<std::fs::File>>> {
    if let Err(e) = std::fs::metadata(path) {
        return Err(Error::io(path, e));
    }
    safetensors_file::open(path).map_err(|e| Error::format(path, e))
}

/// Sets every variable of `varmap` from the safetensors file `st` (read from `file`,
/// which errors name), matched by name and shape and converted to float32: a model
/// folder may hold float32 weights (`train`) or float16 ones (`write_half_model`).
/// Every name, shape and type in the header is checked before any tensor is read; a
/// missing, misshapen, extra or non-float tensor is an error that names it. The
/// tensors are then read one at a time.
pub fn load_weights<R: std::io::Read + std::io::Seek>(
    varmap: &VarMap,
    st: &mut SafetensorsFile<R>,
    file: &Path,
) -> Result<()> {
    let data = varmap.data().lock().expect("varmap lock");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let header: HashMap<&str, &safetensors_file::Entry> =
        st.entries().iter().map(|e| (e.name.as_str(), e)).collect();
    for name in &names {
        let var = &data[*name];
        let e = header
            .get(name.as_str())
            .ok_or_else(|| Error::format(file, format!("no tensor {name}")))?;
        if e.shape != var.dims() {
            return Err(Error::format(
                file,
                format!("{name} is {:?}, the network has {:?}", e.shape, var.dims()),
            ));
        }
        if !matches!(e.dtype, DType::F16 | DType::BF16 | DType::F32 | DType::F64) {
            return Err(Error::format(
                file,
                format!("{name} is {:?}, not floating point", e.dtype),
            ));
        }
    }
    let mut extra: Vec<&str> = header
        .keys()
        .filter(|k| !data.contains_key(**k))
        .copied()
        .collect();
    if !extra.is_empty() {
        extra.sort();
        return Err(Error::format(
            file,
            format!("tensors the network does not have: {extra:?}"),
        ));
    }
    for name in names {
        let var = &data[name];
        let t = st
            .read(name)
            .and_then(|t| t.to_dtype(DType::F32).map_err(|e| e.to_string()))
            .map_err(|e| Error::format(file, format!("{name}: {e}")))?;
        var.set(&t)
            .map_err(|e| Error::format(file, format!("{name}: {e}")))?;
    }
    Ok(())
}

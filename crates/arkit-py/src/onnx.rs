//! `arkit_tool.onnx`: the pixels PerspNet reads, chosen from a predicted mask as
//! `predict --model` chooses them.

use crate::errors::py_err;
use arkit_core::Error;
use numpy::IntoPyArray;
use pyo3::prelude::*;

/// The pixels PerspNet reads, chosen from a predicted mask as `predict --model` chooses
/// them (`arkit_perspnet::predict_crop_raw`): the candidates are the mask's pixels in
/// flat order (every pixel when the mask is empty), and
/// `arkit_data::render::sample_points(len(candidates), m, seed)` picks `m` of
/// them (distinct, increasing, when there are more than `m`; else with wrap-around).
/// `mask`: bool, any shape, read in C order. Returns the `m` flat indices (int64).
#[pyfunction]
pub(crate) fn choose_points<'py>(
    py: Python<'py>,
    mask: numpy::PyReadonlyArrayDyn<'py, bool>,
    m: usize,
    seed: u64,
) -> PyResult<Bound<'py, numpy::PyArray1<i64>>> {
    if m == 0 || m > 1 << 20 {
        return Err(py_err(Error::invalid(
            "m",
            format!("{m} points: must be in 1..=1048576"),
        )));
    }
    let flat: Vec<bool> = mask.as_array().iter().copied().collect();
    if flat.is_empty() || flat.len() > u32::MAX as usize {
        return Err(py_err(Error::invalid(
            "mask",
            format!("{} pixels: must be in 1..=4294967295", flat.len()),
        )));
    }
    let chosen = py.detach(|| {
        let mut candidates: Vec<u32> = (0..flat.len() as u32)
            .filter(|&i| flat[i as usize])
            .collect();
        if candidates.is_empty() {
            candidates = (0..flat.len() as u32).collect();
        }
        arkit_data::render::sample_points(candidates.len(), m, seed)
            .into_iter()
            .map(|k| candidates[k as usize] as i64)
            .collect::<Vec<i64>>()
    });
    Ok(chosen.into_pyarray(py))
}

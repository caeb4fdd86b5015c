//! `arkit_tool.correspondences`: the dense correspondence matrices (the training
//! targets `corr_mat`) written from their sparse form into the caller's arrays.

use crate::errors::DataError;
use arkit_data::loader::{rewrite_correspondence_matrix, write_correspondence_matrix};
use numpy::{PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;

/// Writes the dense correspondence matrices of `ids` (..., n, 3) int64 and `weights`
/// (..., n, 3) float32 into `out` (..., n, V) float32, C-contiguous and writeable: zeros
/// but for each row's weights at its vertex columns, the later of a repeated vertex's
/// weights staying, as the official loader assigns them, without the GIL. With
/// `previous_ids` (the ids `out` was last written with, and the caller's promise that
/// nothing else has written it since) only those columns are cleared before the new
/// weights go in; otherwise every value is written. A vertex id outside `0..V` or
/// shapes that do not fit raise `DataError` before anything is written.
#[pyfunction]
#[pyo3(signature = (out, ids, weights, previous_ids=None))]
pub(crate) fn write_correspondence_matrix_into<'py>(
    py: Python<'py>,
    out: Bound<'py, PyArrayDyn<f32>>,
    ids: numpy::PyReadonlyArrayDyn<'py, i64>,
    weights: numpy::PyReadonlyArrayDyn<'py, f32>,
    previous_ids: Option<numpy::PyReadonlyArrayDyn<'py, i64>>,
) -> PyResult<()> {
    let (shape, id_shape) = (out.shape().to_vec(), ids.shape().to_vec());
    let writeable: bool = out.getattr("flags")?.getattr("writeable")?.extract()?;
    let fits = !shape.is_empty()
        && id_shape.len() == shape.len()
        && id_shape.last() == Some(&3)
        && id_shape[..id_shape.len() - 1] == shape[..shape.len() - 1]
        && weights.shape() == id_shape.as_slice()
        && previous_ids
            .as_ref()
            .is_none_or(|p| p.shape() == id_shape.as_slice());
    if !fits || !out.is_c_contiguous() || !writeable {
        return Err(DataError::new_err(format!(
            "correspondence matrix: out {shape:?}, ids {id_shape:?}, weights {:?}, previous \
             ids {:?}: expected (..., n, V) C-contiguous writeable float32 and (..., n, 3)",
            weights.shape(),
            previous_ids.as_ref().map(|p| p.shape().to_vec())
        )));
    }
    let v = shape[shape.len() - 1];
    let triples = |ids: &numpy::PyReadonlyArrayDyn<'py, i64>, what: &str| {
        let mut out = Vec::with_capacity(ids.len() / 3);
        let mut row = [0u32; 3];
        for (i, &x) in ids.as_array().iter().enumerate() {
            if x < 0 || x as usize >= v {
                return Err(DataError::new_err(format!(
                    "correspondence matrix: row {}: {what}vertex id {x} outside 0..{v}",
                    i / 3
                )));
            }
            row[i % 3] = x as u32;
            if i % 3 == 2 {
                out.push(row);
            }
        }
        Ok(out)
    };
    let vertices = triples(&ids, "")?;
    let previous = previous_ids
        .as_ref()
        .map(|p| triples(p, "previous "))
        .transpose()?;
    let mut w = Vec::with_capacity(vertices.len());
    let mut row = [0f32; 3];
    for (i, &x) in weights.as_array().iter().enumerate() {
        row[i % 3] = x;
        if i % 3 == 2 {
            w.push(row);
        }
    }
    // SAFETY: `out` was checked C-contiguous and writeable; nothing else writes it while
    // the GIL is released (the caller owns it: a buffer it made for this matrix).
    let slice = unsafe { out.as_slice_mut()? };
    py.detach(|| match &previous {
        Some(previous) => rewrite_correspondence_matrix(slice, v, previous, &vertices, &w),
        None => write_correspondence_matrix(slice, v, &vertices, &w),
    });
    Ok(())
}

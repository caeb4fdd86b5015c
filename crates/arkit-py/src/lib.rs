//! `arkit_tool._native`: the Python package's Rust core (pyo3). The Python layer
//! (`python/src/arkit_tool/`) wraps these classes and functions; users import
//! `arkit_tool`, not this module.
//!
//! What crosses the boundary:
//! - `Loader`: `arkit_data::loader::FaceLoader`, one sample as the official PyTorch
//!   loader returns it, as numpy arrays that own the Rust buffers (no copy).
//! - `Dataset`: a converted dataset's samples, by position.
//! - `solve_pnp_ransac`, `project`, `evaluate`: PnP, the release's projection and
//!   the paper's metrics; `topology`: the mesh a dataset was converted with.
//! - `poses_to_opencv`, `poses_from_arkit`, `pose_angles`, ...: the head pose in other
//!   tools' conventions (`arkit_core::conventions::AngleConvention` and `Pose`), on
//!   (N, k) float64 rows; `arkit_tool.conventions` shapes them.
//!
//! Invariants: the GIL is released while Rust works (`Python::detach`); nothing here
//! keeps a thread running (a dataset read from a bucket drives its requests on the
//! calling thread, and makes its client again in a forked child), so a loader is safe
//! to use after `fork` (DataLoader workers); every
//! error, and any panic, reaches Python as `DataError` (a `ValueError`) whose message
//! names the file and the problem, never as a Rust panic. Tested by `python/tests`.
//!
//! One module per Python module served: `dataset` (`ARKitFaceDataset`'s loader),
//! `converted` (`ConvertedDataset`, `read_image`, the topology), `geometry` (PnP,
//! projection, metrics), `photo`, `correspondences`, `conventions` and `onnx`;
//! `errors` holds what they share. This file registers them, nothing else.

mod conventions;
mod converted;
mod correspondences;
mod dataset;
mod errors;
mod geometry;
mod onnx;
mod photo;

use pyo3::prelude::*;

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<dataset::Loader>()?;
    m.add_class::<converted::Dataset>()?;
    m.add_function(wrap_pyfunction!(geometry::solve_pnp_ransac, m)?)?;
    m.add_function(wrap_pyfunction!(geometry::project, m)?)?;
    m.add_function(wrap_pyfunction!(geometry::evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(converted::read_image, m)?)?;
    m.add_function(wrap_pyfunction!(photo::read_photo_upright, m)?)?;
    m.add_function(wrap_pyfunction!(photo::photo_crop, m)?)?;
    m.add_function(wrap_pyfunction!(photo::photo_pose, m)?)?;
    m.add_function(wrap_pyfunction!(photo::detect_faces, m)?)?;
    m.add_function(wrap_pyfunction!(dataset::default_crop_store, m)?)?;
    m.add_function(wrap_pyfunction!(converted::topology, m)?)?;
    m.add_function(wrap_pyfunction!(
        correspondences::write_correspondence_matrix_into,
        m
    )?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_to_opencv, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_from_opencv, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_from_arkit, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_to_arkit, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::pose_angles, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_from_angles, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_to_trg, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_from_trg, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_to_img2pose, m)?)?;
    m.add_function(wrap_pyfunction!(conventions::poses_from_img2pose, m)?)?;
    m.add_function(wrap_pyfunction!(onnx::choose_points, m)?)?;
    m.add("DataError", m.py().get_type::<errors::DataError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}

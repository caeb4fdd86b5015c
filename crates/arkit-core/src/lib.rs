//! `arkit_core`: the parts of `arkit-tool` that need neither polars nor candle, and that
//! every reader of untrusted files goes through.
//!
//! - [`conventions`]: [`Pose`] (the release's `R_t`) and [`Camera`] (its projection).
//! - [`npy`]: NumPy `.npy` / `.npz` reading (bounded, see [`limits`]) and writing.
//! - [`release`]: the release's files: `_info.npz` annotations, list CSVs, layout.
//! - [`target_codec`]: the byte codecs of the `targets` blobs (masks as run lengths,
//!   UV-map delta planes, correspondences); [`predictions_csv`]: the predictions CSV.
//! - [`torch_pickle`]: a bounded reader of `torch.save(state_dict)` archives (no code
//!   from the file is run).
//! - [`limits`]: every bound on what the readers accept, documented in one place.
//! - [`raster`]: the CPU triangle rasterizer core.
//! - [`rng`]: the seeded random streams that make output reproducible.
//! - [`atomic_file`]: writes that never leave a half-written file.
//! - [`error`]: the one error type, naming the file and the problem.
//!
//! The fuzz targets in `fuzz/` link this crate alone, so they build in seconds.

#![deny(missing_docs)]

pub mod atomic_file;
pub mod conventions;
pub mod error;
#[doc(hidden)]
pub mod fuzz_entry;
pub mod lanes;
pub mod limits;
pub mod npy;
pub mod predictions_csv;
pub mod raster;
pub mod release;
pub mod rng;
pub mod target_codec;
pub mod torch_pickle;

pub use conventions::{Camera, EulerAngles, Pose};
pub use error::{Error, ErrorKind, Result};

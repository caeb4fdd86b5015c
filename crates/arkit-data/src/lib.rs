//! `arkit_data`: read, validate, render and synthesise data of the ARKitFace dataset
//! (Kao et al., IEEE TIP 2023), and of data shaped like it: everything of `arkit-tool`
//! but the network (`arkit-perspnet`) and the command line. Needs polars, not candle.
//!
//! Modules, one job each:
//! - [`conventions`]: [`Pose`] (the release's `R_t`, OpenCV form, Euler 'yxz') and
//!   [`Camera`] (OpenGL projection, viewport, y flip, pixel centres).
//! - [`topology`]: [`FaceTopology`]: triangles, UVs, landmarks, and what is derived from
//!   them (boundary loops, hole fills, mirror map).
//! - [`synthetic_face`]: the built-in stand-in face model (not Apple's topology).
//! - [`raster`]: the CPU triangle rasterizer core.
//! - [`crop`]: the square crop around a face and the image resampled into it (ours, and
//!   the official loader's box and `cv2.warpAffine` in [`crop::official`]).
//! - [`render`]: crops, masks, correspondences and UV position maps of one sample;
//!   [`face_targets`]: the value they produce; [`targets_table`]: their compact storage
//!   and the dense reader;
//!   [`render_dataset`]: a whole converted dataset, shard by shard.
//! - [`npy`]: NumPy `.npy` / `.npz` reading and writing.
//! - [`release`]: the release's files: `_info.npz` annotations, list CSVs, layout.
//! - [`synth`]: the synthetic dataset generator.
//! - [`convert`]: the release into validated, sharded Parquet; [`samples_table`]: the
//!   `samples` and `errors` tables; [`split`]: subject-disjoint splits; [`plot`]:
//!   charts as SVG (labelled axes, ticks, legends).
//! - [`eval`]: the paper's metrics; [`predictions_table`]: the predictions file;
//!   [`eval_dataset`]: a dataset's predictions scored, with a report.
//! - [`systematic`]: the rule that stops a run when one check skips most samples.
//! - [`biwi`]: the BIWI Kinect Head Pose database into the release's conventions.
//! - [`import_arkit`]: a user's own ARKit captures into the release's layout.
//! - [`overlay`]: meshes drawn over images; [`image_decode`]: every image read, its
//!   size checked from the header before decoding.
//! - [`pnp`]: the pose from 2D-3D correspondences (P3P + MSAC + Levenberg-Marquardt);
//!   [`predict`]: crop pixels to a release pose, and the oracle predictor.
//! - [`augment`]: face profiling, roll and mirroring of one sample;
//!   [`augment_dataset`]: the rule, the release-layout output, previews.
//! - [`rng`]: the seeded random streams that make output reproducible.
//! - [`atomic_file`]: writes that never leave a half-written file.
//! - [`manifest`]: `dataset.json` and the checks of shards and topology it carries;
//!   [`dataset`]: a converted dataset opened once: manifest, checked shards, images;
//!   [`loader`]: one sample as the official PyTorch loader returns it, on the fly;
//!   [`crop_store`]: each sample's crop pixels and mesh stored once for the loader;
//!   [`crops_dataset`]: the store of a whole dataset.
//! - [`limits`]: every bound on what the readers accept (re-exported from `arkit_core`);
//!   [`target_codec`]: the byte codecs of the `targets` blobs.

#![warn(missing_docs)]

pub mod allocator;
pub mod augment;
pub mod augment_dataset;
pub mod biwi;
pub mod colour_jitter;
pub mod convert;
pub mod crop;
pub mod crop_store;
pub mod crops_dataset;
pub mod dataset;
pub mod eval;
pub mod eval_dataset;
pub mod face_targets;
pub mod image_decode;
pub mod import_arkit;
pub mod loader;
pub mod manifest;
pub mod overlay;
pub mod plot;
pub mod pnp;
pub mod predict;
pub mod predictions_table;
pub mod render;
pub mod render_dataset;
pub mod samples_table;
pub mod split;
pub mod synth;
pub mod synthetic_face;
pub mod systematic;
pub mod targets_table;
pub mod topology;

pub use crop::official as official_crop;

pub use arkit_core::{
    atomic_file, conventions, error, limits, npy, raster, release, rng, target_codec, torch_pickle,
};
pub use conventions::{Camera, EulerAngles, Pose};
pub use error::{Error, ErrorKind, Result};
pub use topology::FaceTopology;

// The types a pipeline is written with, at the crate root.
pub use crop::{CropRule, CropSampling, CropTransform};
pub use dataset::Dataset;
pub use eval::Summary as EvalSummary;
pub use face_targets::FaceTargets;
pub use loader::{FaceLoader, LoaderItem, LoaderOptions};
pub use manifest::{Manifest, ShardEntry};
pub use pnp::{Intrinsics, PnpSolution, RansacParams};
pub use release::SampleKey;
pub use render::{FaceRenderer, UvMapper, UvTexels};
pub use samples_table::{ErrorRecord, SampleRecord};

//! `arkit_tool`: read, validate, render and synthesise data of the ARKitFace dataset
//! (Kao et al., IEEE TIP 2023), and of data shaped like it.
//!
//! The binary `arkit-tool` is a thin command-line front over this library.
//!
//! Modules, one job each:
//! - [`conventions`]: [`Pose`] (the release's `R_t`, OpenCV form, Euler 'yxz') and
//!   [`Camera`] (OpenGL projection, viewport, y flip, pixel centres).
//! - [`topology`]: [`FaceTopology`]: triangles, UVs, landmarks, and what is derived from
//!   them (boundary loops, hole fills, mirror map).
//! - [`synthetic_face`]: the built-in stand-in face model (not Apple's topology).
//! - [`raster`]: the CPU triangle rasterizer core.
//! - [`render`]: crops, masks, correspondences and UV position maps of one sample;
//!   [`targets_table`]: their compact storage and the dense reader;
//!   [`render_dataset`]: a whole converted dataset, shard by shard.
//! - [`npy`]: NumPy `.npy` / `.npz` reading and writing.
//! - [`release`]: the release's files: `_info.npz` annotations, list CSVs, layout.
//! - [`synth`]: the synthetic dataset generator.
//! - [`convert`]: the release into validated, sharded Parquet; [`samples_table`]: the
//!   `samples` and `errors` tables; [`split`]: subject-disjoint splits; [`plot`]:
//!   histogram pictures.
//! - [`eval`]: the paper's metrics; [`predictions_table`]: the predictions file;
//!   [`eval_dataset`]: a dataset's predictions scored, with a report.
//! - [`biwi`]: the BIWI Kinect Head Pose database into the release's conventions.
//! - [`import_arkit`]: a user's own ARKit captures into the release's layout.
//! - [`overlay`]: meshes drawn over images.
//! - [`pnp`]: the pose from 2D-3D correspondences (P3P + MSAC + Levenberg-Marquardt);
//!   [`predict`]: crop pixels to a release pose, and the oracle predictor.
//! - [`augment`]: face profiling, roll and mirroring of one sample;
//!   [`augment_dataset`]: the rule, the release-layout output, previews.
//! - [`perspnet`]: the reference PerspNet in candle (model, losses, config);
//!   [`training`]: examples from storage, the training loop, checkpoints.
//! - [`rng`]: the seeded random streams that make output reproducible.
//! - [`report`]: pictures of each stage and a self-contained `index.html`;
//!   [`demo`]: the whole pipeline on synthetic data, with that report.
//! - [`atomic_file`]: writes that never leave a half-written file.
//! - [`dataset`]: a converted dataset opened once: manifest, checked shards, images;
//!   [`loader`]: one sample as the official PyTorch loader returns it, on the fly.
//! - [`limits`]: every bound on what the readers accept (re-exported from `arkit_core`);
//!   [`target_codec`]: the byte codecs of the `targets` blobs.

#![warn(missing_docs)]

pub mod allocator;
pub mod augment;
pub mod augment_dataset;
pub mod biwi;
pub mod convert;
pub mod crop;
pub mod dataset;
#[cfg(feature = "model")]
pub mod demo;
pub mod eval;
pub mod eval_dataset;
pub mod face_targets;
pub mod import_arkit;
pub mod loader;
pub mod manifest;
pub mod overlay;
#[cfg(feature = "model")]
pub mod perspnet;
pub mod plot;
pub mod pnp;
pub mod predict;
pub mod predictions_table;
pub mod render;
pub mod render_dataset;
pub mod report;
pub mod samples_table;
pub mod split;
pub mod synth;
pub mod synthetic_face;
pub mod targets_table;
pub mod topology;
#[cfg(feature = "model")]
pub mod training;

pub use crop::official as official_crop;

pub use arkit_core::{
    atomic_file, conventions, error, limits, npy, raster, release, rng, target_codec,
};
pub use conventions::{Camera, EulerAngles, Pose};
pub use error::{Error, ErrorKind, Result};
pub use topology::FaceTopology;

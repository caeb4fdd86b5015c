//! `arkit_data`: read, validate, render and synthesise data of the ARKitFace dataset
//! (Kao et al., IEEE TIP 2023), and of data shaped like it: everything of `arkit-tool`
//! but the network (`arkit-perspnet`) and the command line. Needs polars, not candle.
//!
//! One folder per stage of the data flow, each stating its contract in its `mod.rs`;
//! a stage uses only the stages before it in this list (and `arkit_core`: conventions,
//! bounded readers of the release's files, the rasterizer core):
//!
//! - [`mesh`]: the face topology and the built-in synthetic face.
//! - [`crop`]: the square crop around a face and the image resampled into it (ours, and
//!   the official loader's box and `cv2.warpAffine`: [`crop::official_crop`],
//!   [`crop::warp_affine`]).
//! - [`picture`]: images read (bounded before decoding) and pictures drawn for people.
//! - [`store`]: a converted dataset on disk: manifest, shards, the tables, the crop store.
//! - [`ingest`]: the release, BIWI, a user's captures and synthetic data into a dataset;
//!   subject-disjoint splits.
//! - [`render`]: masks, correspondences and UV position maps, per sample and per dataset.
//! - [`augment`]: face profiling.
//! - [`pose`]: PnP and predictions in the release's form.
//! - [`eval`]: the paper's metrics, a predictions file scored, the report.
//! - [`loader`]: the Python package's items, both rule sets, and the crop store written.
//!
//! Each stage is a room with one door: its files are private, and its `mod.rs` names
//! what it offers in one `pub use` block (`arkit_data::ingest::ConvertOptions`, not
//! `arkit_data::ingest::convert::ConvertOptions`); the few public sub-modules left
//! (`ingest::biwi`, `ingest::synth`, `store::crop_store`) say why in a comment. The
//! names a pipeline is usually written with are also at the crate root (the one block of
//! `pub use` below), so that `use arkit_data::{Dataset, FaceRenderer};` is enough to
//! start.
//!
//! # Examples
//!
//! Open a dataset and render one sample's targets (a synthetic release of four images,
//! converted first, as `arkit-tool synth` and `convert` do):
//!
//! ```
//! use arkit_core::conventions::{Camera, Pose};
//! use arkit_core::VisibilityBuffer;
//! use arkit_data::ingest::{self, ConvertOptions, ValidationContext};
//! use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
//! use arkit_data::mesh;
//! use arkit_data::{CropTransform, Dataset, FaceRenderer};
//! use nalgebra::Point3;
//!
//! # fn main() -> arkit_core::Result<()> {
//! let tmp = tempfile::tempdir().unwrap();
//! let (release, data) = (tmp.path().join("release"), tmp.path().join("pq"));
//! let options = SynthOptions {
//!     subjects: 2,
//!     images_per_subject: 2,
//!     width: 256,
//!     height: 256,
//!     ..SynthOptions::default()
//! };
//! synth::generate(&FaceSource::builtin(), &options, &release, &|| {})?;
//! let topology = mesh::builtin().topology.clone();
//! let context = ValidationContext {
//!     projection: Camera::release_projection(),
//!     topology: topology.clone(),
//!     embed_images: false,
//! };
//! let convert_options = ConvertOptions {
//!     input: release,
//!     output: data.clone(),
//!     resources: None,
//!     rows_per_shard: 4,
//!     embed_images: false,
//!     shard_index: 0,
//!     shard_count: 1,
//!     overwrite: false,
//! };
//! ingest::convert(&convert_options, &context, &|_| {})?;
//!
//! let dataset = Dataset::open(&data)?;
//! let samples = dataset.read_all_samples()?;
//! assert_eq!(samples.len(), 4);
//! let sample = &samples[0];
//! let verts: Vec<Point3<f32>> =
//!     sample.verts.chunks(3).map(|c| Point3::new(c[0], c[1], c[2])).collect();
//! let renderer = FaceRenderer::new(topology, Camera::release_projection())?;
//! let crop = CropTransform::around_landmarks(&sample.landmarks_2d, 128);
//! let targets = renderer.render(
//!     &verts,
//!     &Pose::from_release_rt(&sample.rt)?,
//!     sample.image_width,
//!     sample.image_height,
//!     &crop,
//!     &mut VisibilityBuffer::new(1, 1),
//! )?;
//! // The face covers part of the crop, and every face pixel has its triangle's vertices.
//! let face_pixels = targets.mask.iter().filter(|&&m| m).count();
//! assert!(face_pixels > 0 && face_pixels < 128 * 128);
//! assert_eq!(targets.corr_vertices.len(), face_pixels);
//! # Ok(())
//! # }
//! ```
//!
//! Solve PnP: a pose recovered from the projections of 50 points, one of them an
//! outlier that RANSAC leaves out:
//!
//! ```
//! use arkit_data::pose::{Intrinsics, RansacParams, reproject, solve_pnp_ransac};
//! use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};
//!
//! let k = Intrinsics { fx: 600.0, fy: 600.0, cx: 400.0, cy: 400.0 };
//! let truth = Isometry3::from_parts(
//!     Translation3::new(0.02, -0.01, 0.5),
//!     UnitQuaternion::from_euler_angles(0.1, -0.2, 0.05),
//! );
//! // A curved patch 10 cm across, as a face is.
//! let object: Vec<Point3<f64>> = (0..50)
//!     .map(|i| {
//!         let (u, v) = ((i % 10) as f64 / 9.0 - 0.5, (i / 10) as f64 / 4.0 - 0.5);
//!         Point3::new(0.1 * u, 0.1 * v, 0.02 * (u * u + v * v))
//!     })
//!     .collect();
//! let mut image: Vec<_> = object.iter().map(|p| reproject(&k, &truth, p)).collect();
//! image[3].x += 40.0;
//! let solution = solve_pnp_ransac(&object, &image, &k, &RansacParams::default()).unwrap();
//! assert!(!solution.inliers.contains(&3));
//! assert!((solution.translation - truth.translation.vector).norm() < 1e-6);
//! ```
//!
//! Evaluate: a prediction 10 mm off in x has a translation error of 10 mm in x and an
//! ADD of 10 mm, and no rotation error:
//!
//! ```
//! use arkit_data::eval::{EulerDifference, check_prediction, sample_errors, summarize};
//!
//! // `R_t` as the release stores it: row-vector form, translation in row 3, tz < 0.
//! let mut truth = [0.0f64; 16];
//! for i in [0, 5, 10, 15] {
//!     truth[i] = 1.0;
//! }
//! truth[14] = -0.5;
//! let mut predicted = truth;
//! predicted[12] += 0.010;
//! let verts = [0.0f32, 0.0, 0.0, 0.05, 0.0, 0.0, 0.0, 0.05, 0.02];
//! let errors = sample_errors(
//!     &truth,
//!     check_prediction(Some(&predicted)),
//!     &verts,
//!     None,
//!     EulerDifference::Official,
//! );
//! assert!((errors.tx_mm - 10.0).abs() < 1e-9 && errors.ty_mm.abs() < 1e-9);
//! assert!((errors.add_mm - 10.0).abs() < 1e-6);
//! assert!(errors.rotation_deg.abs() < 1e-6);
//! let summary = summarize(&[errors], EulerDifference::Official);
//! assert_eq!((summary.samples, summary.pose_failures), (1, 0));
//! assert!((summary.tx_mae_mm - 10.0).abs() < 1e-9);
//! ```

#![deny(missing_docs)]

pub mod augment;
pub mod crop;
pub mod eval;
#[doc(hidden)]
pub mod fuzz_entry;
pub mod ingest;
mod lanes;
pub mod loader;
pub mod mesh;
pub mod picture;
pub mod pose;
pub mod render;
pub mod storage;
pub mod store;
pub mod video;

// The names a pipeline is written with: open a dataset, render, load, solve, score.
pub use crate::{
    crop::{CropTransform, RuleSet},
    eval::Summary as EvalSummary,
    loader::{FaceLoader, LoaderItem, LoaderOptions},
    mesh::FaceTopology,
    pose::{Intrinsics, PnpSolution, RansacParams},
    render::FaceRenderer,
    store::{Dataset, FaceTargets},
};

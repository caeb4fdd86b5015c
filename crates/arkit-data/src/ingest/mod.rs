//! `ingest`: data from outside into a converted dataset.
//!
//! Contract: [`convert`] turns the release (or [`biwi`], or a user's captures made
//! release-shaped by [`import_arkit`]) into validated, sharded Parquet; a bad sample is
//! reported in the `errors` table and skipped, never substituted, and [`systematic`]
//! stops a run when one check skips most samples (the input is in another convention).
//! [`synth`] writes a synthetic dataset in the release's layout; [`split`] makes
//! subject-disjoint splits from a seed; [`release_camera`] checks and resamples another
//! camera's images into the release's. Depends on `store`, `picture`, `mesh` and
//! `arkit_core`.

pub mod biwi;
pub mod convert;
pub mod import_arkit;
pub mod release_camera;
pub mod split;
pub mod synth;
pub mod systematic;

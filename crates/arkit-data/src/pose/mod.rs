//! `pose`: 6DoF poses from 2D-3D correspondences.
//!
//! Contract: [`pnp`] solves perspective-n-point (P3P + MSAC RANSAC +
//! Levenberg-Marquardt) in OpenCV's convention, reproducibly from a seed; [`predict`]
//! turns crop-pixel correspondences into a pose in the release's form and runs the
//! oracle predictor that checks the whole evaluation path. Depends on `store`, `render`
//! and `arkit_core`.

pub mod pnp;
pub mod predict;

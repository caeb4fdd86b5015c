//! `pose`: 6DoF poses from 2D-3D correspondences.
//!
//! Contract: [`pnp`] solves perspective-n-point (P3P + MSAC RANSAC +
//! Levenberg-Marquardt) in OpenCV's convention, reproducibly from a seed; [`predict`]
//! turns crop-pixel correspondences into a pose in the release's form and runs the
//! oracle predictor that checks the whole evaluation path; [`photo`] poses a face of a
//! photo from its crop's correspondences, in the official demo's camera or the photo's
//! own. Depends on `store`, `render`, `picture` and `arkit_core`.

pub mod photo;
pub mod pnp;
pub mod predict;

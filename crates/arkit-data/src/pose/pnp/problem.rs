//! The problem and its answer: the camera, RANSAC's parameters, the solution and the
//! ways a solve fails.

use nalgebra::{Isometry3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use std::fmt;

/// Pinhole camera intrinsics in pixels (no distortion).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along image x, in pixels.
    pub fx: f64,
    /// Focal length along image y, in pixels.
    pub fy: f64,
    /// Principal point x coordinate, in pixels.
    pub cx: f64,
    /// Principal point y coordinate, in pixels.
    pub cy: f64,
}

/// Parameters of [`solve_pnp_ransac`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacParams {
    /// Reprojection error (pixels) below which a correspondence is an inlier;
    /// also the truncation level of the MSAC cost. Default 8.0.
    pub reprojection_threshold_px: f64,
    /// Upper bound on the number of RANSAC hypotheses (samples). Default 100.
    pub max_iterations: usize,
    /// Desired probability of drawing at least one outlier-free sample; drives
    /// the adaptive iteration count. Default 0.99.
    pub confidence: f64,
    /// Seed of the internal deterministic PRNG. Default 0.
    pub seed: u64,
}

impl Default for RansacParams {
    fn default() -> Self {
        Self {
            reprojection_threshold_px: 8.0,
            max_iterations: 100,
            confidence: 0.99,
            seed: 0,
        }
    }
}

/// A pose estimate with its inlier set and fit quality.
#[derive(Debug, Clone, PartialEq)]
pub struct PnpSolution {
    /// Rotation `R` of `X_cam = R * X_obj + t`.
    pub rotation: Rotation3<f64>,
    /// Translation `t` of `X_cam = R * X_obj + t`, in object units.
    pub translation: Vector3<f64>,
    /// Indices of the correspondences used by the final refinement, ascending
    /// (all indices for [`solve_pnp`]).
    pub inliers: Vec<usize>,
    /// Root-mean-square reprojection error over `inliers`, in pixels.
    pub rms_reprojection_error_px: f64,
    /// Number of RANSAC samples drawn ([`solve_pnp_ransac`]) or 0 ([`solve_pnp`]).
    pub iterations: usize,
    /// Correspondences [`solve_pnp_ransac`] left out because a coordinate was NaN or
    /// infinite (0 for [`solve_pnp`], which refuses them). None of them is in
    /// `inliers`.
    pub non_finite_dropped: usize,
}

impl PnpSolution {
    /// The pose as an isometry mapping object coordinates to camera coordinates.
    pub fn isometry(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.translation),
            UnitQuaternion::from_rotation_matrix(&self.rotation),
        )
    }
}

/// Reasons a PnP problem cannot be solved.
#[derive(Debug, Clone, PartialEq)]
pub enum PnpError {
    /// Fewer finite correspondences than the solver needs once the non-finite ones
    /// are left out ([`solve_pnp_ransac`]).
    TooFewFinite {
        /// Number of correspondences given.
        given: usize,
        /// How many of them are finite.
        finite: usize,
        /// Minimum number required.
        needed: usize,
    },
    /// Fewer correspondences than the solver needs.
    TooFewPoints {
        /// Number of correspondences given.
        given: usize,
        /// Minimum number required.
        needed: usize,
    },
    /// The object and image slices have different lengths.
    LengthMismatch {
        /// Length of the object-point slice.
        object: usize,
        /// Length of the image-point slice.
        image: usize,
    },
    /// A coordinate of correspondence `index` is NaN or infinite.
    NonFinite {
        /// Index of the first offending correspondence.
        index: usize,
    },
    /// The configuration admits no (unique) solution: coincident or collinear
    /// object points, no hypothesis with enough inliers, and so on.
    Degenerate(&'static str),
}

impl fmt::Display for PnpError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PnpError::TooFewFinite {
                given,
                finite,
                needed,
            } => write!(
                f,
                "too few finite points: {finite} of the {given} given are finite (no NaN or infinity), {needed} needed"
            ),
            PnpError::TooFewPoints { given, needed } => {
                write!(f, "too few points: {given} given, {needed} needed")
            }
            PnpError::LengthMismatch { object, image } => write!(
                f,
                "length mismatch: {object} object points, {image} image points"
            ),
            PnpError::NonFinite { index } => {
                write!(f, "non-finite coordinate in correspondence {index}")
            }
            PnpError::Degenerate(why) => write!(f, "degenerate configuration: {why}"),
        }
    }
}

impl std::error::Error for PnpError {}

/// Minimum number of correspondences accepted by the solvers.
pub(super) const MIN_POINTS: usize = 4;

/// Projects an object point with pose `pose` (object → camera) to pixels.
pub fn reproject(k: &Intrinsics, pose: &Isometry3<f64>, p: &Point3<f64>) -> Point2<f64> {
    let c = pose * p;
    Point2::new(k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy)
}

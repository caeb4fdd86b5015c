//! `pose`: 6DoF poses from 2D-3D correspondences.
//!
//! Takes 2D-3D correspondences (crop pixels and mesh points) and a camera. Gives a
//! pose: [`solve_pnp_ransac`] (P3P + MSAC RANSAC + Levenberg-Marquardt, OpenCV's
//! convention) returns a [`PnpSolution`]; [`pose_from_correspondences`] gives it in the
//! release's form; [`oracle_predictions`] and [`mean_pose_predictions`] write the
//! predictors that check the evaluation path; [`face_pose`] poses a face of a photo in
//! the official demo's camera or the photo's own ([`PhotoCamera`]). Guarantees: results
//! are reproducible from the seed; too few (finite) correspondences give a
//! [`PnpError`], never a pose. Depends on `store`, `render`, `picture` and `arkit_core`.

pub(crate) mod photo;
pub(crate) mod pnp;
pub(crate) mod predict;

pub use self::{
    photo::{FacePose, PhotoCamera, check_box, face_pose},
    pnp::{
        Intrinsics, PnpError, PnpSolution, RansacParams, refine_pose, reproject, solve_pnp,
        solve_pnp_ransac,
    },
    predict::{
        Correspondences, MeanPoseSummary, OracleOptions, OracleSummary, crop_pixel_to_image,
        intrinsics, mean_pose, mean_pose_predictions, oracle_predictions,
        pose_from_correspondences,
    },
};

//! Perspective-n-point (PnP) pose estimation: P3P + MSAC RANSAC + Levenberg-Marquardt.
//!
//! # Conventions
//!
//! OpenCV-style pinhole camera: the camera looks down +z, image x points right and
//! y points down, and a camera-frame point `(X, Y, Z)` projects to the pixel
//! `(fx*X/Z + cx, fy*Y/Z + cy)` (no distortion). A pose maps object points into
//! the camera frame: `X_cam = R * X_obj + t`.
//!
//! # Design
//!
//! * **Minimal solver (RANSAC hypotheses):** P3P after Persson & Nordberg's
//!   "Lambda Twist" (ECCV 2018). The three distance equations
//!   `λi² + λj² − 2 (yi·yj) λi λj = |xi − xj|²` are combined into a pencil of
//!   homogeneous conics; a real root of the cubic `det(D1 + γ D2) = 0` gives a
//!   degenerate conic (a pair of planes through the origin in λ-space) which,
//!   intersected with the pencil, gives up to four depth triples. Each triple is
//!   polished with a few Gauss-Newton steps on the three distance equations and
//!   turned into a pose with an exact orthonormal-frame alignment. P3P works on
//!   any non-collinear triple, so planar and nearly planar point sets (the face
//!   surface) need no special handling. The up-to-four solutions are
//!   disambiguated by scoring them on *all* correspondences, which is what the
//!   RANSAC loop does anyway (no separate 4th point is needed).
//! * **Closed-form all-points initialiser (`solve_pnp`):** EPnP (Lepetit,
//!   Moreno-Noguer & Fua, IJCV 2009) with control points from the PCA of the
//!   object points (3 control points when the points are planar, 4 otherwise).
//!   MᵀM is accumulated through its Kronecker structure; null-space dimensions
//!   N = 1, 2 (and 3 when non-planar) get linearised betas refined by
//!   Gauss-Newton on the inter-control-point distances (the paper's N = 4 case
//!   is omitted: LM follows anyway). Each candidate pose is obtained by aligning
//!   the control points (the camera points are the same affine combinations of
//!   them) and the candidate with the lowest reprojection error on a strided
//!   subset of at most 128 points is refined by LM on all points.
//! * **RANSAC variant: MSAC** (Torr & Zisserman 2000). Each hypothesis is scored
//!   by the truncated quadratic `Σ min(e², τ²)` instead of the plain inlier count.
//!   With 1 px noise and an 8 px threshold almost every reasonable hypothesis
//!   has (nearly) the same inlier count, so counting cannot tell a good pose
//!   from a mediocre one (ties are broken by sampling order); the truncated
//!   quadratic still ranks hypotheses by how well they fit the inliers, at the
//!   same cost and with the same outlier robustness. Scoring of a hypothesis
//!   stops as soon as its partial cost exceeds the best one so far. The
//!   iteration count is adaptive, as in OpenCV: `n = log(1 − confidence) /
//!   log(1 − w³)` with `w` the inlier ratio of the best hypothesis, capped by
//!   `max_iterations` (samples are 3 points; the up-to-four P3P solutions are
//!   told apart by the score on all points).
//! * **Refinement:** Levenberg-Marquardt on 6 parameters (axis-angle rotation
//!   increment applied on the left, `R ← exp([ω]×) R`, plus a translation
//!   increment), minimising the sum of squared pixel reprojection errors with
//!   analytic Jacobians (JᵀJ formed block-wise from column dot products) and
//!   Marquardt (diagonal) damping. It stops when the Gauss-Newton predicted
//!   decrease is below 1e-7 of the cost, or takes a last step unverified when
//!   that decrease is below a quarter of the estimated noise variance (the step
//!   is then well under one standard deviation of the estimate, where the model
//!   is linear). After RANSAC: (1) LM on a strided subset of at most 128 of the
//!   best hypothesis' inliers (this stage only has to be good enough to
//!   re-select inliers, and is ~8× cheaper than a full pass), (2) inliers are
//!   re-selected with that pose, (3) LM on all of them. The reported `inliers`
//!   are the set used in (3).
//!
//! # Measured figures
//!
//! Accuracy and time against the attainable accuracy and OpenCV's `solvePnPRansac`
//! (`cargo bench --bench pnp`): docs/performance.md, "PnP accuracy and time".
//!
//! # Files
//!
//! `problem` (the camera, the parameters, the solution, the errors), `geometry` (input
//! checks and shared geometry), `p3p`, `epnp`, `refine` (Levenberg-Marquardt and
//! [`solve_pnp`]) and `ransac` ([`solve_pnp_ransac`]), each file importing only those
//! before it.

mod epnp;
mod geometry;
mod p3p;
mod problem;
mod ransac;
mod refine;
#[cfg(test)]
mod tests;

pub use self::{
    problem::{Intrinsics, PnpError, PnpSolution, RansacParams, reproject},
    ransac::solve_pnp_ransac,
    refine::{refine_pose, solve_pnp},
};

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

use nalgebra::{
    DMatrix, Isometry3, Matrix3, Point2, Point3, Rotation3, SymmetricEigen, Translation3,
    UnitQuaternion, Vector2, Vector3, Vector6,
};
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
const MIN_POINTS: usize = 4;

/// Projects an object point with pose `pose` (object → camera) to pixels.
pub fn reproject(k: &Intrinsics, pose: &Isometry3<f64>, p: &Point3<f64>) -> Point2<f64> {
    let c = pose * p;
    Point2::new(k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy)
}

// ---------------------------------------------------------------------------
// Input validation
// ---------------------------------------------------------------------------

fn validate(object: &[Point3<f64>], image: &[Point2<f64>]) -> Result<(), PnpError> {
    if object.len() != image.len() {
        return Err(PnpError::LengthMismatch {
            object: object.len(),
            image: image.len(),
        });
    }
    if object.len() < MIN_POINTS {
        return Err(PnpError::TooFewPoints {
            given: object.len(),
            needed: MIN_POINTS,
        });
    }
    for (i, (p, q)) in object.iter().zip(image).enumerate() {
        if !(p.coords.iter().all(|v| v.is_finite()) && q.coords.iter().all(|v| v.is_finite())) {
            return Err(PnpError::NonFinite { index: i });
        }
    }
    Ok(())
}

/// Centroid and (ascending) PCA of a point set.
/// Centroid, ascending PCA eigenvalues and matching eigenvectors (columns).
type Pca = (Vector3<f64>, Vector3<f64>, Matrix3<f64>);

fn pca(object: &[Point3<f64>]) -> Pca {
    let n = object.len() as f64;
    let c = object.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mut cov = Matrix3::zeros();
    for p in object {
        let d = p.coords - c;
        cov += d * d.transpose();
    }
    cov /= n;
    let eig = SymmetricEigen::new(cov);
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let vals = Vector3::new(
        eig.eigenvalues[idx[0]].max(0.0),
        eig.eigenvalues[idx[1]].max(0.0),
        eig.eigenvalues[idx[2]].max(0.0),
    );
    let vecs = Matrix3::from_columns(&[
        eig.eigenvectors.column(idx[0]).into_owned(),
        eig.eigenvectors.column(idx[1]).into_owned(),
        eig.eigenvectors.column(idx[2]).into_owned(),
    ]);
    (c, vals, vecs)
}

/// Rejects coincident and collinear object point sets.
fn check_geometry(object: &[Point3<f64>]) -> Result<Pca, PnpError> {
    let (c, vals, vecs) = pca(object);
    let scale2 = object
        .iter()
        .map(|p| p.coords.norm_squared())
        .fold(0.0, f64::max)
        .max(1e-300);
    if vals[2] <= 1e-20 * scale2 {
        return Err(PnpError::Degenerate("all object points coincide"));
    }
    if vals[1] <= 1e-14 * vals[2] {
        return Err(PnpError::Degenerate("object points are collinear"));
    }
    Ok((c, vals, vecs))
}

// ---------------------------------------------------------------------------
// Geometry helpers
// ---------------------------------------------------------------------------

#[inline]
fn project(
    k: &Intrinsics,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    p: &Point3<f64>,
) -> Option<Vector2<f64>> {
    let c = r * p.coords + t;
    if c.z <= 1e-12 {
        return None;
    }
    let iz = 1.0 / c.z;
    Some(Vector2::new(k.fx * c.x * iz + k.cx, k.fy * c.y * iz + k.cy))
}

#[inline]
fn sq_err(
    k: &Intrinsics,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    p: &Point3<f64>,
    q: &Point2<f64>,
) -> f64 {
    match project(k, r, t, p) {
        Some(u) => (u - q.coords).norm_squared(),
        None => f64::INFINITY,
    }
}

/// Rotation closest (Frobenius) to an arbitrary 3x3 matrix, via SVD.
fn nearest_rotation(m: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let d = (u * vt).determinant().signum();
    u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * vt
}

/// Rigid alignment (no scale) `cam ≈ R * obj + t`, least squares (Kabsch).
fn absolute_orientation(
    obj: &[Vector3<f64>],
    cam: &[Vector3<f64>],
) -> (Matrix3<f64>, Vector3<f64>) {
    let n = obj.len() as f64;
    let co = obj.iter().fold(Vector3::zeros(), |a, p| a + p) / n;
    let cc = cam.iter().fold(Vector3::zeros(), |a, p| a + p) / n;
    let mut h = Matrix3::zeros();
    for (o, c) in obj.iter().zip(cam) {
        h += (c - cc) * (o - co).transpose();
    }
    let r = nearest_rotation(&h);
    (r, cc - r * co)
}

// ---------------------------------------------------------------------------
// P3P (Lambda Twist style)
// ---------------------------------------------------------------------------

/// One real root of `c3 x³ + c2 x² + c1 x + c0` (falls back to the quadratic).
fn cubic_real_root(c3: f64, c2: f64, c1: f64, c0: f64) -> Option<f64> {
    let scale = c3.abs().max(c2.abs()).max(c1.abs()).max(c0.abs());
    if scale == 0.0 {
        return None;
    }
    let mut x = if c3.abs() > 1e-12 * scale {
        let (a, b, c) = (c2 / c3, c1 / c3, c0 / c3);
        let q = (a * a - 3.0 * b) / 9.0;
        let r = (2.0 * a * a * a - 9.0 * a * b + 27.0 * c) / 54.0;
        if r * r < q * q * q {
            let th = (r / (q * q.sqrt())).clamp(-1.0, 1.0).acos();
            -2.0 * q.sqrt() * (th / 3.0).cos() - a / 3.0
        } else {
            let aa = -r.signum() * (r.abs() + (r * r - q * q * q).sqrt()).cbrt();
            let bb = if aa != 0.0 { q / aa } else { 0.0 };
            aa + bb - a / 3.0
        }
    } else if c2.abs() > 1e-12 * scale {
        let disc = c1 * c1 - 4.0 * c2 * c0;
        if disc < 0.0 {
            return None;
        }
        (-c1 + disc.sqrt()) / (2.0 * c2)
    } else if c1 != 0.0 {
        -c0 / c1
    } else {
        return None;
    };
    for _ in 0..3 {
        let f = ((c3 * x + c2) * x + c1) * x + c0;
        let df = (3.0 * c3 * x + 2.0 * c2) * x + c1;
        if df == 0.0 {
            break;
        }
        x -= f / df;
    }
    x.is_finite().then_some(x)
}

/// Solves P3P for unit bearing vectors `y` and object points `x`; returns up
/// to four poses `(R, t)` with `λi yi = R xi + t`, `λi > 0`.
fn p3p(y: [Vector3<f64>; 3], x: [Vector3<f64>; 3], out: &mut Vec<(Matrix3<f64>, Vector3<f64>)>) {
    out.clear();
    let b12 = -2.0 * y[0].dot(&y[1]);
    let b13 = -2.0 * y[0].dot(&y[2]);
    let b23 = -2.0 * y[1].dot(&y[2]);
    let a12 = (x[0] - x[1]).norm_squared();
    let a13 = (x[0] - x[2]).norm_squared();
    let a23 = (x[1] - x[2]).norm_squared();
    let m12 = Matrix3::new(1.0, b12 / 2.0, 0.0, b12 / 2.0, 1.0, 0.0, 0.0, 0.0, 0.0);
    let m13 = Matrix3::new(1.0, 0.0, b13 / 2.0, 0.0, 0.0, 0.0, b13 / 2.0, 0.0, 1.0);
    let m23 = Matrix3::new(0.0, 0.0, 0.0, 0.0, 1.0, b23 / 2.0, 0.0, b23 / 2.0, 1.0);
    let d1 = m12 * a23 - m23 * a12;
    let d2 = m13 * a23 - m23 * a13;
    let det3 = |a: Vector3<f64>, b: Vector3<f64>, c: Vector3<f64>| a.dot(&b.cross(&c));
    let (p0, p1, p2) = (
        d1.column(0).into_owned(),
        d1.column(1).into_owned(),
        d1.column(2).into_owned(),
    );
    let (q0, q1, q2) = (
        d2.column(0).into_owned(),
        d2.column(1).into_owned(),
        d2.column(2).into_owned(),
    );
    let c3 = det3(q0, q1, q2);
    let c2 = det3(p0, q1, q2) + det3(q0, p1, q2) + det3(q0, q1, p2);
    let c1 = det3(q0, p1, p2) + det3(p0, q1, p2) + det3(p0, p1, q2);
    let c0 = det3(p0, p1, p2);
    let Some(gamma) = cubic_real_root(c3, c2, c1, c0) else {
        return;
    };
    let d0 = d1 + d2 * gamma;
    let eig = SymmetricEigen::new(d0);
    // Order eigenvalues: largest positive (ia), most negative (ib), ~zero.
    let ev = eig.eigenvalues;
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&a, &b| ev[b].total_cmp(&ev[a]));
    let (ia, ib) = (idx[0], idx[2]);
    let (sa, sb) = (ev[ia], ev[ib]);
    if !(sa > 0.0 && sb < 0.0) {
        return;
    }
    let s = (-sb / sa).sqrt();
    let ea = eig.eigenvectors.column(ia).into_owned();
    let eb = eig.eigenvectors.column(ib).into_owned();
    // Positive definite form: sum of the three distance equations.
    let msum = m12 + m13 + m23;
    let asum = a12 + a13 + a23;
    // Homogeneous form to intersect with each plane: the larger-normed pencil member.
    for sign in [1.0, -1.0] {
        // Plane through the origin: n · Λ = 0 with n = √sa ea ± √(-sb) eb (scaled).
        let n = ea + eb * (sign * s);
        let u = if n.x.abs() < 0.9 * n.norm() {
            Vector3::x().cross(&n)
        } else {
            Vector3::y().cross(&n)
        }
        .normalize();
        let v = n.cross(&u).normalize();
        let restrict = |d: &Matrix3<f64>| (u.dot(&(d * u)), u.dot(&(d * v)), v.dot(&(d * v)));
        let r1 = restrict(&d1);
        let r2 = restrict(&d2);
        let nrm = |r: (f64, f64, f64)| r.0.abs() + r.1.abs() + r.2.abs();
        let (aq, bq, cq) = if nrm(r1) >= nrm(r2) { r1 } else { r2 };
        let disc = bq * bq - aq * cq;
        if disc < 0.0 {
            continue;
        }
        let sq = disc.sqrt();
        let dirs: [Vector3<f64>; 2] = if aq.abs() >= cq.abs() {
            if aq == 0.0 {
                continue;
            }
            // aq α² + 2 bq αβ + cq β² = 0, β = 1.
            [u * ((-bq + sq) / aq) + v, u * ((-bq - sq) / aq) + v]
        } else {
            [u + v * ((-bq + sq) / cq), u + v * ((-bq - sq) / cq)]
        };
        for dir in dirs {
            let qd = dir.dot(&(msum * dir));
            if qd <= 0.0 {
                continue;
            }
            let mut lam = dir * (asum / qd).sqrt();
            if lam.x < 0.0 {
                lam = -lam;
            }
            if !(lam.x > 0.0 && lam.y > 0.0 && lam.z > 0.0) {
                continue;
            }
            // Gauss-Newton polish on the three distance equations.
            for _ in 0..3 {
                let (l1, l2, l3) = (lam.x, lam.y, lam.z);
                let f = Vector3::new(
                    l1 * l1 + l2 * l2 + b12 * l1 * l2 - a12,
                    l1 * l1 + l3 * l3 + b13 * l1 * l3 - a13,
                    l2 * l2 + l3 * l3 + b23 * l2 * l3 - a23,
                );
                let j = Matrix3::new(
                    2.0 * l1 + b12 * l2,
                    2.0 * l2 + b12 * l1,
                    0.0,
                    2.0 * l1 + b13 * l3,
                    0.0,
                    2.0 * l3 + b13 * l1,
                    0.0,
                    2.0 * l2 + b23 * l3,
                    2.0 * l3 + b23 * l2,
                );
                match j.try_inverse() {
                    Some(ji) => {
                        let step = ji * f;
                        if step.iter().all(|v| v.is_finite()) {
                            lam -= step;
                        }
                    }
                    None => break,
                }
            }
            if !(lam.x > 0.0 && lam.y > 0.0 && lam.z > 0.0) {
                continue;
            }
            let c = [y[0] * lam.x, y[1] * lam.y, y[2] * lam.z];
            if let Some(pose) = frame_align(&x, &c) {
                out.push(pose);
            }
        }
    }
}

/// Exact pose from three non-collinear point pairs via orthonormal frames.
fn frame_align(
    x: &[Vector3<f64>; 3],
    c: &[Vector3<f64>; 3],
) -> Option<(Matrix3<f64>, Vector3<f64>)> {
    let frame = |p: &[Vector3<f64>; 3]| -> Option<Matrix3<f64>> {
        let e1 = (p[1] - p[0]).try_normalize(1e-300)?;
        let e3 = e1.cross(&(p[2] - p[0])).try_normalize(1e-300)?;
        let e2 = e3.cross(&e1);
        Some(Matrix3::from_columns(&[e1, e2, e3]))
    };
    let fw = frame(x)?;
    let fc = frame(c)?;
    let r = fc * fw.transpose();
    let t = c[0] - r * x[0];
    Some((r, t))
}

// ---------------------------------------------------------------------------
// EPnP (all-points closed-form initialiser)
// ---------------------------------------------------------------------------

/// EPnP (Lepetit et al., 2009) from all points: control points, the barycentric system,
/// its null space and the best of the one-to-three-vector solutions. Long (over 150
/// lines) on purpose: the steps follow the paper's sections in order and share their
/// intermediate matrices; split, each part would take and return most of them.
fn epnp(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    k: &Intrinsics,
    pca_res: &Pca,
) -> Option<(Matrix3<f64>, Vector3<f64>)> {
    let (c, vals, vecs) = pca_res;
    let planar = vals[0] <= 1e-10 * vals[2];
    // Control points: centroid + principal axes scaled by the standard deviation.
    let axes: Vec<(Vector3<f64>, f64)> = (0..3)
        .rev()
        .filter(|&i| !(planar && i == 0))
        .map(|i| {
            let s = vals[i].sqrt();
            (vecs.column(i).into_owned(), s)
        })
        .collect();
    let nc = axes.len() + 1;
    let mut cw = vec![*c];
    cw.extend(axes.iter().map(|(v, s)| c + v * *s));
    let dim = 3 * nc;
    // MᵀM has Kronecker structure: block (j, l) = Σ_i α_ij α_il S_i with
    // S_i = a aᵀ + b bᵀ, a = (fx, 0, cx − u), b = (0, fy, cy − v).
    let mut blocks = [[[0.0f64; 6]; 4]; 4];
    for (p, q) in object.iter().zip(image) {
        let d = p.coords - c;
        let mut a = [0.0; 4];
        let mut s0 = 0.0;
        for (j, (v, s)) in axes.iter().enumerate() {
            a[j + 1] = d.dot(v) / s;
            s0 += a[j + 1];
        }
        a[0] = 1.0 - s0;
        let (du, dv) = (k.cx - q.x, k.cy - q.y);
        // Unique entries of S: (0,0) (0,2) (1,1) (1,2) (2,2); (0,1) is 0.
        let sm = [
            k.fx * k.fx,
            k.fx * du,
            k.fy * k.fy,
            k.fy * dv,
            du * du + dv * dv,
            0.0,
        ];
        for j in 0..nc {
            for l in j..nc {
                let w = a[j] * a[l];
                let blk = &mut blocks[j][l];
                for e in 0..5 {
                    blk[e] += w * sm[e];
                }
            }
        }
    }
    let mut mtm = DMatrix::<f64>::zeros(dim, dim);
    for j in 0..nc {
        for l in j..nc {
            let b = &blocks[j][l];
            let sfull = Matrix3::new(b[0], 0.0, b[1], 0.0, b[2], b[3], b[1], b[3], b[4]);
            for r in 0..3 {
                for cc in 0..3 {
                    mtm[(3 * j + r, 3 * l + cc)] = sfull[(r, cc)];
                    mtm[(3 * l + cc, 3 * j + r)] = sfull[(r, cc)];
                }
            }
        }
    }
    let eig = SymmetricEigen::new(mtm);
    let mut order: Vec<usize> = (0..dim).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let nullv: Vec<Vec<Vector3<f64>>> = order
        .iter()
        .take(3)
        .map(|&i| {
            let col = eig.eigenvectors.column(i);
            (0..nc)
                .map(|j| Vector3::new(col[3 * j], col[3 * j + 1], col[3 * j + 2]))
                .collect()
        })
        .collect();
    let pairs: Vec<(usize, usize)> = (0..nc)
        .flat_map(|a| ((a + 1)..nc).map(move |b| (a, b)))
        .collect();
    let dw: Vec<f64> = pairs
        .iter()
        .map(|&(a, b)| (cw[a] - cw[b]).norm_squared())
        .collect();

    let max_n = if planar { 2 } else { 3 };
    let mut best: Option<(f64, Matrix3<f64>, Vector3<f64>)> = None;
    for n in 1..=max_n {
        let v = &nullv[..n];
        // Linearised betas: unknowns β_kl (k ≤ l).
        let kl: Vec<(usize, usize)> = (0..n).flat_map(|a| (a..n).map(move |b| (a, b))).collect();
        let mut a_mat = DMatrix::<f64>::zeros(pairs.len(), kl.len());
        for (r, &(pa, pb)) in pairs.iter().enumerate() {
            for (ci, &(kk, ll)) in kl.iter().enumerate() {
                let dk = v[kk][pa] - v[kk][pb];
                let dl = v[ll][pa] - v[ll][pb];
                a_mat[(r, ci)] = if kk == ll {
                    dk.dot(&dk)
                } else {
                    2.0 * dk.dot(&dl)
                };
            }
        }
        let bvec = DMatrix::from_column_slice(pairs.len(), 1, &dw);
        let sol = a_mat.svd(true, true).solve(&bvec, 1e-14).ok()?;
        let mut beta = vec![0.0; n];
        beta[0] = sol[0].abs().sqrt();
        for (l, b) in beta.iter_mut().enumerate().skip(1) {
            let diag = kl.iter().position(|&p| p == (l, l)).unwrap();
            let cross = kl.iter().position(|&p| p == (0, l)).unwrap();
            *b = sol[diag].abs().sqrt() * sol[cross].signum();
        }
        // Gauss-Newton on the distance constraints.
        for _ in 0..5 {
            let cc: Vec<Vector3<f64>> = (0..nc)
                .map(|j| (0..n).fold(Vector3::zeros(), |acc, kk| acc + v[kk][j] * beta[kk]))
                .collect();
            let mut jtj = DMatrix::<f64>::zeros(n, n);
            let mut jtr = DMatrix::<f64>::zeros(n, 1);
            for (r, &(pa, pb)) in pairs.iter().enumerate() {
                let dc = cc[pa] - cc[pb];
                let f = dc.norm_squared() - dw[r];
                let jr: Vec<f64> = (0..n)
                    .map(|kk| 2.0 * dc.dot(&(v[kk][pa] - v[kk][pb])))
                    .collect();
                for i1 in 0..n {
                    jtr[i1] += jr[i1] * f;
                    for i2 in 0..n {
                        jtj[(i1, i2)] += jr[i1] * jr[i2];
                    }
                }
            }
            match jtj.cholesky() {
                Some(ch) => {
                    let step = ch.solve(&jtr);
                    for i in 0..n {
                        beta[i] -= step[i];
                    }
                }
                None => break,
            }
        }
        let mut cc: Vec<Vector3<f64>> = (0..nc)
            .map(|j| (0..n).fold(Vector3::zeros(), |acc, kk| acc + v[kk][j] * beta[kk]))
            .collect();
        // The first control point is the centroid: it must be in front.
        if cc[0].z < 0.0 {
            cc.iter_mut().for_each(|p| *p = -*p);
        }
        // The camera points are the same affine combinations of the camera
        // control points, so aligning the control points aligns the points.
        let (r, t) = absolute_orientation(&cw, &cc);
        if !(r.iter().all(|x| x.is_finite()) && t.iter().all(|x| x.is_finite())) {
            continue;
        }
        // Candidate selection on a strided subset of at most 128 points.
        let stride = object.len().div_ceil(128);
        let err: f64 = object
            .iter()
            .zip(image)
            .step_by(stride)
            .map(|(p, q)| sq_err(k, &r, &t, p, q).min(1e12))
            .sum();
        if best.as_ref().is_none_or(|b| err < b.0) {
            best = Some((err, r, t));
        }
    }
    best.map(|(_, r, t)| (r, t))
}

// ---------------------------------------------------------------------------
// Levenberg-Marquardt refinement
// ---------------------------------------------------------------------------

/// Sum of squared reprojection errors over `idx` (points behind the camera
/// count as a large constant).
fn total_cost(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    idx: &[usize],
    k: &Intrinsics,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
) -> f64 {
    idx.iter()
        .map(|&i| sq_err(k, r, t, &object[i], &image[i]).min(1e10))
        .sum()
}

/// Dot product with four independent accumulators (lets the compiler use SIMD).
#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            acc[l] += x[l] * y[l];
        }
    }
    let tail: f64 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// Points per block in [`linearize`].
const BLOCK: usize = 64;

/// Cost, upper triangle of JᵀJ (row-major, 21 entries) and Jᵀe at a pose.
///
/// Jacobian rows are written block-wise into column buffers, and JᵀJ is then
/// formed from column dot products (vectorisable, no register spills).
fn linearize(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    idx: &[usize],
    k: &Intrinsics,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
) -> (f64, [f64; 21], [f64; 6]) {
    let mut h = [0.0f64; 21];
    let mut g = [0.0f64; 6];
    let mut cost = 0.0;
    let mut cols = [[0.0f64; 2 * BLOCK]; 7];
    for chunk in idx.chunks(BLOCK) {
        let len = 2 * chunk.len();
        for (row, &i) in chunk.iter().enumerate() {
            let rp = r * object[i].coords;
            let pc = rp + t;
            let (u, v) = (2 * row, 2 * row + 1);
            if pc.z <= 1e-12 {
                cost += 1e10;
                for col in cols.iter_mut() {
                    col[u] = 0.0;
                    col[v] = 0.0;
                }
                continue;
            }
            let iz = 1.0 / pc.z;
            let (xn, yn) = (pc.x * iz, pc.y * iz);
            let eu = k.fx * xn + k.cx - image[i].x;
            let ev = k.fy * yn + k.cy - image[i].y;
            cost += (eu * eu + ev * ev).min(1e10);
            // du/dpc = fu [1, 0, -xn], dv/dpc = fv [0, 1, -yn]; dpc/dω = -[rp]x,
            // dpc/dt = I; w^T (-[rp]x) = (rp × w)^T.
            let (fu, fv) = (k.fx * iz, k.fy * iz);
            cols[0][u] = -fu * rp.y * xn;
            cols[1][u] = fu * (rp.z + rp.x * xn);
            cols[2][u] = -fu * rp.y;
            cols[3][u] = fu;
            cols[4][u] = 0.0;
            cols[5][u] = -fu * xn;
            cols[6][u] = eu;
            cols[0][v] = -fv * (rp.y * yn + rp.z);
            cols[1][v] = fv * rp.x * yn;
            cols[2][v] = fv * rp.x;
            cols[3][v] = 0.0;
            cols[4][v] = fv;
            cols[5][v] = -fv * yn;
            cols[6][v] = ev;
        }
        let mut m = 0;
        for p in 0..6 {
            g[p] += dot(&cols[p][..len], &cols[6][..len]);
            for q in p..6 {
                h[m] += dot(&cols[p][..len], &cols[q][..len]);
                m += 1;
            }
        }
    }
    (cost, h, g)
}

fn lm(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    idx: &[usize],
    k: &Intrinsics,
    rotation: Rotation3<f64>,
    translation: Vector3<f64>,
    iterations: usize,
) -> (Rotation3<f64>, Vector3<f64>) {
    let mut rot = rotation;
    let mut t = translation;
    let mut lambda = 1e-4;
    let (mut cost, mut h, mut g) = linearize(object, image, idx, k, rot.matrix(), &t);
    // Below this cost (px², summed) the fit is exact to machine precision.
    let tiny = 1e-24 * idx.len().max(1) as f64;
    for _ in 0..iterations {
        if cost <= tiny {
            break;
        }
        let mut hm = nalgebra::Matrix6::<f64>::zeros();
        let mut m = 0;
        for p in 0..6 {
            for q in p..6 {
                hm[(p, q)] = h[m];
                hm[(q, p)] = h[m];
                m += 1;
            }
        }
        for d in 0..6 {
            hm[(d, d)] += lambda * h[[0, 6, 11, 15, 18, 20][d]].max(1e-12);
        }
        let Some(ch) = hm.cholesky() else {
            lambda *= 10.0;
            continue;
        };
        let gv = Vector6::from_column_slice(&g);
        let step = -ch.solve(&gv);
        // Gauss-Newton predicted decrease of the cost (½ e² convention ×2).
        let mut jtj = nalgebra::Matrix6::<f64>::zeros();
        let mut m = 0;
        for p in 0..6 {
            for q in p..6 {
                jtj[(p, q)] = h[m];
                jtj[(q, p)] = h[m];
                m += 1;
            }
        }
        let predicted = -(2.0 * gv.dot(&step) + step.dot(&(jtj * step)));
        if predicted < 1e-7 * cost {
            break;
        }
        let w = Vector3::new(step[0], step[1], step[2]);
        // A step whose predicted decrease is below a quarter of the estimated
        // noise variance moves the pose by less than half a standard deviation
        // of the estimate, where the model is linear to high accuracy: take it
        // and stop, without paying for another pass over the points.
        let sigma2 = cost / (2 * idx.len()).saturating_sub(6).max(1) as f64;
        if predicted < 0.25 * sigma2 && cost > 1e-6 * idx.len() as f64 {
            rot = Rotation3::new(w) * rot;
            t += Vector3::new(step[3], step[4], step[5]);
            break;
        }
        let dt = Vector3::new(step[3], step[4], step[5]);
        let nrot = Rotation3::new(w) * rot;
        let nt = t + dt;
        let (ncost, nh, ng) = linearize(object, image, idx, k, nrot.matrix(), &nt);
        if ncost < cost {
            let rel = (cost - ncost) / cost;
            rot = nrot;
            t = nt;
            cost = ncost;
            h = nh;
            g = ng;
            lambda = (lambda * 0.1).max(1e-10);
            // Converged: negligible decrease or a step far below noise level.
            if rel < 1e-10 || (w.norm() < 1e-12 && dt.norm() < 1e-12 * t.norm().max(1e-6)) {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e10 {
                break;
            }
        }
    }
    (rot, t)
}

/// Levenberg-Marquardt refinement of a pose on all correspondences.
///
/// Minimises the sum of squared pixel reprojection errors over 6 parameters:
/// an axis-angle increment `ω` applied on the left (`R ← exp([ω]×) R`) and a
/// translation increment. `iterations` bounds the number of LM steps (accepted
/// or rejected); the function stops earlier once the cost no longer decreases.
/// Slices of different lengths are truncated to the shorter one.
pub fn refine_pose(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    k: &Intrinsics,
    rotation: Rotation3<f64>,
    translation: Vector3<f64>,
    iterations: usize,
) -> (Rotation3<f64>, Vector3<f64>) {
    let n = object.len().min(image.len());
    let idx: Vec<usize> = (0..n).collect();
    lm(object, image, &idx, k, rotation, translation, iterations)
}

fn rms(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    idx: &[usize],
    k: &Intrinsics,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
) -> f64 {
    if idx.is_empty() {
        return 0.0;
    }
    (total_cost(object, image, idx, k, r, t) / idx.len() as f64).sqrt()
}

/// Largest inlier subset used by the first (inlier re-selection) LM stage of RANSAC.
const SUBSET_SIZE: usize = 128;

/// Number of LM iterations used by the solvers.
const LM_ITERATIONS: usize = 20;

/// Solves PnP from all correspondences (no outlier rejection): EPnP closed-form
/// initialisation followed by Levenberg-Marquardt refinement.
///
/// Needs at least 4 finite correspondences whose object points are neither
/// coincident nor collinear.
pub fn solve_pnp(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    k: &Intrinsics,
) -> Result<PnpSolution, PnpError> {
    validate(object, image)?;
    let pc = check_geometry(object)?;
    let (r0, t0) = epnp(object, image, k, &pc).ok_or(PnpError::Degenerate("EPnP failed"))?;

    let r0 = Rotation3::from_matrix_unchecked(r0);
    let idx: Vec<usize> = (0..object.len()).collect();
    let (r, t) = lm(object, image, &idx, k, r0, t0, LM_ITERATIONS);
    let e = rms(object, image, &idx, k, r.matrix(), &t);
    Ok(PnpSolution {
        rotation: r,
        translation: t,
        inliers: idx,
        rms_reprojection_error_px: e,
        iterations: 0,
        non_finite_dropped: 0,
    })
}

// ---------------------------------------------------------------------------
// RANSAC
// ---------------------------------------------------------------------------

/// Robust PnP: P3P hypotheses in an MSAC loop, then LM refinement on the inliers.
///
/// A correspondence with a NaN or infinite coordinate (object or image point) is an
/// outlier that no hypothesis can explain: it is left out before solving, counted in
/// [`PnpSolution::non_finite_dropped`], and never among the `inliers`, whose indices
/// still refer to the caller's slices. The result is the one the finite
/// correspondences alone give (same seed, same pose). At least 4 finite
/// correspondences are needed ([`PnpError::TooFewFinite`] otherwise).
///
/// See the module documentation for the algorithm. Errors: [`PnpError::TooFewPoints`]
/// (< 4 given), [`PnpError::TooFewFinite`] (< 4 finite), [`PnpError::LengthMismatch`],
/// and [`PnpError::Degenerate`] for coincident/collinear object points or when no
/// hypothesis has at least 4 inliers.
pub fn solve_pnp_ransac(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    k: &Intrinsics,
    params: &RansacParams,
) -> Result<PnpSolution, PnpError> {
    if object.len() != image.len() {
        return Err(PnpError::LengthMismatch {
            object: object.len(),
            image: image.len(),
        });
    }
    let finite = |i: usize| {
        object[i].coords.iter().all(|v| v.is_finite())
            && image[i].coords.iter().all(|v| v.is_finite())
    };
    let kept: Vec<usize> = (0..object.len()).filter(|&i| finite(i)).collect();
    if kept.len() == object.len() {
        return solve_finite_ransac(object, image, k, params);
    }
    if object.len() < MIN_POINTS {
        return Err(PnpError::TooFewPoints {
            given: object.len(),
            needed: MIN_POINTS,
        });
    }
    if kept.len() < MIN_POINTS {
        return Err(PnpError::TooFewFinite {
            given: object.len(),
            finite: kept.len(),
            needed: MIN_POINTS,
        });
    }
    let o: Vec<Point3<f64>> = kept.iter().map(|&i| object[i]).collect();
    let q: Vec<Point2<f64>> = kept.iter().map(|&i| image[i]).collect();
    let mut s = solve_finite_ransac(&o, &q, k, params)?;
    // Back to the caller's indexing (ascending stays ascending).
    for i in &mut s.inliers {
        *i = kept[*i];
    }
    s.non_finite_dropped = object.len() - kept.len();
    Ok(s)
}

/// [`solve_pnp_ransac`] on correspondences that are all finite.
fn solve_finite_ransac(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    k: &Intrinsics,
    params: &RansacParams,
) -> Result<PnpSolution, PnpError> {
    validate(object, image)?;
    check_geometry(object)?;
    let n = object.len();
    let th2 = params.reprojection_threshold_px * params.reprojection_threshold_px;
    let bearings: Vec<Vector3<f64>> = image
        .iter()
        .map(|q| Vector3::new((q.x - k.cx) / k.fx, (q.y - k.cy) / k.fy, 1.0).normalize())
        .collect();
    let mut rng = arkit_core::Rng::new(params.seed);
    let mut best_cost = f64::INFINITY;
    let mut best: Option<(Matrix3<f64>, Vector3<f64>)> = None;
    let mut best_inliers = 0usize;
    let mut needed = params.max_iterations.max(1);
    let mut iterations = 0;
    let mut sols = Vec::with_capacity(4);
    let log1mc = (1.0 - params.confidence.clamp(0.0, 1.0 - 1e-12)).ln();
    while iterations < needed {
        iterations += 1;
        let i0 = rng.below(n as u64) as usize;
        let mut i1 = rng.below(n as u64 - 1) as usize;
        if i1 >= i0 {
            i1 += 1;
        }
        let (lo, hi) = (i0.min(i1), i0.max(i1));
        let mut i2 = rng.below(n as u64 - 2) as usize;
        if i2 >= lo {
            i2 += 1;
        }
        if i2 >= hi {
            i2 += 1;
        }
        let ids = [i0, i1, i2];
        let x = ids.map(|i| object[i].coords);
        // Skip (nearly) collinear samples.
        let area = (x[1] - x[0]).cross(&(x[2] - x[0])).norm();
        let longest = (x[1] - x[0])
            .norm_squared()
            .max((x[2] - x[0]).norm_squared())
            .max((x[2] - x[1]).norm_squared());
        if area.is_nan() || area <= 1e-6 * longest {
            continue;
        }
        p3p(ids.map(|i| bearings[i]), x, &mut sols);
        for (r, t) in &sols {
            let mut cost = 0.0;
            let mut inl = 0usize;
            for (p, q) in object.iter().zip(image) {
                let e = sq_err(k, r, t, p, q);
                if e < th2 {
                    cost += e;
                    inl += 1;
                } else {
                    cost += th2;
                }
                if cost >= best_cost {
                    break;
                }
            }
            if cost < best_cost {
                best_cost = cost;
                best = Some((*r, *t));
                best_inliers = inl;
                let w = inl as f64 / n as f64;
                let denom = (1.0 - w * w * w).ln();
                let adaptive = if denom < 0.0 {
                    (log1mc / denom).ceil().max(1.0)
                } else {
                    f64::INFINITY
                };
                if adaptive.is_finite() {
                    needed = needed.min(adaptive as usize);
                }
            }
        }
    }
    let Some((r, t)) = best else {
        return Err(PnpError::Degenerate("no valid hypothesis"));
    };
    if best_inliers < MIN_POINTS {
        return Err(PnpError::Degenerate(
            "no hypothesis with at least 4 inliers",
        ));
    }
    let inliers_of = |r: &Matrix3<f64>, t: &Vector3<f64>| -> Vec<usize> {
        (0..n)
            .filter(|&i| sq_err(k, r, t, &object[i], &image[i]) < th2)
            .collect()
    };
    // Stage 1: LM on (a strided subset of at most SUBSET_SIZE of) the
    // hypothesis' inliers; it only needs to be good enough to re-select inliers.
    let inl = inliers_of(&r, &t);
    let stride = inl.len().div_ceil(SUBSET_SIZE).max(1);
    let subset: Vec<usize> = inl.iter().copied().step_by(stride).collect();
    let rot = Rotation3::from_matrix_unchecked(nearest_rotation(&r));
    let (rot1, t1) = lm(object, image, &subset, k, rot, t, LM_ITERATIONS);
    // Stage 2: re-select inliers with the refined pose, LM on all of them.
    let inl2 = inliers_of(rot1.matrix(), &t1);
    let (start_r, start_t, inl) = if inl2.len() >= MIN_POINTS {
        (rot1, t1, inl2)
    } else {
        (rot, t, inl)
    };
    let (rot, t) = lm(object, image, &inl, k, start_r, start_t, LM_ITERATIONS);
    let e = rms(object, image, &inl, k, rot.matrix(), &t);
    Ok(PnpSolution {
        rotation: rot,
        translation: t,
        inliers: inl,
        rms_reprojection_error_px: e,
        iterations,
        non_finite_dropped: 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The crate's generator with the names these tests read well with.
    struct Rng(arkit_core::Rng);

    impl Rng {
        fn new(seed: u64) -> Self {
            Rng(arkit_core::Rng::new(seed))
        }
        fn uniform(&mut self) -> f64 {
            self.0.next_f64()
        }
        fn range(&mut self, a: f64, b: f64) -> f64 {
            self.0.uniform(a, b)
        }
        fn gauss(&mut self) -> f64 {
            self.0.normal()
        }
    }

    const K: Intrinsics = Intrinsics {
        fx: 629.775,
        fy: 629.775,
        cx: 400.0,
        cy: 400.0,
    };

    type Scene = (
        Rotation3<f64>,
        Vector3<f64>,
        Vec<Point3<f64>>,
        Vec<Point2<f64>>,
    );

    /// Random pose looking at a face-sized patch, plus object points on a
    /// curved patch (depth up to ~10 cm, or exactly planar).
    fn scene(rng: &mut Rng, n: usize, planar: bool) -> Scene {
        let d = 60f64.to_radians();
        let base = Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let rot = base
            * Rotation3::from_euler_angles(
                rng.range(-d, d),
                rng.range(-d, d),
                rng.range(-d / 2.0, d / 2.0),
            );
        let z = rng.range(0.3, 1.2);
        let t = Vector3::new(rng.range(-0.05, 0.05), rng.range(-0.05, 0.05), z);
        let pts: Vec<Point3<f64>> = (0..n)
            .map(|_| {
                let x = rng.range(-0.08, 0.08);
                let y = rng.range(-0.09, 0.09);
                let zz = if planar {
                    0.0
                } else {
                    0.1 - 4.0 * (x * x + 0.5 * y * y)
                };
                Point3::new(x, y, zz)
            })
            .collect();
        let iso = Isometry3::from_parts(
            Translation3::from(t),
            UnitQuaternion::from_rotation_matrix(&rot),
        );
        let img = pts.iter().map(|p| reproject(&K, &iso, p)).collect();
        (rot, t, pts, img)
    }

    /// Geodesic angle, accurate near zero (atan2 of sine and cosine parts).
    fn rot_err_deg(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
        let m = (a.inverse() * b).into_inner();
        let s = Vector3::new(
            m[(2, 1)] - m[(1, 2)],
            m[(0, 2)] - m[(2, 0)],
            m[(1, 0)] - m[(0, 1)],
        );
        (0.5 * s.norm()).atan2(0.5 * (m.trace() - 1.0)).to_degrees()
    }

    fn median(mut v: Vec<f64>) -> f64 {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    }

    #[test]
    fn exact_data_solve_pnp_and_ransac() {
        let mut rng = Rng::new(1);
        for trial in 0..40 {
            let planar = trial % 4 == 3;
            let n = if trial % 2 == 0 { 6 } else { 100 };
            let (r, t, obj, img) = scene(&mut rng, n, planar);
            let s = solve_pnp(&obj, &img, &K).unwrap();
            assert!(
                rot_err_deg(&s.rotation, &r) < 1e-6,
                "trial {trial} solve_pnp rot"
            );
            assert!(
                (s.translation - t).norm() < 1e-6,
                "trial {trial} solve_pnp t"
            );
            let params = RansacParams {
                seed: trial,
                ..Default::default()
            };
            let s = solve_pnp_ransac(&obj, &img, &K, &params).unwrap();
            assert!(
                rot_err_deg(&s.rotation, &r) < 1e-6,
                "trial {trial} ransac rot"
            );
            assert!((s.translation - t).norm() < 1e-6, "trial {trial} ransac t");
            assert_eq!(s.inliers.len(), n);
            assert!(s.rms_reprojection_error_px < 1e-6);
        }
    }

    #[test]
    fn p3p_returns_true_pose_among_solutions() {
        let mut rng = Rng::new(7);
        for _ in 0..200 {
            let (r, t, obj, img) = scene(&mut rng, 3, false);
            let y = [0, 1, 2].map(|i| {
                Vector3::new((img[i].x - K.cx) / K.fx, (img[i].y - K.cy) / K.fy, 1.0).normalize()
            });
            let mut sols = Vec::new();
            p3p(y, [0, 1, 2].map(|i| obj[i].coords), &mut sols);
            let best = sols
                .iter()
                .map(|(rr, tt)| (rr - r.matrix()).norm() + (tt - t).norm())
                .fold(f64::INFINITY, f64::min);
            assert!(best < 1e-6, "best {best} of {} solutions", sols.len());
        }
    }

    #[test]
    fn noise_1px_median_rotation_error() {
        let mut rng = Rng::new(2);
        let (mut e_plain, mut e_ransac) = (Vec::new(), Vec::new());
        for trial in 0..50 {
            let (r, _t, obj, mut img) = scene(&mut rng, 500, false);
            for q in &mut img {
                q.x += rng.gauss();
                q.y += rng.gauss();
            }
            let s = solve_pnp(&obj, &img, &K).unwrap();
            e_plain.push(rot_err_deg(&s.rotation, &r));
            let params = RansacParams {
                seed: trial,
                ..Default::default()
            };
            let s = solve_pnp_ransac(&obj, &img, &K, &params).unwrap();
            e_ransac.push(rot_err_deg(&s.rotation, &r));
        }
        let (mp, mr) = (median(e_plain), median(e_ransac));
        assert!(mp < 0.2, "solve_pnp median {mp}");
        assert!(mr < 0.2, "ransac median {mr}");
    }

    #[test]
    fn outliers_30_percent() {
        let mut rng = Rng::new(3);
        let mut errs = Vec::new();
        for trial in 0..30 {
            let n = 1000;
            let (r, t, obj, mut img) = scene(&mut rng, n, trial % 5 == 4);
            let mut is_out = vec![false; n];
            for (i, q) in img.iter_mut().enumerate() {
                if rng.uniform() < 0.3 {
                    *q = Point2::new(rng.range(0.0, 800.0), rng.range(0.0, 800.0));
                    is_out[i] = true;
                } else {
                    q.x += rng.gauss();
                    q.y += rng.gauss();
                }
            }
            let params = RansacParams {
                seed: trial as u64,
                ..Default::default()
            };
            let s = solve_pnp_ransac(&obj, &img, &K, &params).unwrap();
            let e = rot_err_deg(&s.rotation, &r);
            // Oracle: maximum-likelihood fit on the true inliers only.
            let ti: Vec<Point3<f64>> = (0..n).filter(|&i| !is_out[i]).map(|i| obj[i]).collect();
            let tq: Vec<Point2<f64>> = (0..n).filter(|&i| !is_out[i]).map(|i| img[i]).collect();
            let oracle = solve_pnp(&ti, &tq, &K).unwrap();
            let eo = rot_err_deg(&s.rotation, &oracle.rotation);
            assert!(eo < 0.05, "trial {trial}: {eo} deg from the oracle fit");
            // The ML error itself occasionally exceeds 0.5 deg for distant,
            // oblique poses, so the absolute bound is on the median; each
            // trial must match the oracle fit.
            assert!(e < 1.0, "trial {trial}: rotation error {e}");
            errs.push(e);
            assert!(
                (s.translation - t).norm() < 0.02 * t.z,
                "trial {trial}: translation"
            );
            let n_out = is_out.iter().filter(|&&o| o).count();
            let kept_out = s.inliers.iter().filter(|&&i| is_out[i]).count();
            // Uniform outliers landing within 8 px of their true projection
            // are indistinguishable from inliers; allow a few.
            assert!(
                kept_out * 10 < n_out,
                "trial {trial}: {kept_out}/{n_out} outliers kept"
            );
            let n_in = n - n_out;
            let kept_in = s.inliers.len() - kept_out;
            assert!(kept_in * 100 >= n_in * 98, "trial {trial}: inliers lost");
        }
        let m = median(errs);
        assert!(m < 0.2, "median rotation error {m}");
    }

    #[test]
    fn error_cases() {
        let mut rng = Rng::new(4);
        let (_r, _t, obj, img) = scene(&mut rng, 10, false);
        let p = RansacParams::default();
        let too_few = PnpError::TooFewPoints {
            given: 3,
            needed: 4,
        };
        assert_eq!(solve_pnp(&obj[..3], &img[..3], &K).unwrap_err(), too_few);
        assert_eq!(
            solve_pnp_ransac(&obj[..3], &img[..3], &K, &p).unwrap_err(),
            too_few
        );
        let mism = PnpError::LengthMismatch {
            object: 10,
            image: 9,
        };
        assert_eq!(solve_pnp(&obj, &img[..9], &K).unwrap_err(), mism);
        assert_eq!(solve_pnp_ransac(&obj, &img[..9], &K, &p).unwrap_err(), mism);

        let mut bad = obj.clone();
        bad[5].y = f64::NAN;
        assert_eq!(
            solve_pnp(&bad, &img, &K).unwrap_err(),
            PnpError::NonFinite { index: 5 }
        );
        // RANSAC leaves non-finite correspondences out (nan_points_are_dropped...);
        // with fewer than 4 finite ones left it says so.
        let mut bad_img = img.clone();
        for q in &mut bad_img[..7] {
            q.x = f64::INFINITY;
        }
        let e = solve_pnp_ransac(&obj, &bad_img, &K, &p).unwrap_err();
        assert_eq!(
            e,
            PnpError::TooFewFinite {
                given: 10,
                finite: 3,
                needed: 4
            }
        );
        assert!(e.to_string().contains("3 of the 10"), "{e}");

        let collinear: Vec<Point3<f64>> = (0..10)
            .map(|i| Point3::new(0.01 * i as f64, 0.02 * i as f64, 0.003 * i as f64))
            .collect();
        for e in [
            solve_pnp(&collinear, &img, &K).unwrap_err(),
            solve_pnp_ransac(&collinear, &img, &K, &p).unwrap_err(),
        ] {
            assert!(matches!(e, PnpError::Degenerate(_)), "{e}");
        }
        let coincident = vec![Point3::new(0.1, 0.2, 0.3); 10];
        for e in [
            solve_pnp(&coincident, &img, &K).unwrap_err(),
            solve_pnp_ransac(&coincident, &img, &K, &p).unwrap_err(),
        ] {
            assert_eq!(e, PnpError::Degenerate("all object points coincide"));
        }

        // Pure noise: no hypothesis can reach 4 inliers with a tiny threshold.
        let noise: Vec<Point2<f64>> = (0..10)
            .map(|_| Point2::new(rng.range(0.0, 800.0), rng.range(0.0, 800.0)))
            .collect();
        let strict = RansacParams {
            reprojection_threshold_px: 1e-3,
            ..Default::default()
        };
        assert!(matches!(
            solve_pnp_ransac(&obj, &noise, &K, &strict).unwrap_err(),
            PnpError::Degenerate(_)
        ));
        assert!(!PnpError::Degenerate("x").to_string().is_empty());
    }

    #[test]
    fn nan_points_are_dropped_and_the_pose_is_the_one_without_them() {
        let mut rng = Rng::new(11);
        let (r, t, obj, img) = scene(&mut rng, 100, false);
        let img: Vec<Point2<f64>> = img
            .iter()
            .map(|q| q + Vector2::new(rng.gauss(), rng.gauss()))
            .collect();
        let p = RansacParams::default();
        let clean = solve_pnp_ransac(&obj, &img, &K, &p).unwrap();
        assert_eq!(clean.non_finite_dropped, 0);
        for (bad_object, at) in [(false, 0usize), (true, 37), (false, 99)] {
            let (mut o, mut q) = (obj.clone(), img.clone());
            if bad_object {
                o[at].z = f64::NAN;
            } else {
                q[at].y = f64::NAN;
            }
            let s = solve_pnp_ransac(&o, &q, &K, &p).unwrap();
            assert_eq!(s.non_finite_dropped, 1);
            // The same as solving without that point at all ...
            let (mut o2, mut q2) = (obj.clone(), img.clone());
            o2.remove(at);
            q2.remove(at);
            let without = solve_pnp_ransac(&o2, &q2, &K, &p).unwrap();
            assert!(rot_err_deg(&s.rotation, &without.rotation) < 1e-9);
            assert!((s.translation - without.translation).norm() < 1e-12);
            // ... its inliers in the caller's indexing: the point's index is absent and
            // every other index is shifted back past it ...
            assert!(!s.inliers.contains(&at));
            let mapped: Vec<usize> = without
                .inliers
                .iter()
                .map(|&i| if i >= at { i + 1 } else { i })
                .collect();
            assert_eq!(s.inliers, mapped);
            assert_eq!(s.inliers.len(), 99);
            // ... and close to the true pose and to the solution with the point intact.
            assert!(rot_err_deg(&s.rotation, &r) < 1.0);
            assert!((s.translation - t).norm() < 0.02);
            assert!(rot_err_deg(&s.rotation, &clean.rotation) < 0.1);
        }
        // solve_pnp (least squares on all points) still refuses them, naming the first.
        let mut bad = img.clone();
        bad[3].x = f64::NAN;
        assert_eq!(
            solve_pnp(&obj, &bad, &K).unwrap_err(),
            PnpError::NonFinite { index: 3 }
        );
    }

    #[test]
    fn refine_pose_converges_from_perturbed_pose() {
        let mut rng = Rng::new(5);
        for _ in 0..20 {
            let (r, t, obj, img) = scene(&mut rng, 50, false);
            let dw = Vector3::new(rng.gauss(), rng.gauss(), rng.gauss()) * 5f64.to_radians();
            let r0 = Rotation3::new(dw) * r;
            let t0 = t + Vector3::new(rng.gauss(), rng.gauss(), rng.gauss()) * 0.02;
            assert!(rot_err_deg(&r0, &r) > 1.0);
            let (r1, t1) = refine_pose(&obj, &img, &K, r0, t0, 50);
            assert!(rot_err_deg(&r1, &r) < 1e-7);
            assert!((t1 - t).norm() < 1e-9);
        }
    }

    #[test]
    fn deterministic_for_fixed_seed_and_isometry_matches() {
        let mut rng = Rng::new(6);
        let (_r, _t, obj, mut img) = scene(&mut rng, 100, false);
        for q in img.iter_mut().step_by(3) {
            *q = Point2::new(rng.range(0.0, 800.0), rng.range(0.0, 800.0));
        }
        let p = RansacParams {
            seed: 42,
            ..Default::default()
        };
        let a = solve_pnp_ransac(&obj, &img, &K, &p).unwrap();
        let b = solve_pnp_ransac(&obj, &img, &K, &p).unwrap();
        assert_eq!(a, b);
        let iso = a.isometry();
        let i = a.inliers[0];
        let q = reproject(&K, &iso, &obj[i]);
        assert!((q - img[i]).norm() < 8.0);
    }

    #[test]
    fn adaptive_iteration_count_and_cap() {
        let mut rng = Rng::new(8);
        let (_r, _t, obj, mut img) = scene(&mut rng, 400, false);
        for q in &mut img {
            q.x += rng.gauss();
            q.y += rng.gauss();
        }
        let s = solve_pnp_ransac(&obj, &img, &K, &RansacParams::default()).unwrap();
        assert!(
            s.iterations <= 5,
            "{} iterations without outliers",
            s.iterations
        );
        for q in img.iter_mut().step_by(2) {
            *q = Point2::new(rng.range(0.0, 800.0), rng.range(0.0, 800.0));
        }
        // 50% outliers: n = log(0.01) / log(1 - 0.5^3) ≈ 35 samples.
        let s = solve_pnp_ransac(&obj, &img, &K, &RansacParams::default()).unwrap();
        assert!((10..=100).contains(&s.iterations), "{}", s.iterations);
        let capped = RansacParams {
            max_iterations: 7,
            ..Default::default()
        };
        let s = solve_pnp_ransac(&obj, &img, &K, &capped).unwrap();
        assert!(s.iterations <= 7);
    }

    #[test]
    fn planar_points_with_noise() {
        let mut rng = Rng::new(9);
        let mut errs = Vec::new();
        for trial in 0..20 {
            let (r, _t, obj, mut img) = scene(&mut rng, 300, true);
            for q in &mut img {
                q.x += rng.gauss();
                q.y += rng.gauss();
            }
            let a = solve_pnp(&obj, &img, &K).unwrap();
            let p = RansacParams {
                seed: trial,
                ..Default::default()
            };
            let b = solve_pnp_ransac(&obj, &img, &K, &p).unwrap();
            // Both reach the same (flat, planar) optimum; LM stops within a
            // small fraction of the estimate's standard deviation.
            assert!(rot_err_deg(&a.rotation, &b.rotation) < 0.05);
            assert!((a.rms_reprojection_error_px - b.rms_reprojection_error_px).abs() < 1e-3);
            errs.push(rot_err_deg(&a.rotation, &r));
        }
        let m = median(errs);
        assert!(m < 0.5, "planar median {m}");
    }
}

//! Levenberg-Marquardt refinement on the six pose parameters, and [`solve_pnp`]
//! (EPnP, then LM on all points).

use super::epnp::epnp;
use super::geometry::{check_geometry, sq_err, validate};
use super::problem::{Intrinsics, PnpError, PnpSolution};
use nalgebra::{Matrix3, Point2, Point3, Rotation3, Vector3, Vector6};

/// Sum of squared reprojection errors over `idx` (points behind the camera
/// count as a large constant).
pub(super) fn total_cost(
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
pub(super) fn dot(a: &[f64], b: &[f64]) -> f64 {
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
pub(super) const BLOCK: usize = 64;

/// Cost, upper triangle of JᵀJ (row-major, 21 entries) and Jᵀe at a pose.
///
/// Jacobian rows are written block-wise into column buffers, and JᵀJ is then
/// formed from column dot products (vectorisable, no register spills).
pub(super) fn linearize(
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

pub(super) fn lm(
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

pub(super) fn rms(
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
pub(super) const SUBSET_SIZE: usize = 128;

/// Number of LM iterations used by the solvers.
pub(super) const LM_ITERATIONS: usize = 20;

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

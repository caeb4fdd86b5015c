//! The MSAC RANSAC loop of [`solve_pnp_ransac`] (P3P hypotheses, then LM on the
//! inliers).

use super::geometry::{check_geometry, nearest_rotation, sq_err, validate};
use super::p3p::p3p;
use super::problem::{Intrinsics, MIN_POINTS, PnpError, PnpSolution, RansacParams};
use super::refine::{LM_ITERATIONS, SUBSET_SIZE, lm, rms};
use nalgebra::{Matrix3, Point2, Point3, Rotation3, Vector3};

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
pub(super) fn solve_finite_ransac(
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

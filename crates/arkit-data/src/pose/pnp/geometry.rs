//! Input checks and the geometry every stage shares: projection, squared
//! reprojection error, the nearest rotation and absolute orientation.

use super::problem::{Intrinsics, MIN_POINTS, PnpError};
use nalgebra::{Matrix3, Point2, Point3, SymmetricEigen, Vector2, Vector3};

pub(super) fn validate(object: &[Point3<f64>], image: &[Point2<f64>]) -> Result<(), PnpError> {
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
pub(super) type Pca = (Vector3<f64>, Vector3<f64>, Matrix3<f64>);

pub(super) fn pca(object: &[Point3<f64>]) -> Pca {
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
pub(super) fn check_geometry(object: &[Point3<f64>]) -> Result<Pca, PnpError> {
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

#[inline]
pub(super) fn project(
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
pub(super) fn sq_err(
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
pub(super) fn nearest_rotation(m: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let d = (u * vt).determinant().signum();
    u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * vt
}

/// Rigid alignment (no scale) `cam ≈ R * obj + t`, least squares (Kabsch).
pub(super) fn absolute_orientation(
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

//! P3P after Persson & Nordberg's "Lambda Twist" (ECCV 2018): RANSAC's minimal solver.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

/// One real root of `c3 x³ + c2 x² + c1 x + c0` (falls back to the quadratic).
pub(super) fn cubic_real_root(c3: f64, c2: f64, c1: f64, c0: f64) -> Option<f64> {
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
pub(super) fn p3p(
    y: [Vector3<f64>; 3],
    x: [Vector3<f64>; 3],
    out: &mut Vec<(Matrix3<f64>, Vector3<f64>)>,
) {
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
pub(super) fn frame_align(
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

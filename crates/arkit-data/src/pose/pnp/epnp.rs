//! EPnP (Lepetit, Moreno-Noguer & Fua, IJCV 2009): the closed-form all-points
//! initialiser.

use super::geometry::{Pca, absolute_orientation, sq_err};
use super::problem::Intrinsics;
use nalgebra::{DMatrix, Matrix3, Point2, Point3, SymmetricEigen, Vector3};

/// EPnP (Lepetit et al., 2009) from all points: control points, the barycentric system,
/// its null space and the best of the one-to-three-vector solutions. Long (over 150
/// lines) on purpose: the steps follow the paper's sections in order and share their
/// intermediate matrices; split, each part would take and return most of them.
pub(super) fn epnp(
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

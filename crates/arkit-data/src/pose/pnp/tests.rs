use super::p3p::p3p;
use super::problem::{Intrinsics, PnpError, RansacParams, reproject};
use super::ransac::solve_pnp_ransac;
use super::refine::{refine_pose, solve_pnp};
use nalgebra::{
    Isometry3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3,
};

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

//! Euler angles against values SciPy itself computed (fixtures/scipy, made by the
//! script beside them), including gimbal lock, where SciPy's rule decides the split
//! between yaw and roll.

use arkit_core::conventions::EulerAngles;
use nalgebra::{Matrix3, Rotation3};

#[test]
fn euler_angles_match_scipy_as_euler_yxz() {
    let path = crate::support::workspace().join("fixtures/scipy/euler_yxz_golden.csv");
    let text = std::fs::read_to_string(path).expect("fixture present");
    let mut rows = 0;
    let mut worst: f64 = 0.0;
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let v: Vec<f64> = line.split(',').map(|s| s.parse().unwrap()).collect();
        assert_eq!(v.len(), 12);
        let rt3 = Matrix3::from_row_slice(&v[..9]);
        let r = Rotation3::from_matrix_unchecked(rt3.transpose());
        let e = EulerAngles::from_rotation(&r);
        for (ours, theirs) in [(e.yaw_deg, v[9]), (e.pitch_deg, v[10]), (e.roll_deg, v[11])] {
            // Angles are equal modulo 360 (+180 and -180 are the same angle).
            let d = (ours - theirs + 180.0).rem_euclid(360.0) - 180.0;
            worst = worst.max(d.abs());
            assert!(
                d.abs() < 1e-6,
                "row {rows}: ours {e:?}, scipy {:?}",
                &v[9..]
            );
        }
        rows += 1;
    }
    assert!(rows >= 260, "{rows} rows");
    eprintln!("{rows} rotations, largest difference from SciPy {worst:.2e} degrees");
}

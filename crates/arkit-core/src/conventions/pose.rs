//! The head pose: the release's row-vector `R_t`, OpenCV's `(R, t)`, and Euler angles.
//!
//! A [`Pose`] maps a point of the canonical face frame (metres, y up, the face looking
//! toward +z) into the OpenGL camera frame (x right, y up, the camera looking down -z).
//! Internally it is an [`Isometry3`] in column-vector form, `p_cam = R p + t`; the
//! release stores the same map as the transposed 4x4 `R_t`:
//!
//! ```text
//! [xc yc zc 1] = [x y z 1] @ R_t,     R_t = [[R^T, 0], [t^T, 1]]
//! ```
//!
//! so `R_t[:3,:3]` is `R^T` and `R_t[3,:3]` is the translation in metres; `tz < 0` for
//! every face in front of the camera.
//!
//! Euler angles are those of the release and its official evaluation,
//! `Rotation.from_matrix(R_t[:3,:3].T).as_euler('yxz', degrees=True)` in SciPy:
//! extrinsic rotations about y (yaw), then x (pitch), then z (roll), so
//! `R = Rz(roll) Rx(pitch) Ry(yaw)`. [`Pose::euler`] reproduces SciPy's algorithm
//! (matrix to quaternion, then the quaternion-to-Euler method of Bernardes and Viollet,
//! 2022), including its choice at gimbal lock (|pitch| within 1e-7 rad of 90 degrees:
//! roll is set to zero and yaw absorbs the rest), so values match SciPy to rounding.

use crate::error::{Error, Result};
use nalgebra::{
    Isometry3, Matrix3, Matrix4, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};

/// Largest deviation of `R^T R` from the identity accepted for a rotation read from a
/// file. The release stores float32 matrices, whose rounding is about 1e-7.
pub const ORTHONORMAL_TOLERANCE: f64 = 1e-4;

/// Yaw, pitch and roll in degrees, in the release's 'yxz' extrinsic convention.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EulerAngles {
    /// Rotation about the camera's y axis (turning the head left/right), degrees.
    pub yaw_deg: f64,
    /// Rotation about the x axis (nodding), degrees.
    pub pitch_deg: f64,
    /// Rotation about the z axis (tilting toward a shoulder), degrees.
    pub roll_deg: f64,
}

impl EulerAngles {
    /// Angles in degrees.
    pub fn new(yaw_deg: f64, pitch_deg: f64, roll_deg: f64) -> Self {
        EulerAngles {
            yaw_deg,
            pitch_deg,
            roll_deg,
        }
    }

    /// The rotation `Rz(roll) Rx(pitch) Ry(yaw)` (SciPy `from_euler('yxz', ...)`).
    pub fn to_rotation(&self) -> Rotation3<f64> {
        let ry = Rotation3::from_axis_angle(&Vector3::y_axis(), self.yaw_deg.to_radians());
        let rx = Rotation3::from_axis_angle(&Vector3::x_axis(), self.pitch_deg.to_radians());
        let rz = Rotation3::from_axis_angle(&Vector3::z_axis(), self.roll_deg.to_radians());
        rz * rx * ry
    }

    /// The angles SciPy's `as_euler('yxz')` returns for `rotation` (see module docs).
    pub fn from_rotation(rotation: &Rotation3<f64>) -> Self {
        let q = scipy_quaternion(rotation.matrix());
        let [yaw, pitch, roll] = tait_bryan_from_quaternion(q, [1, 0, 2]);
        EulerAngles::new(yaw.to_degrees(), pitch.to_degrees(), roll.to_degrees())
    }

    /// The release's `euler_angles` key order: `[pitch, yaw, roll]` in degrees.
    pub fn to_release_order(&self) -> [f64; 3] {
        [self.pitch_deg, self.yaw_deg, self.roll_deg]
    }
}

/// Quaternion `[x, y, z, w]` of a rotation matrix as SciPy's `from_matrix` computes it
/// (the largest of the diagonal and the trace picks the stable formula).
pub(super) fn scipy_quaternion(m: &Matrix3<f64>) -> [f64; 4] {
    let trace = m[(0, 0)] + m[(1, 1)] + m[(2, 2)];
    let decision = [m[(0, 0)], m[(1, 1)], m[(2, 2)], trace];
    let mut choice = 0;
    for (k, &v) in decision.iter().enumerate() {
        if v > decision[choice] {
            choice = k;
        }
    }
    let mut q = [0.0; 4];
    if choice != 3 {
        let i = choice;
        let j = (i + 1) % 3;
        let k = (j + 1) % 3;
        q[i] = 1.0 - trace + 2.0 * m[(i, i)];
        q[j] = m[(j, i)] + m[(i, j)];
        q[k] = m[(k, i)] + m[(i, k)];
        q[3] = m[(k, j)] - m[(j, k)];
    } else {
        q[0] = m[(2, 1)] - m[(1, 2)];
        q[1] = m[(0, 2)] - m[(2, 0)];
        q[2] = m[(1, 0)] - m[(0, 1)];
        q[3] = 1.0 + trace;
    }
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    q.map(|v| v / norm)
}

/// Extrinsic Tait-Bryan angles (radians) about the axes `axes` (0 = x, 1 = y, 2 = z) of
/// the quaternion `q = [x, y, z, w]`, by the direct method of Bernardes and Viollet
/// (2022), with SciPy's gimbal-lock rule.
pub(super) fn tait_bryan_from_quaternion(q: [f64; 4], axes: [usize; 3]) -> [f64; 3] {
    use std::f64::consts::PI;
    let [i, j, k] = axes;
    let sign = ((i as i64 - j as i64) * (j as i64 - k as i64) * (k as i64 - i as i64) / 2) as f64;
    let a = q[3] - q[j];
    let b = q[i] + q[k] * sign;
    let c = q[j] + q[3];
    let d = q[k] * sign - q[i];

    const EPS: f64 = 1e-7;
    let half_sum = b.atan2(a);
    let half_diff = d.atan2(c);
    let mut angles = [0.0; 3];
    angles[1] = 2.0 * c.hypot(d).atan2(a.hypot(b));
    let near_zero = angles[1].abs() <= EPS;
    let near_pi = (angles[1] - PI).abs() <= EPS;
    if near_zero {
        angles[0] = 2.0 * half_sum;
    } else if near_pi {
        angles[0] = -2.0 * half_diff;
    } else {
        angles[0] = half_sum - half_diff;
        angles[2] = half_sum + half_diff;
    }
    angles[2] *= sign;
    angles[1] -= PI / 2.0;
    angles.map(|v| (v + PI).rem_euclid(2.0 * PI) - PI)
}

/// A rigid head pose: canonical face frame to OpenGL camera frame. See the module docs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// `p_cam = rotation * p + translation`, column-vector form, metres.
    pub face_to_camera: Isometry3<f64>,
}

impl Pose {
    /// A pose from its rotation (column-vector form) and translation in metres.
    pub fn new(rotation: Rotation3<f64>, translation_m: Vector3<f64>) -> Self {
        Pose {
            face_to_camera: Isometry3::from_parts(
                Translation3::from(translation_m),
                UnitQuaternion::from_rotation_matrix(&rotation),
            ),
        }
    }

    /// The pose of given Euler angles (degrees, 'yxz') and translation (metres).
    pub fn from_euler(angles: EulerAngles, translation_m: Vector3<f64>) -> Self {
        Pose::new(angles.to_rotation(), translation_m)
    }

    /// Reads the release's row-vector `R_t` (row-major, 16 numbers) after checking it
    /// with [`Pose::check_release_rt`].
    pub fn from_release_rt(rt: &[f64; 16]) -> Result<Self> {
        Pose::check_release_rt(rt)?;
        let m = Matrix4::from_row_slice(rt);
        let r_rows = m.fixed_view::<3, 3>(0, 0).transpose();
        // Re-orthonormalise float32 rounding so the isometry is exact.
        let rotation = Rotation3::from_matrix(&r_rows);
        let t = Vector3::new(m[(3, 0)], m[(3, 1)], m[(3, 2)]);
        Ok(Pose::new(rotation, t))
    }

    /// Reads a row-vector `R_t` (row-major, 16 numbers) that need not put the face in
    /// front of the camera: the checks of `Pose::check_rigid_rt` only. The
    /// conversions to other tools' conventions accept such poses.
    pub fn from_rigid_rt(rt: &[f64; 16]) -> Result<Self> {
        Pose::check_rigid_rt(rt)?;
        let m = Matrix4::from_row_slice(rt);
        let rotation = Rotation3::from_matrix(&m.fixed_view::<3, 3>(0, 0).transpose());
        Ok(Pose::new(
            rotation,
            Vector3::new(m[(3, 0)], m[(3, 1)], m[(3, 2)]),
        ))
    }

    /// Checks that `rt` is a pose the release's projection can use: the checks of
    /// `Pose::check_rigid_rt` and `tz < 0` (the face in front of the camera).
    pub fn check_release_rt(rt: &[f64; 16]) -> Result<()> {
        Pose::check_rigid_rt(rt)?;
        if rt[14] >= 0.0 {
            return Err(Error::invalid(
                "R_t",
                format!(
                    "tz = {} m must be negative (the camera looks down -z)",
                    rt[14]
                ),
            ));
        }
        Ok(())
    }

    /// Checks that `rt` is a rigid row-vector transform: finite values, last column
    /// `(0, 0, 0, 1)` and an orthonormal right-handed rotation (within
    /// [`ORTHONORMAL_TOLERANCE`]).
    pub(crate) fn check_rigid_rt(rt: &[f64; 16]) -> Result<()> {
        if let Some(i) = rt.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                "R_t",
                format!("non-finite value {} at [{}][{}]", rt[i], i / 4, i % 4),
            ));
        }
        let last_col = [rt[3], rt[7], rt[11], rt[15]];
        if (last_col[0].abs() + last_col[1].abs() + last_col[2].abs() + (last_col[3] - 1.0).abs())
            > 1e-6
        {
            return Err(Error::invalid(
                "R_t",
                format!("last column must be (0, 0, 0, 1) in row-vector form, found {last_col:?}"),
            ));
        }
        let r = Matrix3::new(
            rt[0], rt[1], rt[2], rt[4], rt[5], rt[6], rt[8], rt[9], rt[10],
        );
        let deviation = (r.transpose() * r - Matrix3::identity()).abs().max();
        if deviation > ORTHONORMAL_TOLERANCE {
            return Err(Error::invalid(
                "R_t",
                format!("rotation is not orthonormal (max |R^T R - I| = {deviation:.2e})"),
            ));
        }
        if r.determinant() <= 0.0 {
            return Err(Error::invalid(
                "R_t",
                "rotation is a reflection (determinant <= 0)",
            ));
        }
        Ok(())
    }

    /// The release's row-vector `R_t`, row-major.
    pub fn to_release_rt(&self) -> [f64; 16] {
        let m = self.release_matrix();
        let mut out = [0.0; 16];
        for r in 0..4 {
            for c in 0..4 {
                out[r * 4 + c] = m[(r, c)];
            }
        }
        out
    }

    /// The release's row-vector `R_t` as a matrix (`[x y z 1] @ R_t`).
    pub fn release_matrix(&self) -> Matrix4<f64> {
        self.face_to_camera.to_homogeneous().transpose()
    }

    /// A pose from OpenCV's `(R, t)`: `x_cv = R X + t`, camera looking down +z with y
    /// down. The release form is `[[R^T, 0], [t^T, 1]] @ diag(1, -1, -1, 1)`.
    pub fn from_opencv(r: &Rotation3<f64>, t: &Vector3<f64>) -> Self {
        let flip = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        let rotation = Rotation3::from_matrix_unchecked(flip * r.matrix());
        Pose::new(rotation, flip * t)
    }

    /// OpenCV's `(R, t)` of this pose (inverse of [`Pose::from_opencv`]).
    pub fn to_opencv(&self) -> (Rotation3<f64>, Vector3<f64>) {
        let flip = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        let r = self.rotation();
        (
            Rotation3::from_matrix_unchecked(flip * r.matrix()),
            flip * self.translation_m(),
        )
    }

    /// The rotation part (column-vector form: `R = R_t[:3,:3]^T`).
    pub fn rotation(&self) -> Rotation3<f64> {
        self.face_to_camera.rotation.to_rotation_matrix()
    }

    /// The translation in metres (`R_t[3,:3]`).
    pub fn translation_m(&self) -> Vector3<f64> {
        self.face_to_camera.translation.vector
    }

    /// Yaw, pitch, roll exactly as the release computes them (see module docs).
    pub fn euler(&self) -> EulerAngles {
        EulerAngles::from_rotation(&self.rotation())
    }

    /// A canonical point in camera coordinates (OpenGL frame, metres).
    pub fn to_camera(&self, p: &Point3<f64>) -> Point3<f64> {
        self.face_to_camera * p
    }

    /// The geodesic angle between the rotations of two poses, in degrees (the angle of
    /// `R_a^T R_b`), in [0, 180].
    pub fn rotation_angle_to_deg(&self, other: &Pose) -> f64 {
        geodesic_angle_deg(&self.rotation(), &other.rotation())
    }

    /// Checks that the pose can be projected: finite, orthonormal, `tz < 0`.
    pub fn check(&self) -> Result<()> {
        Pose::check_release_rt(&self.to_release_rt())
    }
}

/// The geodesic distance between two rotations, in degrees: the rotation angle of
/// `a^T b`, computed robustly from the trace (clamped) so identical rotations give 0.
pub fn geodesic_angle_deg(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
    let rel = a.transpose() * b;
    // Use the quaternion form: angle = 2 atan2(|v|, |w|) is accurate near 0 and 180.
    let q = UnitQuaternion::from_rotation_matrix(&rel);
    let v = q.imag().norm();
    (2.0 * v.atan2(q.w.abs())).to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn yaw_alone_rotates_about_y() {
        // yaw 90: Ry(90) maps +z to +x.
        let r = EulerAngles::new(90.0, 0.0, 0.0).to_rotation();
        let p = r * Vector3::new(0.0, 0.0, 1.0);
        assert!((p - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
        // pitch 90: Rx(90) maps +z to -y (the face looks down).
        let r = EulerAngles::new(0.0, 90.0, 0.0).to_rotation();
        let p = r * Vector3::new(0.0, 0.0, 1.0);
        assert!((p - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn composition_order_is_extrinsic_yxz() {
        // With yaw 90 then roll 90 (extrinsic): +z -> +x (yaw) -> +y (roll about z).
        let r = EulerAngles::new(90.0, 0.0, 90.0).to_rotation();
        let p = r * Vector3::new(0.0, 0.0, 1.0);
        assert!((p - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12, "{p}");
    }

    #[test]
    fn release_rt_layout_is_row_vector() {
        let pose = Pose::from_euler(
            EulerAngles::new(30.0, 0.0, 0.0),
            Vector3::new(0.01, 0.02, -0.5),
        );
        let rt = pose.to_release_rt();
        // Translation in row 3, last column (0,0,0,1).
        assert_eq!(&rt[12..15], &[0.01, 0.02, -0.5]);
        assert_eq!([rt[3], rt[7], rt[11], rt[15]], [0.0, 0.0, 0.0, 1.0]);
        // R_t[0][2] = R[2][0] = -sin(30) for Ry(30) (R[2][0] = -sin).
        assert!(close(rt[2], -0.5, 1e-12), "{}", rt[2]);
        // A point through [x y z 1] @ R_t equals R p + t.
        let p = Point3::new(0.03, -0.02, 0.07);
        let row = nalgebra::RowVector4::new(p.x, p.y, p.z, 1.0) * pose.release_matrix();
        let q = pose.to_camera(&p);
        assert!((row[0] - q.x).abs() < 1e-15 && (row[2] - q.z).abs() < 1e-15);
    }

    #[test]
    fn gimbal_lock_matches_scipy_rule() {
        // pitch exactly +90: SciPy sets roll = 0 and puts yaw - roll... into yaw.
        let r = EulerAngles::new(20.0, 90.0, 10.0).to_rotation();
        let e = EulerAngles::from_rotation(&r);
        assert!(close(e.pitch_deg, 90.0, 1e-9));
        assert_eq!(e.roll_deg, 0.0);
        // The angles still describe the same rotation.
        assert!(geodesic_angle_deg(&e.to_rotation(), &r) < 1e-6);
        let r = EulerAngles::new(20.0, -90.0, 10.0).to_rotation();
        let e = EulerAngles::from_rotation(&r);
        assert!(close(e.pitch_deg, -90.0, 1e-9));
        assert_eq!(e.roll_deg, 0.0);
        assert!(geodesic_angle_deg(&e.to_rotation(), &r) < 1e-6);
    }

    #[test]
    fn rejects_poses_that_cannot_project() {
        let good = Pose::from_euler(
            EulerAngles::new(10.0, 5.0, 0.0),
            Vector3::new(0.0, 0.0, -0.4),
        );
        let rt = good.to_release_rt();
        assert!(Pose::from_release_rt(&rt).is_ok());
        let mut bad = rt;
        bad[14] = 0.4;
        assert!(format!("{}", Pose::from_release_rt(&bad).unwrap_err()).contains("negative"));
        let mut bad = rt;
        bad[5] = f64::NAN;
        assert!(format!("{}", Pose::from_release_rt(&bad).unwrap_err()).contains("non-finite"));
        let mut bad = rt;
        bad[0] *= 1.1;
        assert!(format!("{}", Pose::from_release_rt(&bad).unwrap_err()).contains("orthonormal"));
        let mut bad = rt;
        for v in &mut bad[0..3] {
            *v = -*v;
        }
        assert!(format!("{}", Pose::from_release_rt(&bad).unwrap_err()).contains("reflection"));
        let mut bad = rt;
        bad[3] = 0.5;
        assert!(format!("{}", Pose::from_release_rt(&bad).unwrap_err()).contains("last column"));
    }

    #[test]
    fn geodesic_angle_of_known_rotations() {
        let a = EulerAngles::new(0.0, 0.0, 0.0).to_rotation();
        let b = EulerAngles::new(0.0, 0.0, 37.5).to_rotation();
        assert!(close(geodesic_angle_deg(&a, &b), 37.5, 1e-9));
        let c = EulerAngles::new(180.0, 0.0, 0.0).to_rotation();
        assert!(close(geodesic_angle_deg(&a, &c), 180.0, 1e-9));
        assert_eq!(geodesic_angle_deg(&b, &b), 0.0);
    }

    proptest! {
        #[test]
        fn euler_round_trip(yaw in -179.0f64..179.0, pitch in -89.0f64..89.0, roll in -179.0f64..179.0) {
            let e = EulerAngles::new(yaw, pitch, roll);
            let back = EulerAngles::from_rotation(&e.to_rotation());
            prop_assert!(close(back.yaw_deg, yaw, 1e-7), "{back:?}");
            prop_assert!(close(back.pitch_deg, pitch, 1e-7), "{back:?}");
            prop_assert!(close(back.roll_deg, roll, 1e-7), "{back:?}");
        }

        #[test]
        fn opencv_round_trip(yaw in -90.0f64..90.0, pitch in -70.0f64..70.0, roll in -90.0f64..90.0,
                             tx in -0.2f64..0.2, ty in -0.2f64..0.2, tz in -0.9f64..-0.3) {
            let pose = Pose::from_euler(EulerAngles::new(yaw, pitch, roll), Vector3::new(tx, ty, tz));
            let (r, t) = pose.to_opencv();
            let back = Pose::from_opencv(&r, &t);
            prop_assert!(pose.rotation_angle_to_deg(&back) < 1e-9);
            prop_assert!((pose.translation_m() - back.translation_m()).norm() < 1e-12);
            // The documented formula: R_t = [[R^T, 0], [t^T, 1]] @ diag(1, -1, -1, 1).
            let mut cv = Matrix4::identity();
            cv.fixed_view_mut::<3, 3>(0, 0).copy_from(&r.matrix().transpose());
            cv[(3, 0)] = t.x; cv[(3, 1)] = t.y; cv[(3, 2)] = t.z;
            let formula = cv * Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0));
            prop_assert!((formula - pose.release_matrix()).abs().max() < 1e-12);
            // OpenCV puts the face at positive depth.
            prop_assert!(t.z > 0.0);
        }

        #[test]
        fn release_rt_round_trip(yaw in -90.0f64..90.0, pitch in -70.0f64..70.0, roll in -90.0f64..90.0,
                                 tz in -0.9f64..-0.3) {
            let pose = Pose::from_euler(EulerAngles::new(yaw, pitch, roll), Vector3::new(0.01, -0.02, tz));
            let back = Pose::from_release_rt(&pose.to_release_rt()).unwrap();
            prop_assert!(pose.rotation_angle_to_deg(&back) < 1e-9);
            let e = back.euler();
            prop_assert!(close(e.yaw_deg, yaw, 1e-7) && close(e.pitch_deg, pitch, 1e-7) && close(e.roll_deg, roll, 1e-7));
        }
    }
}

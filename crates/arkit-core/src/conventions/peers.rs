//! The head pose in the conventions of other tools: OpenCV's rotation vector, ARKit's
//! world transforms, and the Euler angles of the official code, WCPA, TRG, 6DRepNet
//! and img2pose.
//!
//! Every conversion goes through [`Pose`] (column form `x_gl = R x + t` in the OpenGL
//! camera, the release's `R_t = [[R^T, 0], [t^T, 1]]`). `F = diag(1, -1, -1)` (a half
//! turn about x) takes the OpenGL camera (y up, looking down -z) to OpenCV's (y down,
//! looking down +z), and ARKit's face frame (y up, +z out of the face) to the frame
//! of TRG's and img2pose's models (y down, +z into the head).
//!
//! | tool | rotation, translation | angles (order, unit) |
//! |---|---|---|
//! | release / official | `R`, `t` | `[yaw, pitch, roll]` deg, 'yxz' of `R`: `R = Rz(roll) Rx(pitch) Ry(yaw)` |
//! | WCPA 2022 | as the release | `[pitch, yaw, roll]` rad, same definition |
//! | OpenCV | `rvec = log(F R)`, `tvec = F t` | none |
//! | ARKit | `face_anchor = camera * [[R, t], [0, 1]]` | none |
//! | TRG | `R' = F R F`, `t' = F t` | `[yaw, pitch, roll]` deg, 'yxz' of `R'` |
//! | 6DRepNet | `M = R^T` (`R_t[:3,:3]`) | `[pitch, yaw, roll]` deg, `M = Rz(roll) Ry(yaw) Rx(pitch)` |
//! | img2pose | `[rvec, t]` of `R' = F R F`, `t' = F t` | `[pitch, yaw, roll]` deg: `(a, -b, -c)`, `R'^T = Rz(c) Ry(b) Rx(a)` |
//!
//! **ARKit's device orientation is not modelled.** `inverse(camera.transform) *
//! faceAnchor.transform` is the face in ARKit's camera space, whose x axis runs along
//! the device's long side whatever way the device is held; no peer's code rotates it
//! for the interface orientation, and whether the release's images were rotated
//! before annotation could not be determined. [`Pose::from_arkit`] applies no such
//! rotation: for frames captured in portrait, the result may be the release's pose
//! turned by a quarter turn about the viewing axis.

use super::pose::{EulerAngles, ORTHONORMAL_TOLERANCE, Pose};
use super::pose::{scipy_quaternion, tait_bryan_from_quaternion};
use crate::error::{Error, Result};
use nalgebra::{
    Isometry3, Matrix3, Matrix4, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3,
};
use std::fmt;
use std::str::FromStr;

/// `F R F` for `F = diag(1, -1, -1)`: the entries in row 0 or column 0 (but not
/// both) change sign. Exact, and its own inverse.
fn flip_conjugate(r: &Rotation3<f64>) -> Rotation3<f64> {
    let mut m = *r.matrix();
    for k in 1..3 {
        m[(0, k)] = -m[(0, k)];
        m[(k, 0)] = -m[(k, 0)];
    }
    Rotation3::from_matrix_unchecked(m)
}

/// `F t` for `F = diag(1, -1, -1)`.
fn flip(t: &Vector3<f64>) -> Vector3<f64> {
    Vector3::new(t.x, -t.y, -t.z)
}

/// The rotation of an OpenCV rotation vector (`cv2.Rodrigues`): the axis `rvec / |rvec|`
/// and the angle `|rvec|` in radians, right-handed. Accurate for every angle, zero
/// included (computed through the unit quaternion `(cos(a/2), sin(a/2) axis)`).
pub fn rotation_from_rvec(rvec: &Vector3<f64>) -> Rotation3<f64> {
    let angle = rvec.norm();
    if angle == 0.0 {
        return Rotation3::identity();
    }
    let half = 0.5 * angle;
    // sin(a/2)/a is accurate for tiny a too (no cancellation).
    let v = rvec * (half.sin() / angle);
    UnitQuaternion::from_quaternion(Quaternion::new(half.cos(), v.x, v.y, v.z)).to_rotation_matrix()
}

/// The rotation vector of `rotation`: axis times angle, the angle in `[0, pi]`.
///
/// Computed from the rotation's quaternion (the stable formula chosen by the largest
/// of the diagonal and the trace), so it stays accurate near 0 (where `acos` of the
/// trace loses half the digits) and near pi (where the skew-symmetric part vanishes).
/// At pi both `±axis` describe the rotation; within rounding of pi (quaternion `w`
/// below 1e-15) the one whose first non-zero component is positive is returned, as
/// OpenCV does, so that a half turn has one rotation vector.
pub fn rvec_from_rotation(rotation: &Rotation3<f64>) -> Vector3<f64> {
    let [mut x, mut y, mut z, mut w] = scipy_quaternion(rotation.matrix());
    if w < 0.0 {
        (x, y, z, w) = (-x, -y, -z, -w);
    }
    let s = (x * x + y * y + z * z).sqrt();
    if s == 0.0 {
        return Vector3::zeros();
    }
    let mut v = Vector3::new(x, y, z) * (2.0 * s.atan2(w) / s);
    if w <= 1e-15 {
        let first = v.iter().copied().find(|c| *c != 0.0).unwrap_or(0.0);
        if first < 0.0 {
            v = -v;
        }
    }
    v
}

/// Checks that `m` (column form, `x' = M x`) is a rigid transform and returns it:
/// finite values, last row `(0, 0, 0, 1)`, an orthonormal right-handed rotation (within
/// [`ORTHONORMAL_TOLERANCE`]; no scale, no reflection).
pub fn check_rigid_transform(m: &Matrix4<f64>, what: &str) -> Result<Isometry3<f64>> {
    if let Some((k, v)) = m.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(Error::invalid(
            what,
            format!("non-finite value {v} at [{}][{}]", k % 4, k / 4),
        ));
    }
    let row = [m[(3, 0)], m[(3, 1)], m[(3, 2)], m[(3, 3)]];
    let off = |v: [f64; 4]| v[0].abs() + v[1].abs() + v[2].abs() + (v[3] - 1.0).abs();
    if off(row) > 1e-6 {
        let col = [m[(0, 3)], m[(1, 3)], m[(2, 3)], m[(3, 3)]];
        let hint = if off(col) <= 1e-6 {
            " (it looks transposed: a simd_float4x4 is stored column by column; read its 16 \
             numbers as columns, or transpose it)"
        } else {
            ""
        };
        return Err(Error::invalid(
            what,
            format!(
                "not a rigid transform: the last row must be (0, 0, 0, 1), found {row:?}{hint}"
            ),
        ));
    }
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
    let deviation = (r.transpose() * r - Matrix3::identity()).abs().max();
    if deviation > ORTHONORMAL_TOLERANCE {
        return Err(Error::invalid(
            what,
            format!(
                "not a rigid transform: the rotation is not orthonormal (max |R^T R - I| = \
                 {deviation:.2e}; a scaled transform is not supported)"
            ),
        ));
    }
    if r.determinant() <= 0.0 {
        return Err(Error::invalid(
            what,
            "not a rigid transform: the rotation is a reflection (determinant <= 0; ARKit \
             gives left-handed face anchors when the rear camera tracks faces, which is not \
             supported)",
        ));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r)),
    ))
}

impl Pose {
    /// A pose from OpenCV's rotation vector and translation (`cv2.solvePnP`'s `rvec`,
    /// `tvec`: `x_cv = Rodrigues(rvec) X + tvec`, camera looking down +z, y down).
    pub fn from_opencv_rvec(rvec: &Vector3<f64>, tvec: &Vector3<f64>) -> Self {
        Pose::from_opencv(&rotation_from_rvec(rvec), tvec)
    }

    /// OpenCV's `(rvec, tvec)` of this pose (inverse of [`Pose::from_opencv_rvec`]);
    /// the rotation angle `|rvec|` is in `[0, pi]`.
    pub fn to_opencv_rvec(&self) -> (Vector3<f64>, Vector3<f64>) {
        let (r, t) = self.to_opencv();
        (rvec_from_rotation(&r), t)
    }

    /// The pose of ARKit's `faceAnchor.transform` seen from `camera.transform` (both
    /// world transforms in column form, translation in the last column; a
    /// `simd_float4x4` dumped as its 16 floats is column-major:
    /// `Matrix4::from_column_slice`). The pose is `inverse(camera) * face_anchor`: ARKit's
    /// camera space is the release's OpenGL camera (x right, y up, looking down -z) and
    /// its face frame the release's canonical frame.
    ///
    /// No device-orientation rotation is applied (see the module docs). Both matrices
    /// must be rigid ([`check_rigid_transform`]); the face need not be in front of the
    /// camera (check with [`Pose::check`]).
    pub fn from_arkit(face_anchor: &Matrix4<f64>, camera: &Matrix4<f64>) -> Result<Self> {
        let face = check_rigid_transform(face_anchor, "face anchor transform")?;
        let camera = check_rigid_transform(camera, "camera transform")?;
        Ok(Pose {
            face_to_camera: camera.inverse() * face,
        })
    }

    /// The face anchor transform (world, column form) of this pose seen from
    /// `camera` (a camera transform as in [`Pose::from_arkit`]): `camera * pose`.
    pub fn to_arkit(&self, camera: &Matrix4<f64>) -> Result<Matrix4<f64>> {
        let camera = check_rigid_transform(camera, "camera transform")?;
        Ok((camera * self.face_to_camera).to_homogeneous())
    }

    /// A pose from TRG's rotation and translation (column form, `R' = F R F`,
    /// `t' = F t`: OpenCV's camera, a model frame with y down and z into the head).
    pub fn from_trg(rotation: &Rotation3<f64>, translation_m: &Vector3<f64>) -> Self {
        Pose::new(flip_conjugate(rotation), flip(translation_m))
    }

    /// TRG's rotation and translation of this pose (column form; its row-vector `R_t`
    /// is `[[R'^T, 0], [t'^T, 1]]`, what its ARKitFace loader makes of the release's).
    pub fn to_trg(&self) -> (Rotation3<f64>, Vector3<f64>) {
        (
            flip_conjugate(&self.rotation()),
            flip(&self.translation_m()),
        )
    }

    /// A pose from img2pose's 6-vector `[rvec, t]` (OpenCV's camera, the model frame
    /// of its reference points: y down, z into the head).
    pub fn from_img2pose(dof: &[f64; 6]) -> Self {
        let r = rotation_from_rvec(&Vector3::new(dof[0], dof[1], dof[2]));
        Pose::from_trg(&r, &Vector3::new(dof[3], dof[4], dof[5]))
    }

    /// img2pose's 6-vector `[rvec, t]` of this pose (inverse of
    /// [`Pose::from_img2pose`]), the rotation angle in `[0, pi]`.
    pub fn to_img2pose(&self) -> [f64; 6] {
        let (r, t) = self.to_trg();
        let v = rvec_from_rotation(&r);
        [v.x, v.y, v.z, t.x, t.y, t.z]
    }
}

/// The unit of a convention's angles.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum AngleUnit {
    /// Degrees.
    Degrees,
    /// Radians.
    Radians,
}

/// Whose Euler angles: each tool's definition, order and unit (see the module docs and
/// docs/conventions.md). Parses from and prints as [`AngleConvention::name`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum AngleConvention {
    /// The release and its official evaluation: `[yaw, pitch, roll]` in degrees,
    /// SciPy's 'yxz' of `R_t[:3,:3]^T` ([`EulerAngles`]).
    Official,
    /// WCPA 2022 track 2's labels: the same angles as `[pitch, yaw, roll]` in radians.
    Wcpa,
    /// TRG's evaluation: `[yaw, pitch, roll]` in degrees, SciPy's 'yxz' of its rotation
    /// `F R F`; equal to the official `(-yaw, pitch, -roll)`.
    Trg,
    /// 6DRepNet's formula on `R_t[:3,:3]`: `[pitch, yaw, roll]` in degrees with
    /// `R_t[:3,:3] = Rz(roll) Ry(yaw) Rx(pitch)`, and its branch (roll = 0) when
    /// `sqrt(R00^2 + R10^2) < 1e-6`.
    SixDRepNet,
    /// img2pose's AFLW conversion: `[pitch, yaw, roll]` in degrees, `(a, -b, -c)` for
    /// SciPy's `as_euler('xyz')` `(a, b, c)` of the transpose of its rotation `F R F`.
    Img2pose,
}

impl AngleConvention {
    /// Every convention, in the order of the docs.
    pub const ALL: [AngleConvention; 5] = [
        AngleConvention::Official,
        AngleConvention::Wcpa,
        AngleConvention::Trg,
        AngleConvention::SixDRepNet,
        AngleConvention::Img2pose,
    ];

    /// The name that [`FromStr`] parses: `official`, `wcpa`, `trg`, `6drepnet`,
    /// `img2pose`.
    pub fn name(self) -> &'static str {
        match self {
            AngleConvention::Official => "official",
            AngleConvention::Wcpa => "wcpa",
            AngleConvention::Trg => "trg",
            AngleConvention::SixDRepNet => "6drepnet",
            AngleConvention::Img2pose => "img2pose",
        }
    }

    /// What the three values of [`AngleConvention::angles`] are, in order.
    pub fn order(self) -> [&'static str; 3] {
        match self {
            AngleConvention::Official | AngleConvention::Trg => ["yaw", "pitch", "roll"],
            _ => ["pitch", "yaw", "roll"],
        }
    }

    /// The unit of the angles.
    pub fn unit(self) -> AngleUnit {
        match self {
            AngleConvention::Wcpa => AngleUnit::Radians,
            _ => AngleUnit::Degrees,
        }
    }

    /// The pose's angles in this convention's order ([`AngleConvention::order`]) and
    /// unit ([`AngleConvention::unit`]).
    pub fn angles(self, pose: &Pose) -> [f64; 3] {
        self.angles_of(&pose.rotation())
    }

    /// This convention's yaw, pitch and roll of the release's rotation `r` (column
    /// form), in degrees whatever the convention's order and unit: what `eval
    /// --angles` scores. For [`AngleConvention::Official`] exactly
    /// [`EulerAngles::from_rotation`].
    pub fn euler_of(self, r: &Rotation3<f64>) -> EulerAngles {
        if self == AngleConvention::Official {
            return EulerAngles::from_rotation(r);
        }
        let mut a = self.angles_of(r);
        if self.unit() == AngleUnit::Radians {
            a = a.map(f64::to_degrees);
        }
        let pick = |name: &str| a[self.order().iter().position(|&n| n == name).expect("named")];
        EulerAngles::new(pick("yaw"), pick("pitch"), pick("roll"))
    }

    /// [`AngleConvention::angles`] of a rotation (column form).
    fn angles_of(self, r: &Rotation3<f64>) -> [f64; 3] {
        let r = *r;
        match self {
            AngleConvention::Official => {
                let e = EulerAngles::from_rotation(&r);
                [e.yaw_deg, e.pitch_deg, e.roll_deg]
            }
            AngleConvention::Wcpa => {
                let e = EulerAngles::from_rotation(&r);
                [e.pitch_deg, e.yaw_deg, e.roll_deg].map(f64::to_radians)
            }
            AngleConvention::Trg => {
                let e = EulerAngles::from_rotation(&flip_conjugate(&r));
                [e.yaw_deg, e.pitch_deg, e.roll_deg]
            }
            AngleConvention::SixDRepNet => six_d_rep_net_angles(&r.matrix().transpose()),
            AngleConvention::Img2pose => {
                let m = flip_conjugate(&r).matrix().transpose();
                let [a, b, c] = tait_bryan_from_quaternion(scipy_quaternion(&m), [0, 1, 2]);
                [a, -b, -c].map(f64::to_degrees)
            }
        }
    }

    /// The release's rotation (column form, `R = R_t[:3,:3]^T`) of angles given in this
    /// convention's order and unit; every convention defines one for any angles.
    pub fn rotation(self, angles: [f64; 3]) -> Rotation3<f64> {
        let rad = match self.unit() {
            AngleUnit::Degrees => angles.map(f64::to_radians),
            AngleUnit::Radians => angles,
        };
        let rx = |a: f64| Rotation3::from_axis_angle(&Vector3::x_axis(), a);
        let ry = |a: f64| Rotation3::from_axis_angle(&Vector3::y_axis(), a);
        let rz = |a: f64| Rotation3::from_axis_angle(&Vector3::z_axis(), a);
        match self {
            AngleConvention::Official => rz(rad[2]) * rx(rad[1]) * ry(rad[0]),
            AngleConvention::Wcpa => rz(rad[2]) * rx(rad[0]) * ry(rad[1]),
            AngleConvention::Trg => flip_conjugate(&(rz(rad[2]) * rx(rad[1]) * ry(rad[0]))),
            AngleConvention::SixDRepNet => (rz(rad[2]) * ry(rad[1]) * rx(rad[0])).transpose(),
            AngleConvention::Img2pose => {
                flip_conjugate(&(rz(-rad[2]) * ry(-rad[1]) * rx(rad[0])).transpose())
            }
        }
    }

    /// The pose of angles in this convention and the release's translation
    /// (`R_t[3,:3]`, metres, OpenGL camera); the inverse of [`AngleConvention::angles`].
    pub fn from_angles(self, angles: [f64; 3], translation_m: Vector3<f64>) -> Pose {
        Pose::new(self.rotation(angles), translation_m)
    }
}

/// 6DRepNet's `compute_euler_angles_from_rotation_matrices` on `m` (its `R`), in
/// degrees, `[pitch, yaw, roll]`.
fn six_d_rep_net_angles(m: &Matrix3<f64>) -> [f64; 3] {
    let sy = m[(0, 0)].hypot(m[(1, 0)]);
    let yaw = (-m[(2, 0)]).atan2(sy);
    let (pitch, roll) = if sy < 1e-6 {
        ((-m[(1, 2)]).atan2(m[(1, 1)]), 0.0)
    } else {
        (m[(2, 1)].atan2(m[(2, 2)]), m[(1, 0)].atan2(m[(0, 0)]))
    };
    [pitch, yaw, roll].map(f64::to_degrees)
}

impl fmt::Display for AngleConvention {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for AngleConvention {
    type Err = Error;

    /// One of the names of [`AngleConvention::name`], in any case.
    fn from_str(s: &str) -> Result<Self> {
        AngleConvention::ALL
            .into_iter()
            .find(|c| c.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                let names: Vec<&str> = AngleConvention::ALL.iter().map(|c| c.name()).collect();
                Error::invalid(
                    "angle convention",
                    format!("{s:?}: expected one of {}", names.join(", ")),
                )
            })
    }
}

#[cfg(test)]
mod tests {
    //! The peers' formulas are written out again here from their published code (see
    //! docs/conventions.md), with plain matrices and closed forms, independently of
    //! the module's quaternion route.
    use super::*;
    use crate::conventions::geodesic_angle_deg;
    use crate::rng::Rng;

    const N: usize = 1000;

    fn rx(a: f64) -> Matrix3<f64> {
        let (s, c) = a.sin_cos();
        Matrix3::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)
    }
    fn ry(a: f64) -> Matrix3<f64> {
        let (s, c) = a.sin_cos();
        Matrix3::new(c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)
    }
    fn rz(a: f64) -> Matrix3<f64> {
        let (s, c) = a.sin_cos();
        Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
    }
    fn f() -> Matrix3<f64> {
        Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
    }

    /// Rodrigues' formula `I + sin(a) K + (1 - cos(a)) K^2` for the unit axis.
    fn rodrigues_matrix(v: &Vector3<f64>) -> Matrix3<f64> {
        let a = v.norm();
        if a == 0.0 {
            return Matrix3::identity();
        }
        let k = (v / a).cross_matrix();
        Matrix3::identity() + k * a.sin() + k * k * (1.0 - a.cos())
    }

    /// `R_t[:3,:3]` (row-major 3x3) and `R_t[3,:3]` of a row-vector `R_t`.
    fn blocks(rt: &[f64; 16]) -> (Matrix3<f64>, Vector3<f64>) {
        (
            Matrix3::new(
                rt[0], rt[1], rt[2], rt[4], rt[5], rt[6], rt[8], rt[9], rt[10],
            ),
            Vector3::new(rt[12], rt[13], rt[14]),
        )
    }

    fn random_rotation(rng: &mut Rng) -> Rotation3<f64> {
        let q = Quaternion::new(rng.normal(), rng.normal(), rng.normal(), rng.normal());
        UnitQuaternion::from_quaternion(q).to_rotation_matrix()
    }

    fn random_pose(rng: &mut Rng) -> Pose {
        let t = Vector3::new(
            rng.uniform(-0.3, 0.3),
            rng.uniform(-0.3, 0.3),
            rng.uniform(-1.0, -0.2),
        );
        Pose::new(random_rotation(rng), t)
    }

    fn random_camera(rng: &mut Rng) -> Matrix4<f64> {
        let t = Translation3::new(
            rng.uniform(-2.0, 2.0),
            rng.uniform(-2.0, 2.0),
            rng.uniform(-2.0, 2.0),
        );
        Isometry3::from_parts(
            t,
            UnitQuaternion::from_rotation_matrix(&random_rotation(rng)),
        )
        .to_homogeneous()
    }

    fn rt_diff(a: &Pose, b: &Pose) -> f64 {
        let (a, b) = (a.to_release_rt(), b.to_release_rt());
        a.iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }

    /// Largest difference of two angle triples, modulo a full turn in `unit`.
    fn angle_diff(a: [f64; 3], b: [f64; 3], unit: AngleUnit) -> f64 {
        let turn = match unit {
            AngleUnit::Degrees => 360.0,
            AngleUnit::Radians => std::f64::consts::TAU,
        };
        (0..3)
            .map(|k| ((a[k] - b[k] + turn / 2.0).rem_euclid(turn) - turn / 2.0).abs())
            .fold(0.0, f64::max)
    }

    /// The index of the angle a convention limits to [-90, 90] degrees.
    fn middle(c: AngleConvention) -> usize {
        if c == AngleConvention::Wcpa { 0 } else { 1 }
    }

    #[test]
    fn every_conversion_round_trips_on_random_poses() {
        let mut rng = Rng::new(51);
        for i in 0..N {
            let pose = random_pose(&mut rng);
            let camera = random_camera(&mut rng);
            let (rvec, tvec) = pose.to_opencv_rvec();
            let opencv = Pose::from_opencv_rvec(&rvec, &tvec);
            assert!(rt_diff(&pose, &opencv) < 1e-9, "{i}: opencv");
            let anchor = pose.to_arkit(&camera).unwrap();
            let arkit = Pose::from_arkit(&anchor, &camera).unwrap();
            assert!(rt_diff(&pose, &arkit) < 1e-9, "{i}: arkit");
            let (r, t) = pose.to_trg();
            assert!(rt_diff(&pose, &Pose::from_trg(&r, &t)) < 1e-9, "{i}: trg");
            let img2pose = Pose::from_img2pose(&pose.to_img2pose());
            assert!(rt_diff(&pose, &img2pose) < 1e-9, "{i}: img2pose");
            for c in AngleConvention::ALL {
                let back = c.from_angles(c.angles(&pose), pose.translation_m());
                assert!(rt_diff(&pose, &back) < 1e-9, "{i}: {c}");
            }
            // Every pair: a chain through all of them, each step from the previous.
            let mut p = pose;
            let (rvec, tvec) = p.to_opencv_rvec();
            p = Pose::from_opencv_rvec(&rvec, &tvec);
            p = Pose::from_arkit(&p.to_arkit(&camera).unwrap(), &camera).unwrap();
            let (r, t) = p.to_trg();
            p = Pose::from_trg(&r, &t);
            p = Pose::from_img2pose(&p.to_img2pose());
            for c in AngleConvention::ALL {
                p = c.from_angles(c.angles(&p), p.translation_m());
            }
            assert!(rt_diff(&pose, &p) < 1e-9, "{i}: chain");
        }
    }

    #[test]
    fn angles_round_trip_through_the_pose() {
        let mut rng = Rng::new(52);
        for c in AngleConvention::ALL {
            let scale = match c.unit() {
                AngleUnit::Degrees => 1.0,
                AngleUnit::Radians => 1f64.to_radians(),
            };
            for _ in 0..N {
                let mut a = [0.0; 3].map(|_| rng.uniform(-179.0, 179.0));
                a[middle(c)] = rng.uniform(-89.0, 89.0);
                let a = a.map(|v| v * scale);
                let pose = c.from_angles(a, Vector3::new(0.0, 0.0, -0.5));
                let back = c.angles(&pose);
                assert!(
                    angle_diff(a, back, c.unit()) < 1e-9 * scale,
                    "{c}: {a:?} -> {back:?}"
                );
            }
        }
    }

    #[test]
    fn official_and_wcpa_angles_match_the_closed_form_of_yxz() {
        let mut rng = Rng::new(53);
        for _ in 0..N {
            let pose = random_pose(&mut rng);
            // R_t[:3,:3]^T = Rz(c) Rx(b) Ry(a): its row 2 is (-cos b sin a, sin b,
            // cos b cos a) and its column 1 (-sin c cos b, cos c cos b, sin b).
            let (m, _) = blocks(&pose.to_release_rt());
            let m = m.transpose();
            let yaw = (-m[(2, 0)]).atan2(m[(2, 2)]);
            let pitch = m[(2, 1)].atan2(m[(2, 0)].hypot(m[(2, 2)]));
            let roll = (-m[(0, 1)]).atan2(m[(1, 1)]);
            let expect = [yaw, pitch, roll].map(f64::to_degrees);
            let official = AngleConvention::Official.angles(&pose);
            assert!(angle_diff(official, expect, AngleUnit::Degrees) < 1e-9);
            let wcpa = AngleConvention::Wcpa.angles(&pose);
            assert!(angle_diff(wcpa, [pitch, yaw, roll], AngleUnit::Radians) < 1e-11);
        }
    }

    #[test]
    fn trg_matches_its_loader_chain_and_evaluation() {
        let mut rng = Rng::new(54);
        for _ in 0..N {
            let pose = random_pose(&mut rng);
            // TRG's loader, written out: ZYX angles of R_t[:3,:3]^T ...
            let (m, t) = blocks(&pose.to_release_rt());
            let r = m.transpose();
            let yaw = r[(1, 0)].atan2(r[(0, 0)]);
            let pitch = (-r[(2, 0)]).atan2(r[(2, 1)].hypot(r[(2, 2)]));
            let roll = r[(2, 1)].atan2(r[(2, 2)]);
            // ... euler_to_rotation_matrix(roll, -pitch, -yaw) = Rz(-yaw) Ry(-pitch) Rx(roll),
            // stored transposed, with ty and tz negated.
            let rotmat = rz(-yaw) * ry(-pitch) * rx(roll);
            let (r_trg, t_trg) = pose.to_trg();
            assert!((r_trg.matrix() - rotmat).abs().max() < 1e-12);
            assert!((t_trg - Vector3::new(t.x, -t.y, -t.z)).norm() < 1e-15);
            // Its release-style R_t is [[R'^T, 0], [t'^T, 1]].
            let rt_trg = Pose::new(r_trg, t_trg).to_release_rt();
            let (m_trg, _) = blocks(&rt_trg);
            assert!((m_trg - rotmat.transpose()).abs().max() < 1e-12);
            // Its evaluation: 'yxz' of the column-form rotation, [yaw, pitch, roll].
            let e = [
                (-rotmat[(2, 0)]).atan2(rotmat[(2, 2)]),
                rotmat[(2, 1)].atan2(rotmat[(2, 0)].hypot(rotmat[(2, 2)])),
                (-rotmat[(0, 1)]).atan2(rotmat[(1, 1)]),
            ]
            .map(f64::to_degrees);
            let trg = AngleConvention::Trg.angles(&pose);
            assert!(angle_diff(trg, e, AngleUnit::Degrees) < 1e-9);
            // The derived relation: the official (-yaw, pitch, -roll).
            let o = AngleConvention::Official.angles(&pose);
            assert!(angle_diff(trg, [-o[0], o[1], -o[2]], AngleUnit::Degrees) < 1e-9);
        }
    }

    #[test]
    fn six_d_rep_net_matches_its_formula_on_the_release_block() {
        let mut rng = Rng::new(55);
        for _ in 0..N {
            let pose = random_pose(&mut rng);
            let (r, _) = blocks(&pose.to_release_rt());
            let sy = (r[(0, 0)] * r[(0, 0)] + r[(1, 0)] * r[(1, 0)]).sqrt();
            assert!(sy >= 1e-6, "a random pose at the singular branch");
            let x = r[(2, 1)].atan2(r[(2, 2)]);
            let y = (-r[(2, 0)]).atan2(sy);
            let z = r[(1, 0)].atan2(r[(0, 0)]);
            let expect = [x, y, z].map(|v| v * 180.0 / std::f64::consts::PI);
            let got = AngleConvention::SixDRepNet.angles(&pose);
            assert!(angle_diff(got, expect, AngleUnit::Degrees) < 1e-9);
            // Its get_R(pitch, yaw, roll) = Rz(roll) Ry(yaw) Rx(pitch) gives the block back.
            let [p, yw, rl] = got.map(f64::to_radians);
            assert!((rz(rl) * ry(yw) * rx(p) - r).abs().max() < 1e-12);
        }
    }

    #[test]
    fn img2pose_matches_its_frame_and_aflw_conversion() {
        let mut rng = Rng::new(56);
        for _ in 0..N {
            let pose = random_pose(&mut rng);
            let dof = pose.to_img2pose();
            let rv = Vector3::new(dof[0], dof[1], dof[2]);
            let t = Vector3::new(dof[3], dof[4], dof[5]);
            assert!(rv.norm() <= std::f64::consts::PI + 1e-12);
            // Its frame: OpenCV's camera, model points F v (y down, z into the head):
            // from_rotvec(rvec) (F v) + t = F (R v + t).
            let rot = rodrigues_matrix(&rv);
            let v = Vector3::new(rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.05);
            let cam = pose.to_camera(&v.into()).coords;
            assert!((rot * (f() * v) + t - f() * cam).norm() < 1e-12);
            // convert_to_aflw: transpose, SciPy's 'xyz' (M = Rz(c) Ry(b) Rx(a)), then
            // [a, -b, -c] in degrees.
            let m = rot.transpose();
            let a = m[(2, 1)].atan2(m[(2, 2)]);
            let b = (-m[(2, 0)]).atan2(m[(2, 1)].hypot(m[(2, 2)]));
            let c = m[(1, 0)].atan2(m[(0, 0)]);
            let expect = [a, -b, -c].map(f64::to_degrees);
            let got = AngleConvention::Img2pose.angles(&pose);
            assert!(
                angle_diff(got, expect, AngleUnit::Degrees) < 1e-9,
                "{got:?} {expect:?}"
            );
            // The same numbers as 6DRepNet's away from its singular branch.
            let six = AngleConvention::SixDRepNet.angles(&pose);
            assert!(angle_diff(got, six, AngleUnit::Degrees) < 1e-9);
        }
    }

    #[test]
    fn opencv_rvec_matches_rodrigues_and_the_release_formula() {
        let mut rng = Rng::new(57);
        for _ in 0..N {
            let pose = random_pose(&mut rng);
            let (rvec, tvec) = pose.to_opencv_rvec();
            assert!(rvec.norm() <= std::f64::consts::PI + 1e-12);
            let r = rodrigues_matrix(&rvec);
            // R_t = [[R^T, 0], [t^T, 1]] @ diag(1, -1, -1, 1).
            let (m, t) = blocks(&pose.to_release_rt());
            assert!((r.transpose() * f() - m).abs().max() < 1e-12);
            assert!((f() * tvec - t).norm() < 1e-15);
            // And back from an rvec of any length (angles beyond pi included).
            let any = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 2.0;
            let p = Pose::from_opencv_rvec(&any, &tvec);
            assert!(
                (p.to_opencv().0.matrix() - rodrigues_matrix(&any))
                    .abs()
                    .max()
                    < 1e-12
            );
        }
    }

    #[test]
    fn arkit_pose_is_the_inverse_camera_times_the_anchor() {
        let mut rng = Rng::new(58);
        for _ in 0..N {
            let camera = random_camera(&mut rng);
            let anchor = random_camera(&mut rng);
            let pose = Pose::from_arkit(&anchor, &camera).unwrap();
            let expect = camera.try_inverse().unwrap() * anchor;
            let got = pose.face_to_camera.to_homogeneous();
            assert!((got - expect).abs().max() < 1e-12);
            // A face point through the world and into the camera.
            let p = nalgebra::Point3::new(0.03, -0.02, 0.05);
            let world = anchor * p.to_homogeneous();
            let in_camera = camera.try_inverse().unwrap() * world;
            assert!((pose.to_camera(&p).coords - in_camera.xyz()).norm() < 1e-12);
        }
        // A simd_float4x4 dumped column by column reads with from_column_slice.
        let mut columns = [0.0; 16];
        columns[0] = 1.0;
        columns[5] = 1.0;
        columns[10] = 1.0;
        columns[12..16].copy_from_slice(&[0.01, 0.02, -0.4, 1.0]);
        let anchor = Matrix4::from_column_slice(&columns);
        let pose = Pose::from_arkit(&anchor, &Matrix4::identity()).unwrap();
        assert_eq!(pose.translation_m(), Vector3::new(0.01, 0.02, -0.4));
    }

    #[test]
    fn hand_derived_values_for_yaw_20_pitch_10_roll_5() {
        let t = Vector3::new(0.01, -0.02, -0.5);
        let pose = Pose::from_euler(EulerAngles::new(20.0, 10.0, 5.0), t);
        let deg = AngleUnit::Degrees;
        let official = AngleConvention::Official.angles(&pose);
        assert!(angle_diff(official, [20.0, 10.0, 5.0], deg) < 1e-12);
        let wcpa = AngleConvention::Wcpa.angles(&pose);
        let expect = [10f64, 20.0, 5.0].map(f64::to_radians);
        assert!(angle_diff(wcpa, expect, AngleUnit::Radians) < 1e-14);
        let trg = AngleConvention::Trg.angles(&pose);
        assert!(angle_diff(trg, [-20.0, 10.0, -5.0], deg) < 1e-12);
        // The notes' (-8.16, -20.79, -5.27) for 6DRepNet and img2pose, and SciPy's
        // full-precision values.
        let scipy = [-8.163082061995787, -20.78978991186315, -5.2677127071460195];
        for c in [AngleConvention::SixDRepNet, AngleConvention::Img2pose] {
            let a = c.angles(&pose);
            assert!(
                angle_diff(a, [-8.16, -20.79, -5.27], deg) < 0.005,
                "{c}: {a:?}"
            );
            assert!(angle_diff(a, scipy, deg) < 1e-9, "{c}: {a:?}");
        }
        // cv2.Rodrigues of F R (OpenCV 5.1) and SciPy's rotvec of F R F.
        let (rvec, tvec) = pose.to_opencv_rvec();
        let cv = Vector3::new(-2.932712523784816, 0.17340360628288584, -0.5286749139310808);
        assert!((rvec - cv).norm() < 1e-12, "{rvec}");
        assert_eq!(tvec, Vector3::new(0.01, 0.02, 0.5));
        let dof = pose.to_img2pose();
        let expect = [
            0.15748812656829222,
            -0.35557041134883827,
            -0.11662590751074577,
            0.01,
            0.02,
            0.5,
        ];
        assert!(
            (0..6).all(|k| (dof[k] - expect[k]).abs() < 1e-12),
            "{dof:?}"
        );
    }

    #[test]
    fn rodrigues_near_zero() {
        assert_eq!(rotation_from_rvec(&Vector3::zeros()), Rotation3::identity());
        assert_eq!(rvec_from_rotation(&Rotation3::identity()), Vector3::zeros());
        for scale in [1e-150, 1e-15, 1e-12, 1e-8, 1e-5, 1e-3] {
            let v = Vector3::new(0.3, -1.0, 0.2) * scale;
            let r = rotation_from_rvec(&v);
            // First order: R = I + [v]x, with an error of order |v|^2.
            let first = Matrix3::identity() + v.cross_matrix();
            assert!((r.matrix() - first).abs().max() <= v.norm_squared() + 1e-16);
            let back = rvec_from_rotation(&r);
            // Component by component: no squares to underflow at 1e-150.
            let big = v.abs().max();
            assert!((back - v).abs().max() <= 1e-12 * big, "{scale}: {back}");
            // From the matrix Rodrigues formula too (its rounding limits the accuracy).
            let from_formula =
                rvec_from_rotation(&Rotation3::from_matrix_unchecked(rodrigues_matrix(&v)));
            assert!(
                (from_formula - v).abs().max() <= 1e-15 + 1e-9 * big,
                "{scale}"
            );
        }
    }

    #[test]
    fn rodrigues_near_pi() {
        use std::f64::consts::PI;
        let mut rng = Rng::new(59);
        for _ in 0..100 {
            let axis = Vector3::new(rng.normal(), rng.normal(), rng.normal()).normalize();
            for gap in [1e-3, 1e-7, 1e-10, 1e-13] {
                let r = Rotation3::from_matrix_unchecked(rodrigues_matrix(&(axis * (PI - gap))));
                let v = rvec_from_rotation(&r);
                assert!((v - axis * (PI - gap)).norm() < 1e-9, "{gap}: {v}");
                assert!((rotation_from_rvec(&v).matrix() - r.matrix()).abs().max() < 1e-12);
                // Just past pi: the same rotation as the opposite axis, short of pi.
                let past = Rotation3::from_matrix_unchecked(rodrigues_matrix(&(axis * (PI + gap))));
                let v = rvec_from_rotation(&past);
                assert!((v + axis * (PI - gap)).norm() < 1e-9, "{gap}: {v}");
            }
            // Exactly a half turn: the axis whose first non-zero component is positive.
            let half = rotation_from_rvec(&(axis * PI));
            let v = rvec_from_rotation(&half);
            let signed = if axis.x > 0.0 { axis } else { -axis };
            assert!((v - signed * PI).norm() < 1e-9, "{v} {axis}");
        }
        let v = rvec_from_rotation(&Rotation3::from_matrix_unchecked(Matrix3::from_diagonal(
            &Vector3::new(-1.0, 1.0, -1.0),
        )));
        assert_eq!(v, Vector3::new(0.0, PI, 0.0));
    }

    #[test]
    fn gimbal_lock_poses_keep_their_rotation() {
        let d = f64::to_radians;
        // Each convention's singular poses: official / WCPA / TRG pitch +-90 (rotation
        // Rz Rx(+-90) Ry), 6DRepNet / img2pose yaw +-90 (R_t block Rz Ry(+-90) Rx).
        let mut poses = Vec::new();
        for s in [90.0, -90.0] {
            let r = rz(d(10.0)) * rx(d(s)) * ry(d(30.0));
            poses.push(Rotation3::from_matrix_unchecked(r));
            let block = rz(d(25.0)) * ry(d(s)) * rx(d(-40.0));
            poses.push(Rotation3::from_matrix_unchecked(block.transpose()));
        }
        for (k, r) in poses.iter().enumerate() {
            let pose = Pose::new(*r, Vector3::new(0.0, 0.0, -0.5));
            for c in AngleConvention::ALL {
                let a = c.angles(&pose);
                assert!(a.iter().all(|v| v.is_finite()), "{k} {c}: {a:?}");
                let back = c.rotation(a);
                assert!(
                    geodesic_angle_deg(&back, &pose.rotation()) < 1e-6,
                    "{k} {c}: {a:?}"
                );
            }
        }
        // Official: pitch +-90 and SciPy's rule (roll 0); TRG and WCPA alike.
        let pose = Pose::new(poses[0], Vector3::zeros());
        let o = AngleConvention::Official.angles(&pose);
        assert!((o[1] - 90.0).abs() < 1e-9 && o[2] == 0.0, "{o:?}");
        let t = AngleConvention::Trg.angles(&pose);
        assert!((t[1] - 90.0).abs() < 1e-9 && t[2] == 0.0, "{t:?}");
        let w = AngleConvention::Wcpa.angles(&pose);
        assert!((w[0] - d(90.0)).abs() < 1e-11 && w[2] == 0.0, "{w:?}");
        // 6DRepNet's singular branch: roll 0, yaw +-90, pitch from R12 and R11.
        for (k, s) in [(1, 90.0), (3, -90.0)] {
            let pose = Pose::new(poses[k], Vector3::zeros());
            let a = AngleConvention::SixDRepNet.angles(&pose);
            assert!(a[2] == 0.0 && (a[1] - s).abs() < 1e-6, "{a:?}");
            let i = AngleConvention::Img2pose.angles(&pose);
            assert!(i[2] == 0.0 && (i[1] - s).abs() < 1e-6, "{i:?}");
        }
        // Rz(25) Ry(90) Rx(-40) = Ry(90) Rx(-40 - 25): the branch's pitch is -65.
        let a = AngleConvention::SixDRepNet.angles(&Pose::new(poses[1], Vector3::zeros()));
        assert!((a[0] + 65.0).abs() < 1e-9, "{a:?}");
    }

    #[test]
    fn bad_arkit_matrices_are_refused() {
        let good = Matrix4::new_translation(&Vector3::new(0.0, 0.0, -0.4));
        assert!(Pose::from_arkit(&good, &Matrix4::identity()).is_ok());
        let message = |anchor: Matrix4<f64>| {
            let e = Pose::from_arkit(&anchor, &Matrix4::identity()).unwrap_err();
            assert_eq!(e.kind(), crate::error::ErrorKind::Invalid);
            e.to_string()
        };
        let scaled = good * Matrix4::new_scaling(1.1);
        assert!(
            message(scaled).contains("orthonormal"),
            "{}",
            message(scaled)
        );
        let mut nan = good;
        nan[(1, 2)] = f64::NAN;
        assert!(message(nan).contains("non-finite value NaN at [1][2]"));
        let mut row = good;
        row[(3, 0)] = 0.2;
        assert!(message(row).contains("last row") && !message(row).contains("transposed"));
        let transposed = good.transpose();
        assert!(
            message(transposed).contains("transposed"),
            "{}",
            message(transposed)
        );
        let mirror = Matrix4::from_diagonal(&nalgebra::Vector4::new(-1.0, 1.0, 1.0, 1.0));
        assert!(message(mirror).contains("reflection"));
        assert!(message(mirror).starts_with("invalid face anchor transform"));
        let e = Pose::from_arkit(&good, &scaled).unwrap_err().to_string();
        assert!(e.starts_with("invalid camera transform"), "{e}");
        let pose = Pose::from_arkit(&good, &Matrix4::identity()).unwrap();
        assert!(pose.to_arkit(&transposed).is_err());
    }

    #[test]
    fn convention_names_parse_and_print() {
        for c in AngleConvention::ALL {
            assert_eq!(c.name().parse::<AngleConvention>().unwrap(), c);
            assert_eq!(c.to_string(), c.name());
        }
        assert_eq!(
            "6DRepNet".parse::<AngleConvention>().unwrap(),
            AngleConvention::SixDRepNet
        );
        let e = "opencv".parse::<AngleConvention>().unwrap_err().to_string();
        assert!(e.contains("\"opencv\"") && e.contains("official, wcpa, trg, 6drepnet, img2pose"));
        assert_eq!(AngleConvention::Wcpa.order(), ["pitch", "yaw", "roll"]);
        assert_eq!(AngleConvention::Trg.unit(), AngleUnit::Degrees);
    }

    #[test]
    fn euler_of_reads_each_convention_s_yaw_pitch_and_roll_in_degrees() {
        // The official angles unchanged; WCPA's are the official ones (radians, another
        // order); TRG's are (-yaw, pitch, -roll) of the official ones (its frame is the
        // release's conjugated by diag(1, -1, -1)); 6DRepNet's by its own order.
        let pose = Pose::from_euler(
            EulerAngles::new(20.0, 10.0, 5.0),
            Vector3::new(0.0, 0.0, -0.5),
        );
        let r = pose.rotation();
        let official = AngleConvention::Official.euler_of(&r);
        assert_eq!(official, EulerAngles::from_rotation(&r));
        let wcpa = AngleConvention::Wcpa.euler_of(&r);
        let trg = AngleConvention::Trg.euler_of(&r);
        for (a, b) in [
            (wcpa.yaw_deg, official.yaw_deg),
            (wcpa.pitch_deg, official.pitch_deg),
            (wcpa.roll_deg, official.roll_deg),
            (trg.yaw_deg, -official.yaw_deg),
            (trg.pitch_deg, official.pitch_deg),
            (trg.roll_deg, -official.roll_deg),
        ] {
            assert!((a - b).abs() < 1e-9, "{a} {b}");
        }
        let six = AngleConvention::SixDRepNet.euler_of(&r);
        let [p, y, ro] = AngleConvention::SixDRepNet.angles(&pose);
        assert_eq!((six.pitch_deg, six.yaw_deg, six.roll_deg), (p, y, ro));
    }
}

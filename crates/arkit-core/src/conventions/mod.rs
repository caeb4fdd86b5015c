//! The release's conventions, in one place. No other module re-derives them.
//!
//! | convention | where |
//! |---|---|
//! | canonical face frame: metres, y up, face toward +z | [`Pose`] |
//! | `R_t`: row-vector 4x4, `[x y z 1] @ R_t`, translation in row 3, `tz < 0` | [`Pose`] |
//! | OpenCV `(R, t)` <-> `R_t`: `[[R^T,0],[t^T,1]] @ diag(1,-1,-1,1)` | [`Pose::from_opencv`] |
//! | Euler angles: SciPy `as_euler('yxz')` of `R_t[:3,:3]^T`, degrees | [`EulerAngles`] |
//! | `_info.npz` `euler_angles` order: `[pitch, yaw, roll]` | [`EulerAngles::to_release_order`] |
//! | projection: `@ P @ M1`, divide by w, `v = H - y` | [`Camera::project`] |
//! | pixel `(i, j)` covers `[i,i+1) x [j,j+1)`, centre `(i+0.5, j+0.5)` | [`ImagePoint`] |
//! | pinhole equivalent `fx = P00 W/2, cx = W/2` | [`Camera::pinhole`] |
//! | OpenCV `rvec`/`tvec` (Rodrigues) <-> pose | [`Pose::from_opencv_rvec`], [`Pose::to_opencv_rvec`] |
//! | ARKit: pose = `inverse(camera.transform) * faceAnchor.transform`, no device-orientation rotation | [`Pose::from_arkit`], [`Pose::to_arkit`] |
//! | WCPA angles: `[pitch, yaw, roll]` radians, official definition | [`AngleConvention::Wcpa`] |
//! | TRG: `R' = F R F`, `t' = F t` (`F = diag(1,-1,-1)`); its angles 'yxz' of `R'` | [`Pose::to_trg`], [`AngleConvention::Trg`] |
//! | 6DRepNet angles: its formula on `R_t[:3,:3]`, `[pitch, yaw, roll]` degrees | [`AngleConvention::SixDRepNet`] |
//! | img2pose: `[rvec, t]` of `F R F`, `F t`; angles `as_euler('xyz')` of the transpose, yaw and roll negated | [`Pose::to_img2pose`], [`AngleConvention::Img2pose`] |
//! | every tool's angles, by name (`official`, `wcpa`, `trg`, `6drepnet`, `img2pose`) | [`AngleConvention`] |
//!
//! The facts come from the release's official loader and evaluation code; the tests
//! check them against hand-derived values and, in `tests/conventions_scipy.rs`, against
//! angles that SciPy itself computed.

mod camera;
mod peers;
mod pose;

pub use camera::{Camera, ImagePoint, Pinhole};
pub use peers::{
    AngleConvention, AngleUnit, check_rigid_transform, rotation_from_rvec, rvec_from_rotation,
};
pub use pose::{EulerAngles, ORTHONORMAL_TOLERANCE, Pose, geodesic_angle_deg};

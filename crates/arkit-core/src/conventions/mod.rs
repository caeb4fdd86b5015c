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
//!
//! The facts come from the release's official loader and evaluation code; the tests
//! check them against hand-derived values and, in `tests/conventions_scipy.rs`, against
//! angles that SciPy itself computed.

mod camera;
mod pose;

pub use camera::{Camera, ImagePoint, Pinhole};
pub use pose::{EulerAngles, ORTHONORMAL_TOLERANCE, Pose, geodesic_angle_deg};

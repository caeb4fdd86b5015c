//! The camera of the release: its OpenGL projection matrix, viewport and y flip.
//!
//! The release projects a canonical vertex `v` to image pixels as
//!
//! ```text
//! q = [x y z 1] @ R_t @ P @ M1,   q /= q[3],   (u, v) = (q[0], H - q[1])
//! M1 = [[W/2, 0, 0, 0], [0, H/2, 0, 0], [0, 0, 1, 0], [W/2, H/2, 0, 1]]
//! ```
//!
//! with `P` the row-vector OpenGL projection matrix of `projection_matrix.txt`
//! ([`Camera::RELEASE_FOCAL_NDC`] on the diagonal, near plane 0.001 m).
//!
//! **Image coordinates and pixel centres.** `u` runs from 0 at the left edge of the
//! image to `W` at its right edge and `v` from 0 at the top to `H` at the bottom (the
//! OpenGL viewport convention). Pixel `(i, j)` is the square `[i, i+1) x [j, j+1)` and
//! its centre is `(i + 0.5, j + 0.5)`. Every module samples pixels at that centre. (OpenCV
//! puts pixel centres at integer coordinates: subtract 0.5 from `u`, `v` to get OpenCV
//! pixel coordinates.)
//!
//! **Pinhole equivalent.** For a projection with no skew, `P` is the pinhole camera
//! `u = fx X/Z + cx`, `v = fy Y/Z + cy` on OpenCV camera coordinates
//! `(X, Y, Z) = (x, -y, -z)` with `fx = P00 W/2`, `fy = P11 H/2`,
//! `cx = W/2 (1 - P20)`, `cy = H/2 (1 + P21)`; for the release's P, `cx = W/2`,
//! `cy = H/2`. [`Camera::pinhole`] returns it; tests check both paths agree.

use super::pose::Pose;
use crate::error::{Error, Result};
use crate::raster::ScreenVertex;
use nalgebra::{Matrix3, Matrix4, Point3, RowVector4};
use std::path::Path;

/// Pinhole intrinsics in the image coordinates described in the module docs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pinhole {
    /// Horizontal focal length in pixels.
    pub fx: f64,
    /// Vertical focal length in pixels.
    pub fy: f64,
    /// Principal point, pixels from the left edge.
    pub cx: f64,
    /// Principal point, pixels from the top edge.
    pub cy: f64,
}

impl Pinhole {
    /// The 3x3 matrix `K` (for OpenCV-style solvers on coordinates of this module).
    pub fn k(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }
}

/// A point projected to the image, with its depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImagePoint {
    /// Pixels from the left edge.
    pub u: f64,
    /// Pixels from the top edge (after the release's y flip).
    pub v: f64,
    /// Distance along the viewing axis in metres (`-z` in the OpenGL camera frame);
    /// positive in front of the camera.
    pub depth_m: f64,
}

/// The release camera: projection matrix and image size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Row-vector OpenGL projection matrix `P` (`clip = [x y z 1] @ P`).
    pub projection: Matrix4<f64>,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Camera {
    /// `P[0][0] = P[1][1]` of the release's `projection_matrix.txt`.
    pub const RELEASE_FOCAL_NDC: f64 = 1.57443701;
    /// The release's near plane in metres.
    pub(crate) const RELEASE_NEAR_M: f64 = 0.001;

    /// The release's projection matrix (the values of `projection_matrix.txt`).
    pub fn release_projection() -> Matrix4<f64> {
        let f = Self::RELEASE_FOCAL_NDC;
        Matrix4::new(
            f,
            0.0,
            0.0,
            0.0, //
            0.0,
            f,
            0.0,
            0.0, //
            0.0,
            0.0,
            -0.99999976,
            -1.0, //
            0.0,
            0.0,
            -Self::RELEASE_NEAR_M,
            0.0,
        )
    }

    /// The release camera for an image of `width` x `height` pixels.
    pub fn release(width: u32, height: u32) -> Self {
        Camera {
            projection: Self::release_projection(),
            width,
            height,
        }
    }

    /// A camera from a row-vector projection matrix, checked with [`Camera::check`].
    pub fn new(projection: Matrix4<f64>, width: u32, height: u32) -> Result<Self> {
        let camera = Camera {
            projection,
            width,
            height,
        };
        camera.check()?;
        Ok(camera)
    }

    /// Reads a 4x4 projection matrix written as text (4 rows of 4 numbers, as the
    /// release's `projection_matrix.txt`).
    pub fn read_projection_txt(path: &Path) -> Result<Matrix4<f64>> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let values: Vec<f64> = text
            .split_whitespace()
            .map(|s| {
                s.parse::<f64>()
                    .map_err(|_| Error::format(path, format!("'{s}' is not a number")))
            })
            .collect::<Result<_>>()?;
        if values.len() != 16 {
            return Err(Error::format(
                path,
                format!("expected 16 numbers (a 4x4 matrix), found {}", values.len()),
            ));
        }
        Ok(Matrix4::from_row_slice(&values))
    }

    /// Checks that this camera can project: positive size, finite matrix, an OpenGL
    /// perspective (`P[2][3] = -1`, `P[0][3] = P[1][3] = P[3][3] = 0`), positive focal
    /// lengths and no skew.
    pub fn check(&self) -> Result<()> {
        if self.width == 0 || self.height == 0 {
            return Err(Error::invalid(
                "camera",
                format!("image size {}x{} is empty", self.width, self.height),
            ));
        }
        let p = &self.projection;
        if p.iter().any(|v| !v.is_finite()) {
            return Err(Error::invalid(
                "camera",
                "projection matrix has a non-finite value",
            ));
        }
        let perspective =
            p[(2, 3)] == -1.0 && p[(0, 3)] == 0.0 && p[(1, 3)] == 0.0 && p[(3, 3)] == 0.0;
        if !perspective {
            return Err(Error::invalid(
                "camera",
                "projection matrix is not an OpenGL perspective in row-vector form (expected last column (0, 0, -1, 0))",
            ));
        }
        if p[(0, 0)] <= 0.0 || p[(1, 1)] <= 0.0 {
            return Err(Error::invalid(
                "camera",
                format!(
                    "focal lengths must be positive, found {} and {}",
                    p[(0, 0)],
                    p[(1, 1)]
                ),
            ));
        }
        if p[(1, 0)] != 0.0 || p[(0, 1)] != 0.0 || p[(3, 0)] != 0.0 || p[(3, 1)] != 0.0 {
            return Err(Error::invalid(
                "camera",
                "projection matrix has skew or a shift this camera model cannot express",
            ));
        }
        Ok(())
    }

    /// The viewport matrix `M1` of the release (row-vector form).
    pub(crate) fn viewport_matrix(&self) -> Matrix4<f64> {
        let (w2, h2) = (self.width as f64 / 2.0, self.height as f64 / 2.0);
        Matrix4::new(
            w2, 0.0, 0.0, 0.0, //
            0.0, h2, 0.0, 0.0, //
            0.0, 0.0, 1.0, 0.0, //
            w2, h2, 0.0, 1.0,
        )
    }

    /// The equivalent pinhole intrinsics (see module docs).
    pub fn pinhole(&self) -> Pinhole {
        let p = &self.projection;
        let (w2, h2) = (self.width as f64 / 2.0, self.height as f64 / 2.0);
        Pinhole {
            fx: p[(0, 0)] * w2,
            fy: p[(1, 1)] * h2,
            cx: w2 * (1.0 - p[(2, 0)]),
            cy: h2 * (1.0 + p[(2, 1)]),
        }
    }

    /// Projects a canonical point exactly as the release's loader does: the full matrix
    /// chain `R_t @ P @ M1`, the perspective divide, and the y flip.
    pub fn project(&self, pose: &Pose, p: &Point3<f64>) -> ImagePoint {
        let chain = pose.release_matrix() * self.projection * self.viewport_matrix();
        self.project_with_chain(&chain, p)
    }

    /// Projects many points with one matrix chain (see [`Camera::project`]).
    pub fn project_all(&self, pose: &Pose, points: &[Point3<f64>]) -> Vec<ImagePoint> {
        let chain = pose.release_matrix() * self.projection * self.viewport_matrix();
        points
            .iter()
            .map(|p| self.project_with_chain(&chain, p))
            .collect()
    }

    fn project_with_chain(&self, chain: &Matrix4<f64>, p: &Point3<f64>) -> ImagePoint {
        let q = RowVector4::new(p.x, p.y, p.z, 1.0) * chain;
        let w = q[3];
        ImagePoint {
            u: q[0] / w,
            v: self.height as f64 - q[1] / w,
            depth_m: w,
        }
    }

    /// Projects points to rasterizer input: image position and `1 / depth`.
    ///
    /// The same operations as [`Camera::project`] (each output the chain's row of four
    /// products summed left to right, then the three divisions), written out over
    /// eight points at a time so that they run in vector lanes: the divisions were a
    /// point's cost one at a time (tested against the matrix chain, bit for bit).
    pub fn project_to_screen(&self, pose: &Pose, points: &[Point3<f32>]) -> Vec<ScreenVertex> {
        let chain = pose.release_matrix() * self.projection * self.viewport_matrix();
        let c = |i: usize, j: usize| chain[(i, j)];
        let col = |j: usize| [c(0, j), c(1, j), c(2, j), c(3, j)];
        let columns = [col(0), col(1), col(3)];
        let height = self.height as f64;
        screen_vertices(points, columns, height)
    }

    #[cfg(test)]
    /// Projects a point already in OpenGL camera coordinates with the pinhole model.
    /// Independent of the matrix chain; the two must agree.
    pub(crate) fn project_camera_point(&self, pc: &Point3<f64>) -> nalgebra::Point2<f64> {
        let k = self.pinhole();
        let (x, y, z) = (pc.x, -pc.y, -pc.z);
        nalgebra::Point2::new(k.fx * x / z + k.cx, k.fy * y / z + k.cy)
    }

    /// Checks that `pose` can be projected by this camera and that every point of
    /// `points` lies in front of it (beyond the near plane).
    pub fn check_projectable(&self, pose: &Pose, points: &[Point3<f64>]) -> Result<()> {
        self.check()?;
        pose.check()?;
        let near = self.near_plane_m();
        for (i, p) in points.iter().enumerate() {
            let depth = -pose.to_camera(p).z;
            if depth.is_nan() || depth <= near {
                return Err(Error::invalid(
                    "pose",
                    format!(
                        "vertex {i} is {depth:.4} m in front of the camera, not beyond the near plane ({near} m)"
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The near plane distance in metres implied by `P` (`P[3][2] / (P[2][2] - 1)`).
    pub fn near_plane_m(&self) -> f64 {
        let p = &self.projection;
        p[(3, 2)] / (p[(2, 2)] - 1.0)
    }
}

/// [`Camera::project_to_screen`]'s arithmetic with the chain's columns for `u`, `v`
/// and `w` and the image height: eight points at a time, so that the divisions run in
/// vector lanes.
fn screen_vertices(
    points: &[Point3<f32>],
    [cu, cv, cw]: [[f64; 4]; 3],
    height: f64,
) -> Vec<ScreenVertex> {
    let mut out = Vec::with_capacity(points.len());
    for chunk in points.chunks(8) {
        let mut x = [0f64; 8];
        let mut y = [0f64; 8];
        let mut z = [0f64; 8];
        for (k, p) in chunk.iter().enumerate() {
            (x[k], y[k], z[k]) = (p.x as f64, p.y as f64, p.z as f64);
        }
        let row = |m: [f64; 4], k: usize| x[k] * m[0] + y[k] * m[1] + z[k] * m[2] + m[3];
        let mut sx = [0f32; 8];
        let mut sy = [0f32; 8];
        let mut sw = [0f32; 8];
        for k in 0..8 {
            let w = row(cw, k);
            sx[k] = (row(cu, k) / w) as f32;
            sy[k] = (height - row(cv, k) / w) as f32;
            sw[k] = (1.0 / w) as f32;
        }
        out.extend((0..chunk.len()).map(|k| ScreenVertex {
            x: sx[k],
            y: sy[k],
            inv_w: sw[k],
        }));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::conventions::EulerAngles;
    use nalgebra::Vector3;
    use proptest::prelude::*;

    #[test]
    fn screen_vertices_are_the_matrix_chains_bit_for_bit() {
        // Many points (every remainder of the eight-point groups) at several poses.
        let mut x = 0x51ed_270b_u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as f32 / u32::MAX as f32 - 0.5
        };
        for (i, angles) in [(0.0, 0.0, 0.0), (17.0, -30.0, 12.0), (-63.0, 40.0, 166.0)]
            .into_iter()
            .enumerate()
        {
            let (pitch_deg, yaw_deg, roll_deg) = angles;
            let pose = Pose::from_euler(
                EulerAngles {
                    yaw_deg,
                    pitch_deg,
                    roll_deg,
                },
                Vector3::new(0.01 * i as f64, -0.02, -0.4 - 0.1 * i as f64),
            );
            let camera = Camera::release(800, 640 + 80 * i as u32);
            for n in [0usize, 1, 7, 8, 9, 1220] {
                let points: Vec<Point3<f32>> = (0..n)
                    .map(|_| Point3::new(0.2 * next(), 0.2 * next(), 0.1 * next()))
                    .collect();
                let screen = camera.project_to_screen(&pose, &points);
                assert_eq!(screen.len(), n);
                // The same as the arithmetic written out from the chain's columns.
                let chain = pose.release_matrix() * camera.projection * camera.viewport_matrix();
                let col = |j: usize| [0, 1, 2, 3].map(|i| chain[(i, j)]);
                let plain =
                    screen_vertices(&points, [col(0), col(1), col(3)], camera.height as f64);
                assert_eq!(plain, screen);
                for (p, s) in points.iter().zip(&screen) {
                    let q = camera.project(&pose, &p.cast());
                    let want = (q.u as f32, q.v as f32, (1.0 / q.depth_m) as f32);
                    assert_eq!(
                        (s.x.to_bits(), s.y.to_bits(), s.inv_w.to_bits()),
                        (want.0.to_bits(), want.1.to_bits(), want.2.to_bits()),
                        "{p:?} at {angles:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn release_pinhole_at_800() {
        let k = Camera::release(800, 800).pinhole();
        assert!((k.fx - 1.57443701 * 400.0).abs() < 1e-9);
        assert_eq!(k.fy, k.fx);
        assert_eq!((k.cx, k.cy), (400.0, 400.0));
        // Near plane of the release's matrix: 0.001 / (0.99999976 + 1) ~ 0.0005 m.
        assert!((Camera::release(800, 800).near_plane_m() - 0.001 / 1.99999976).abs() < 1e-12);
    }

    #[test]
    fn golden_yaw_30_projects_to_hand_derived_pixel() {
        // A point 10 cm in front of the face origin (a nose tip), the head turned by yaw
        // 30 degrees, 0.5 m from the camera:
        //   R p = (0.1 sin 30, 0, 0.1 cos 30) = (0.05, 0, 0.0866025...)
        //   camera point = (0.05, 0, -0.5 + 0.0866025) = (0.05, 0, -0.4133975)
        //   u = 400 + 629.774804 * 0.05 / 0.4133975 = 400 + 76.1711...
        //   v = 400 (on the optical axis vertically).
        let cam = Camera::release(800, 800);
        let pose = Pose::from_euler(
            EulerAngles::new(30.0, 0.0, 0.0),
            Vector3::new(0.0, 0.0, -0.5),
        );
        let q = cam.project(&pose, &Point3::new(0.0, 0.0, 0.1));
        let f = 1.57443701 * 400.0;
        let expected_u = 400.0 + f * 0.05 / (0.5 - 0.1 * (30f64).to_radians().cos());
        assert!((expected_u - 476.1711).abs() < 1e-3, "{expected_u}");
        assert!((q.u - expected_u).abs() < 1e-9, "{} vs {}", q.u, expected_u);
        assert!((q.v - 400.0).abs() < 1e-9);
        assert!((q.depth_m - 0.4133975).abs() < 1e-6);
    }

    #[test]
    fn y_is_flipped_so_up_is_smaller_v() {
        let cam = Camera::release(640, 480);
        let pose = Pose::from_euler(
            EulerAngles::new(0.0, 0.0, 0.0),
            Vector3::new(0.0, 0.0, -0.5),
        );
        let top = cam.project(&pose, &Point3::new(0.0, 0.05, 0.0));
        let bottom = cam.project(&pose, &Point3::new(0.0, -0.05, 0.0));
        assert!(top.v < 240.0 && bottom.v > 240.0);
        // fy = P11 * H/2 = 1.57443701 * 240; offset = fy * 0.05 / 0.5.
        assert!((bottom.v - 240.0 - 1.57443701 * 240.0 * 0.1).abs() < 1e-9);
    }

    #[test]
    fn rejects_bad_cameras_and_points_behind() {
        let mut p = Camera::release_projection();
        p[(2, 3)] = 0.0;
        assert!(Camera::new(p, 800, 800).is_err());
        assert!(Camera::new(Camera::release_projection(), 0, 800).is_err());
        let mut p = Camera::release_projection();
        p[(0, 0)] = f64::NAN;
        assert!(Camera::new(p, 800, 800).is_err());
        let cam = Camera::release(800, 800);
        let pose = Pose::from_euler(
            EulerAngles::new(0.0, 0.0, 0.0),
            Vector3::new(0.0, 0.0, -0.05),
        );
        let err = cam
            .check_projectable(&pose, &[Point3::new(0.0, 0.0, 0.1)])
            .unwrap_err();
        assert!(format!("{err}").contains("vertex 0"));
    }

    #[test]
    fn reads_projection_text() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("projection_matrix.txt");
        std::fs::write(&path, "1.57443701 0.0 0.0 0.0\n0.0 1.57443701 0.0 0.0\n0.0 0.0 -0.99999976 -1.0\n0.0 0.0 -0.001 0.0\n").unwrap();
        assert_eq!(
            Camera::read_projection_txt(&path).unwrap(),
            Camera::release_projection()
        );
        std::fs::write(&path, "1 2 3").unwrap();
        let err = Camera::read_projection_txt(&path).unwrap_err().to_string();
        assert!(
            err.contains("projection_matrix.txt") && err.contains("16 numbers"),
            "{err}"
        );
    }

    proptest! {
        #[test]
        fn matrix_chain_equals_pinhole(yaw in -80.0f64..80.0, pitch in -60.0f64..50.0, roll in -90.0f64..60.0,
                                       tx in -0.1f64..0.1, ty in -0.1f64..0.1, tz in -0.9f64..-0.3,
                                       x in -0.08f64..0.08, y in -0.09f64..0.09, z in -0.02f64..0.07,
                                       w in 100u32..1500, h in 100u32..1500) {
            let cam = Camera::release(w, h);
            let pose = Pose::from_euler(EulerAngles::new(yaw, pitch, roll), Vector3::new(tx, ty, tz));
            let p = Point3::new(x, y, z);
            let a = cam.project(&pose, &p);
            let b = cam.project_camera_point(&pose.to_camera(&p));
            prop_assert!((a.u - b.x).abs() < 1e-6 && (a.v - b.y).abs() < 1e-6, "{a:?} {b}");
            // OpenCV's (R, t) with K gives the same pixel.
            let (r, t) = pose.to_opencv();
            let pc = r * p.coords + t;
            let k = cam.pinhole().k();
            let uvw = k * pc;
            prop_assert!((uvw.x / uvw.z - a.u).abs() < 1e-6 && (uvw.y / uvw.z - a.v).abs() < 1e-6);
        }
    }
}

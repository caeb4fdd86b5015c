//! `photo`: a face's pose in a photo, from the network's correspondences in its crop.
//!
//! The crop was cut from the official demo's 800-px square ([`DemoSquare`],
//! [`crate::picture::photo::demo_crop`]); each chosen crop pixel maps back to the square,
//! and PnP solves the pose in the camera of [`PhotoCamera`]: the demo's (the release's
//! projection for the square, the official `demo.py`'s `K`), or the photo's own pinhole
//! camera when its focal length is known (the pixels mapped on to the photo first).

use crate::crop::CropTransform;
use crate::picture::photo::DemoSquare;
use crate::pose::pnp::{Intrinsics, RansacParams};
use crate::pose::predict::{crop_pixel_to_image, intrinsics, pose_from_correspondences};
use arkit_core::conventions::Pose;
use arkit_core::{Error, Result};
use nalgebra::{Point2, Point3};

/// The camera a photo's faces are posed in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PhotoCamera {
    /// The official demo's: the release's projection for the 800-px square
    /// (`f = 1.57443701 x 400` px, centre `(400, 400)`), whatever the photo's real
    /// camera. Rotations are right for any photo whose field of view is close to the
    /// release's (about 65 degrees across the square); translations are in a camera
    /// that may not be the photo's.
    Demo,
    /// The photo's own pinhole camera: this focal length in the photo's pixels, the
    /// principal point at the photo's centre `(W / 2, H / 2)`, no distortion. The
    /// translation is then in that camera's metres.
    FocalPx(f64),
}

impl PhotoCamera {
    /// The camera whose horizontal field of view (across the photo's width) is
    /// `fov_deg`: `f = (W / 2) / tan(fov / 2)`.
    pub fn from_horizontal_fov(fov_deg: f64, width: u32) -> Result<Self> {
        if !(fov_deg > 1.0 && fov_deg < 179.0) {
            return Err(Error::invalid(
                "--fov-deg",
                format!("{fov_deg}: a horizontal field of view must lie in (1, 179) degrees"),
            ));
        }
        Ok(PhotoCamera::FocalPx(
            width as f64 / 2.0 / (fov_deg.to_radians() / 2.0).tan(),
        ))
    }

    /// Checks a focal length: finite and in `[1, 1e6]` pixels.
    pub fn check(&self) -> Result<()> {
        match *self {
            PhotoCamera::Demo => Ok(()),
            PhotoCamera::FocalPx(f) if f.is_finite() && (1.0..=1e6).contains(&f) => Ok(()),
            PhotoCamera::FocalPx(f) => Err(Error::invalid(
                "--focal-px",
                format!("{f}: a focal length must lie in [1, 1e6] pixels"),
            )),
        }
    }

    /// The intrinsics PnP uses, in the pixels `PhotoCamera::image_point` gives.
    pub fn intrinsics(&self, square: &DemoSquare) -> Intrinsics {
        match *self {
            PhotoCamera::Demo => intrinsics(square.side, square.side),
            PhotoCamera::FocalPx(f) => Intrinsics {
                fx: f,
                fy: f,
                cx: square.width as f64 / 2.0,
                cy: square.height as f64 / 2.0,
            },
        }
    }

    /// A point of the demo's square in this camera's image: itself for the demo's
    /// camera, the photo pixel under it for the photo's.
    pub(crate) fn image_point(&self, square: &DemoSquare, u: f64, v: f64) -> Point2<f64> {
        match self {
            PhotoCamera::Demo => Point2::new(u, v),
            PhotoCamera::FocalPx(_) => {
                let (x, y) = square.point_to_photo(u, v);
                Point2::new(x, y)
            }
        }
    }

    /// A camera's image point back in the photo's pixels.
    pub(crate) fn to_photo(self, square: &DemoSquare, p: Point2<f64>) -> (f64, f64) {
        match self {
            PhotoCamera::Demo => square.point_to_photo(p.x, p.y),
            PhotoCamera::FocalPx(_) => (p.x, p.y),
        }
    }

    /// Where a camera-space point (OpenCV's frame: x right, y down, z forward) falls in
    /// the photo, or `None` behind the camera.
    pub fn project_to_photo(&self, square: &DemoSquare, p: &Point3<f64>) -> Option<(f64, f64)> {
        if p.z <= 1e-9 {
            return None;
        }
        let k = self.intrinsics(square);
        let q = Point2::new(k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
        Some(self.to_photo(square, q))
    }
}

/// Checks a face box against a `width x height` photo: finite, `x0 < x1`, `y0 < y1`, and
/// overlapping the photo (a box may reach past the edges: the crop reads black there,
/// as the demo's `cv2.warpAffine` does).
pub fn check_box(b: [f64; 4], width: u32, height: u32) -> Result<()> {
    let [x0, y0, x1, y1] = b;
    if !b.iter().all(|v| v.is_finite()) || x1 <= x0 || y1 <= y0 {
        return Err(Error::invalid(
            "face box",
            format!("[{x0}, {y0}, {x1}, {y1}]: expected x0 < x1 and y0 < y1, all finite"),
        ));
    }
    if x1 <= 0.0 || y1 <= 0.0 || x0 >= width as f64 || y0 >= height as f64 {
        return Err(Error::invalid(
            "face box",
            format!("[{x0}, {y0}, {x1}, {y1}] lies outside the {width}x{height} photo"),
        ));
    }
    Ok(())
}

/// A face's solved pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FacePose {
    /// The pose, in the release's convention and the camera's metres.
    pub pose: Pose,
    /// RANSAC's inliers among `points`.
    pub inliers: usize,
    /// The distinct chosen pixels PnP was given.
    pub points: usize,
}

/// The pose of a face from the network's correspondences: `pixels` (flat indices
/// `y * S + x` of the `crop`, cut from `square`) and the canonical `points` (metres)
/// they show. Repeated pixels count once (the first). `None` when PnP fails (fewer than
/// four distinct points, or no pose in front of the camera).
pub fn face_pose(
    square: &DemoSquare,
    crop: &CropTransform,
    camera: &PhotoCamera,
    pixels: &[u32],
    points: &[[f32; 3]],
    ransac: &RansacParams,
) -> Result<Option<FacePose>> {
    if pixels.len() != points.len() {
        return Err(Error::invalid(
            "correspondences",
            format!("{} pixels but {} points", pixels.len(), points.len()),
        ));
    }
    let n = crop.size as u64 * crop.size as u64;
    if let Some(p) = pixels.iter().find(|&&p| p as u64 >= n) {
        return Err(Error::invalid(
            "correspondences",
            format!("pixel index {p} outside the {0}x{0} crop", crop.size),
        ));
    }
    camera.check()?;
    let mut seen = std::collections::HashSet::new();
    let (mut object, mut image) = (Vec::new(), Vec::new());
    for (&px, p) in pixels.iter().zip(points) {
        if seen.insert(px) {
            object.push(Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
            let q = crop_pixel_to_image(crop, px);
            image.push(camera.image_point(square, q.x, q.y));
        }
    }
    let k = camera.intrinsics(square);
    Ok(pose_from_correspondences(&object, &image, &k, ransac)
        .ok()
        .map(|(pose, inliers)| FacePose {
            pose,
            inliers,
            points: object.len(),
        }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::picture::photo::demo_crop;
    use arkit_core::conventions::EulerAngles;
    use nalgebra::Vector3;

    /// Points of a face posed in a camera, seen through a crop: the pose comes back in
    /// both cameras, on a non-square photo.
    #[test]
    fn a_face_seen_through_the_crop_gives_its_pose_back() {
        let square = DemoSquare::of(1200, 700, 800);
        let truth = Pose::from_euler(
            EulerAngles::new(20.0, -10.0, 5.0),
            Vector3::new(0.03, -0.02, -0.5),
        );
        // A grid of canonical points on a curved surface.
        let model: Vec<[f32; 3]> = (0..12)
            .flat_map(|i| {
                (0..12).map(move |j| {
                    let (x, y) = (i as f32 * 0.012 - 0.066, j as f32 * 0.014 - 0.077);
                    [x, y, 0.03 - 4.0 * (x * x + y * y)]
                })
            })
            .collect();
        for camera in [PhotoCamera::Demo, PhotoCamera::FocalPx(900.0)] {
            // Project each point into the photo's camera, then into the square, then
            // to the nearest crop pixel; keep the point the pixel shows exactly by
            // moving the 3D point onto the pixel's ray at its depth.
            let k = camera.intrinsics(&square);
            let (r, t) = truth.to_opencv();
            let cam: Vec<Point3<f64>> = model
                .iter()
                .map(|p| r * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64) + t)
                .collect();
            let (mut u0, mut v0, mut u1, mut v1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
            for p in &cam {
                let (x, y) = camera.project_to_photo(&square, p).unwrap();
                u0 = u0.min(x);
                v0 = v0.min(y);
                u1 = u1.max(x);
                v1 = v1.max(y);
            }
            let crop = demo_crop(square.box_to_square([u0, v0, u1, v1]), 192).unwrap();
            let (mut pixels, mut points) = (Vec::new(), Vec::new());
            for p in &cam {
                let (x, y) = camera.project_to_photo(&square, p).unwrap();
                let sq = (x + square.pad_left as f64) * square.scale();
                let sv = (y + square.pad_top as f64) * square.scale();
                let (cu, cv) = crop.to_crop(sq, sv);
                let o = crop.rules.sample_offset();
                let (i, j) = ((cu - o).round() as u32, (cv - o).round() as u32);
                pixels.push(j * 192 + i);
                // The 3D point on the ray through that pixel, at the point's depth.
                let q = crop_pixel_to_image(&crop, j * 192 + i);
                let q = camera.image_point(&square, q.x, q.y);
                let ray = Point3::new((q.x - k.cx) / k.fx * p.z, (q.y - k.cy) / k.fy * p.z, p.z);
                let back = r.inverse() * (ray - t);
                points.push([back.x as f32, back.y as f32, back.z as f32]);
            }
            let found = face_pose(
                &square,
                &crop,
                &camera,
                &pixels,
                &points,
                &RansacParams::default(),
            )
            .unwrap()
            .unwrap();
            assert_eq!(found.points, 144);
            assert_eq!(found.inliers, 144, "{camera:?}");
            let d = found.pose.translation_m() - truth.translation_m();
            assert!(d.norm() < 1e-4, "{camera:?}: {d}");
            let r = found.pose.rotation().inverse() * truth.rotation();
            let cos = ((r.matrix().trace() - 1.0) / 2.0).clamp(-1.0, 1.0);
            assert!(cos.acos().to_degrees() < 0.02, "{camera:?}: {cos}");
        }
    }

    #[test]
    fn the_field_of_view_gives_the_focal_length() {
        // 90 degrees across 1000 px: f = 500 / tan(45) = 500.
        let PhotoCamera::FocalPx(f) = PhotoCamera::from_horizontal_fov(90.0, 1000).unwrap() else {
            panic!()
        };
        assert!((f - 500.0).abs() < 1e-9);
        assert!(PhotoCamera::from_horizontal_fov(0.0, 1000).is_err());
        assert!(PhotoCamera::FocalPx(f64::NAN).check().is_err());
    }

    #[test]
    fn mismatched_or_outside_correspondences_are_refused() {
        let square = DemoSquare::of(800, 800, 800);
        let crop = demo_crop([100.0, 100.0, 300.0, 300.0], 64).unwrap();
        let r = RansacParams::default();
        let cam = PhotoCamera::Demo;
        assert!(face_pose(&square, &crop, &cam, &[1, 2], &[[0.0; 3]], &r).is_err());
        assert!(face_pose(&square, &crop, &cam, &[64 * 64], &[[0.0; 3]], &r).is_err());
        // Too few points: no pose, not an error.
        assert!(
            face_pose(&square, &crop, &cam, &[1, 2], &[[0.0; 3]; 2], &r)
                .unwrap()
                .is_none()
        );
    }
}

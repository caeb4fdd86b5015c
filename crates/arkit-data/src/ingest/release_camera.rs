//! `release_camera`: a captured image and its intrinsics checked and resampled into the
//! release's camera, for the ingesters of other cameras ([`crate::ingest::biwi`],
//! [`crate::ingest::import_arkit`]).

use arkit_core::conventions::Camera;
use image::{Rgb, RgbImage};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

/// Checks that the principal point of `k` lies in the middle half of a `width x
/// height` image (`|cx - w/2| <= w/4`, the same for y): true of every real camera's
/// intrinsics for the image they were calibrated on, false when the image was resized
/// by a factor of 2 or more, or the intrinsics belong to another resolution. The error
/// says what was found.
pub(crate) fn principal_point_check(
    k: &Matrix3<f64>,
    width: u32,
    height: u32,
) -> std::result::Result<(), String> {
    let (cx, cy) = (k[(0, 2)], k[(1, 2)]);
    let (w, h) = (width as f64, height as f64);
    if (cx - w / 2.0).abs() > w / 4.0 || (cy - h / 2.0).abs() > h / 4.0 {
        return Err(format!(
            "the intrinsics' principal point ({cx}, {cy}) is far from the centre of this {width}x{height} image: the intrinsics are for another image size (was the image resized?)"
        ));
    }
    Ok(())
}

/// Resamples a captured image (intrinsics `k`, OpenCV pixel convention) into the
/// release camera at `side x side` pixels, the written camera turned by `orientation`
/// (`d_captured = orientation d_written`). Bilinear; rays the capture did not see are
/// black.
pub fn resample_to_release(
    captured: &RgbImage,
    k: &Matrix3<f64>,
    orientation: &Matrix3<f64>,
    side: u32,
) -> RgbImage {
    let f = Camera::RELEASE_FOCAL_NDC * side as f64 / 2.0;
    let c = side as f64 / 2.0;
    let (w, h) = (captured.width() as f64, captured.height() as f64);
    let mut out = RgbImage::new(side, side);
    let rows: Vec<(u32, Vec<Rgb<u8>>)> = (0..side)
        .into_par_iter()
        .map(|j| {
            let row = (0..side)
                .map(|i| {
                    // The ray of the written pixel's centre, OpenGL camera frame.
                    let gl =
                        Vector3::new((i as f64 + 0.5 - c) / f, -(j as f64 + 0.5 - c) / f, -1.0);
                    let d = orientation * gl;
                    // OpenCV frame of the captured camera: (x, -y, -z).
                    let (x, y, z) = (d.x, -d.y, -d.z);
                    if z <= 0.0 {
                        return Rgb([0, 0, 0]);
                    }
                    let u = k[(0, 0)] * x / z + k[(0, 1)] * y / z + k[(0, 2)];
                    let v = k[(1, 1)] * y / z + k[(1, 2)];
                    if !(-0.5..w - 0.5).contains(&u) || !(-0.5..h - 0.5).contains(&v) {
                        return Rgb([0, 0, 0]);
                    }
                    bilinear(captured, u, v)
                })
                .collect();
            (j, row)
        })
        .collect();
    for (j, row) in rows {
        for (i, p) in row.into_iter().enumerate() {
            out.put_pixel(i as u32, j, p);
        }
    }
    out
}

/// Bilinear sample at `(u, v)`, pixel centres at integers, edges clamped.
fn bilinear(img: &RgbImage, u: f64, v: f64) -> Rgb<u8> {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let (u0, v0) = (u.floor(), v.floor());
    let (fu, fv) = (u - u0, v - v0);
    let at = |x: i64, y: i64| img.get_pixel(x.clamp(0, w - 1) as u32, y.clamp(0, h - 1) as u32);
    let (x0, y0) = (u0 as i64, v0 as i64);
    let (a, b, c, d) = (
        at(x0, y0),
        at(x0 + 1, y0),
        at(x0, y0 + 1),
        at(x0 + 1, y0 + 1),
    );
    Rgb(std::array::from_fn(|ch| {
        let top = a[ch] as f64 * (1.0 - fu) + b[ch] as f64 * fu;
        let bottom = c[ch] as f64 * (1.0 - fu) + d[ch] as f64 * fu;
        (top * (1.0 - fv) + bottom * fv).round().clamp(0.0, 255.0) as u8
    }))
}

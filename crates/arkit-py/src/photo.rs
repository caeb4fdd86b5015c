//! `arkit_tool.photo`: a photo read upright, its faces found (SeetaFace), each cropped as
//! the official `demo.py` crops it, and a face's pose from the network's correspondences.

use crate::errors::{DataError, run};
use arkit_core::Error;
use numpy::{
    IntoPyArray, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// A photo as people see it (`arkit_data::picture::read_photo_upright`): decoded as
/// `read_image` decodes it, then turned upright by its EXIF orientation. `(H, W, 3)`
/// uint8 RGB of the upright photo.
#[pyfunction]
pub(crate) fn read_photo_upright<'py>(
    py: Python<'py>,
    path: PathBuf,
) -> PyResult<Bound<'py, PyAny>> {
    let (img, _) = run(py, || arkit_data::picture::read_photo_upright(&path))?;
    let (w, h) = img.dimensions();
    Ok(img
        .into_raw()
        .into_pyarray(py)
        .reshape([h as usize, w as usize, 3])?
        .into_any())
}

/// A photo made ready for the network as the official `demo.py` makes it
/// (`arkit_data::picture::demo_crop`): padded with black to a square, resized to `side`
/// (`cv2.resize`, bilinear), and the crop of `box` (`[x0, y0, x1, y1]` in the photo's
/// pixels; finite, `x0 < x1`, `y0 < y1`, overlapping the photo) by the 0.75 rule through
/// `cv2.warpAffine`. Returns a dict: `square` (side x
/// side x 3 uint8), `crop` (size x size x 3 uint8), `input` (the crop as the network
/// takes it: 3 x size x size float32, ImageNet-normalised exactly as `predict` does),
/// `pad_left`, `pad_top`, `scale` and `box_square` (the box in the square's pixels).
#[pyfunction]
#[pyo3(signature = (photo, r#box, size=192, side=800))]
pub(crate) fn photo_crop<'py>(
    py: Python<'py>,
    photo: numpy::PyReadonlyArray3<'py, u8>,
    r#box: [f64; 4],
    size: u32,
    side: u32,
) -> PyResult<Bound<'py, PyDict>> {
    use arkit_data::picture::{DemoSquare, demo_crop};
    let shape = photo.shape().to_vec();
    let limit = arkit_core::limits::MAX_IMAGE_SIDE as usize;
    if shape[2] != 3
        || !(1..=limit).contains(&shape[0])
        || !(1..=limit).contains(&shape[1])
        || !(2..=arkit_core::limits::MAX_CROP_SIZE).contains(&size)
        || !(1..=8192).contains(&side)
    {
        return Err(DataError::new_err(format!(
            "photo_crop: photo {shape:?}, size {size}, side {side}: expected (H, W, 3) \
             uint8 with H and W in 1..={limit}, size in 2..=4096, side in 1..=8192"
        )));
    }
    let raw: Vec<u8> = photo.as_array().iter().copied().collect();
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    let (square, crop, frame, b) = run(py, || {
        arkit_data::pose::check_box(r#box, w, h)?;
        let img = image::RgbImage::from_raw(w, h, raw).expect("size matches");
        let frame = DemoSquare::of(w, h, side);
        let square = frame.image(&img);
        let b = frame.box_to_square(r#box);
        let crop = demo_crop(b, size)?.crop_image(&square);
        Ok::<_, Error>((square, crop, frame, b))
    })?;
    let d = PyDict::new(py);
    let side = side as usize;
    d.set_item(
        "square",
        square
            .into_raw()
            .into_pyarray(py)
            .reshape([side, side, 3])?,
    )?;
    let size = size as usize;
    let input = arkit_data::loader::normalise(crop.as_raw());
    d.set_item("input", input.into_pyarray(py).reshape([3, size, size])?)?;
    d.set_item(
        "crop",
        crop.into_raw().into_pyarray(py).reshape([size, size, 3])?,
    )?;
    d.set_item("pad_left", frame.pad_left)?;
    d.set_item("pad_top", frame.pad_top)?;
    d.set_item("scale", frame.scale())?;
    d.set_item("box_square", b.to_vec())?;
    Ok(d)
}

/// The pose of a face of a `width` x `height` photo from the network's correspondences
/// in the crop of `box` (as [`photo_crop`] cuts it at `size`): `pixels` (M flat crop
/// indices `y * size + x`) and `points` (M x 3 canonical metres), by our PnP (P3P + MSAC
/// RANSAC from `seed`, then Levenberg-Marquardt) in the official demo's camera, or the
/// photo's own with `focal_px`. `None` when PnP fails; else a dict: `R_t` (4 x 4, the
/// release's convention), `inliers`, `points` (distinct pixels used).
#[pyfunction]
#[pyo3(signature = (width, height, r#box, size, pixels, points, focal_px=None, threshold_px=8.0, seed=0))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn photo_pose<'py>(
    py: Python<'py>,
    width: u32,
    height: u32,
    r#box: [f64; 4],
    size: u32,
    pixels: PyReadonlyArray1<'py, i64>,
    points: PyReadonlyArray2<'py, f32>,
    focal_px: Option<f64>,
    threshold_px: f64,
    seed: u64,
) -> PyResult<Option<Bound<'py, PyDict>>> {
    use arkit_data::picture::{DEMO_SIDE, DemoSquare, demo_crop};
    use arkit_data::pose::{PhotoCamera, face_pose};
    let limit = arkit_core::limits::MAX_IMAGE_SIDE;
    if !(1..=limit).contains(&width)
        || !(1..=limit).contains(&height)
        || !(2..=arkit_core::limits::MAX_CROP_SIZE).contains(&size)
    {
        return Err(DataError::new_err(format!(
            "photo_pose: photo {width}x{height}, crop {size}: sides in 1..={limit}, crop in 2..=4096"
        )));
    }
    let pts = points.as_array();
    if pts.ncols() != 3 {
        return Err(DataError::new_err(format!(
            "photo_pose: points must be (M, 3), got {:?}",
            pts.shape()
        )));
    }
    let n = size as i64 * size as i64;
    let px: Vec<u32> = pixels
        .as_array()
        .iter()
        .map(|&p| {
            if (0..n).contains(&p) {
                Ok(p as u32)
            } else {
                Err(DataError::new_err(format!(
                    "photo_pose: pixel index {p} outside the {size}x{size} crop"
                )))
            }
        })
        .collect::<PyResult<_>>()?;
    let p3: Vec<[f32; 3]> = pts.rows().into_iter().map(|r| [r[0], r[1], r[2]]).collect();
    let camera = focal_px.map_or(PhotoCamera::Demo, PhotoCamera::FocalPx);
    let ransac = arkit_data::pose::RansacParams {
        reprojection_threshold_px: threshold_px,
        seed,
        ..Default::default()
    };
    let found = run(py, || {
        arkit_data::pose::check_box(r#box, width, height)?;
        let square = DemoSquare::of(width, height, DEMO_SIDE);
        let crop = demo_crop(square.box_to_square(r#box), size)?;
        face_pose(&square, &crop, &camera, &px, &p3, &ransac)
    })?;
    let Some(f) = found else {
        return Ok(None);
    };
    let d = PyDict::new(py);
    d.set_item(
        "R_t",
        f.pose
            .to_release_rt()
            .to_vec()
            .into_pyarray(py)
            .reshape([4, 4])?,
    )?;
    d.set_item("inliers", f.inliers)?;
    d.set_item("points", f.points)?;
    Ok(Some(d))
}

/// The faces SeetaFace's frontal detector (embedded; docs/photos.md) finds in a photo
/// (H x W x 3 uint8): a list of `(box, score)`, boxes `[x0, y0, x1, y1]` in the photo's
/// pixels, left to right; empty when there is none.
#[pyfunction]
#[pyo3(signature = (photo, min_face_px=40, score_threshold=2.0))]
#[allow(clippy::type_complexity)]
pub(crate) fn detect_faces(
    py: Python<'_>,
    photo: numpy::PyReadonlyArray3<'_, u8>,
    min_face_px: u32,
    score_threshold: f64,
) -> PyResult<Vec<([f64; 4], f64)>> {
    let shape = photo.shape().to_vec();
    let limit = arkit_core::limits::MAX_IMAGE_SIDE as usize;
    if shape[2] != 3 || !(1..=limit).contains(&shape[0]) || !(1..=limit).contains(&shape[1]) {
        return Err(DataError::new_err(format!(
            "detect_faces: photo {shape:?}: expected (H, W, 3) uint8 with H and W in 1..={limit}"
        )));
    }
    let raw: Vec<u8> = photo.as_array().iter().copied().collect();
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    let options = arkit_data::picture::DetectOptions {
        min_face_px,
        score_threshold,
    };
    let faces = run(py, || {
        let img = image::RgbImage::from_raw(w, h, raw).expect("size matches");
        arkit_data::picture::detect_faces(&img, &options)
    })?;
    Ok(faces.iter().map(|f| (f.bbox, f.score)).collect())
}

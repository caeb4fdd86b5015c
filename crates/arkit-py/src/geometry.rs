//! `arkit_tool`'s PnP, projection and metrics (`_geometry.py`): `solve_pnp_ransac`,
//! `project` (the release's camera) and `evaluate` (the paper's metrics, as `eval --json`).

use crate::errors::{DataError, run};
use arkit_core::conventions::{Camera, Pose};
use arkit_core::{Error, SampleKey};
use nalgebra::{Point2, Point3};
use numpy::{IntoPyArray, PyArrayMethods, PyReadonlyArray2};
use pyo3::prelude::*;
use std::path::{Path, PathBuf};

/// Robust PnP (P3P + MSAC + Levenberg-Marquardt) with OpenCV's conventions:
/// `X_cam = R X + t`, pixels, `camera_matrix` 3x3, no distortion. Returns
/// `(success, rvec (3, 1), tvec (3, 1), inliers (k, 1) int32)`, or
/// `(False, None, None, None)`. Correspondences with a NaN or infinite coordinate are
/// left out (never inliers; the inlier indices are the caller's).
#[pyfunction]
#[pyo3(signature = (object_points, image_points, camera_matrix, reprojection_error=8.0, iterations_count=100, confidence=0.99, seed=0))]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
pub(crate) fn solve_pnp_ransac<'py>(
    py: Python<'py>,
    object_points: PyReadonlyArray2<'py, f64>,
    image_points: PyReadonlyArray2<'py, f64>,
    camera_matrix: PyReadonlyArray2<'py, f64>,
    reprojection_error: f64,
    iterations_count: usize,
    confidence: f64,
    seed: u64,
) -> PyResult<(
    bool,
    Option<Py<PyAny>>,
    Option<Py<PyAny>>,
    Option<Py<PyAny>>,
)> {
    let (o, i, k) = (
        object_points.as_array(),
        image_points.as_array(),
        camera_matrix.as_array(),
    );
    if o.ncols() != 3 || i.ncols() != 2 || o.nrows() != i.nrows() {
        return Err(DataError::new_err(format!(
            "object_points must be (N, 3) and image_points (N, 2) with the same N; got {:?} and {:?}",
            o.shape(),
            i.shape()
        )));
    }
    if k.shape() != [3, 3] {
        return Err(DataError::new_err(format!(
            "camera_matrix must be 3x3, got {:?}",
            k.shape()
        )));
    }
    let object: Vec<Point3<f64>> = o
        .rows()
        .into_iter()
        .map(|r| Point3::new(r[0], r[1], r[2]))
        .collect();
    let image: Vec<Point2<f64>> = i
        .rows()
        .into_iter()
        .map(|r| Point2::new(r[0], r[1]))
        .collect();
    let intr = arkit_data::pose::Intrinsics {
        fx: k[[0, 0]],
        fy: k[[1, 1]],
        cx: k[[0, 2]],
        cy: k[[1, 2]],
    };
    let params = arkit_data::pose::RansacParams {
        reprojection_threshold_px: reprojection_error,
        max_iterations: iterations_count,
        confidence,
        seed,
    };
    let solved = py.detach(|| arkit_data::pose::solve_pnp_ransac(&object, &image, &intr, &params));
    match solved {
        Err(_) => Ok((false, None, None, None)),
        Ok(s) => {
            let r = s.rotation.scaled_axis();
            let rvec = vec![r.x, r.y, r.z].into_pyarray(py).reshape([3, 1])?;
            let t = s.translation;
            let tvec = vec![t.x, t.y, t.z].into_pyarray(py).reshape([3, 1])?;
            let inl: Vec<i32> = s.inliers.iter().map(|&x| x as i32).collect();
            let m = inl.len();
            let inliers = inl.into_pyarray(py).reshape([m, 1])?;
            Ok((
                true,
                Some(rvec.into_any().unbind()),
                Some(tvec.into_any().unbind()),
                Some(inliers.into_any().unbind()),
            ))
        }
    }
}

/// Projects canonical points `(N, 3)` with the release's `R_t` (4x4, row-vector form)
/// and camera for a `width x height` image: `(N, 2)` pixels (the release's y flip).
#[pyfunction]
pub(crate) fn project<'py>(
    py: Python<'py>,
    verts: PyReadonlyArray2<'py, f64>,
    r_t: PyReadonlyArray2<'py, f64>,
    width: u32,
    height: u32,
) -> PyResult<Bound<'py, PyAny>> {
    let (v, m) = (verts.as_array(), r_t.as_array());
    if v.ncols() != 3 || m.shape() != [4, 4] {
        return Err(DataError::new_err(format!(
            "verts must be (N, 3) and R_t 4x4; got {:?} and {:?}",
            v.shape(),
            m.shape()
        )));
    }
    let mut rt = [0f64; 16];
    for (k, x) in m.iter().enumerate() {
        rt[k] = *x;
    }
    let points: Vec<Point3<f64>> = v
        .rows()
        .into_iter()
        .map(|r| Point3::new(r[0], r[1], r[2]))
        .collect();
    let n = points.len();
    let out = run(py, || {
        let pose = Pose::from_release_rt(&rt)?;
        let camera = Camera::new(Camera::release_projection(), width, height)?;
        Ok(camera
            .project_all(&pose, &points)
            .iter()
            .flat_map(|p| [p.u, p.v])
            .collect::<Vec<f64>>())
    })?;
    Ok(out.into_pyarray(py).reshape([n, 2])?.into_any())
}

/// One prediction from Python: `(subject_id, facial_action, img_id, R_t or None)`.
type PredictionRow = (String, String, String, Option<Vec<f64>>);

/// The paper's metrics of `predictions` (`(subject_id, facial_action, img_id, R_t as 16
/// numbers or None)` rows, or a Parquet/CSV file's path) on `dir`: `eval --json`'s
/// output as JSON text.
#[pyfunction]
#[pyo3(signature = (dir, predictions=None, predictions_path=None, split=None))]
pub(crate) fn evaluate(
    py: Python<'_>,
    dir: PathBuf,
    predictions: Option<Vec<PredictionRow>>,
    predictions_path: Option<PathBuf>,
    split: Option<String>,
) -> PyResult<String> {
    run(py, || {
        let rows = match (predictions, predictions_path) {
            (Some(rows), None) => rows
                .into_iter()
                .enumerate()
                .map(|(i, (s, a, id, rt))| {
                    Ok(arkit_core::PredictionRecord {
                        key: SampleKey {
                            subject_id: s,
                            facial_action: a,
                            img_id: id,
                        },
                        rt: arkit_core::rt_of(rt.as_deref(), Path::new("predictions"), i)?,
                        verts: None,
                        mask_rle: None,
                    })
                })
                .collect::<arkit_core::Result<Vec<_>>>()?,
            (None, Some(path)) => arkit_data::store::read_predictions(&path)?,
            _ => {
                return Err(Error::invalid(
                    "predictions",
                    "give either rows or a file's path",
                ));
            }
        };
        let options = arkit_data::eval::EvalOptions {
            split,
            keep_worst: 0,
            ..Default::default()
        };
        let ev = arkit_data::eval::evaluate(&dir, &rows, &options)?;
        let p = &ev.problems;
        Ok(serde_json::json!({
            "summary": ev.summary,
            "problems": {
                "unknown": p.unknown.len(),
                "duplicates": p.duplicates.len(),
                "missing": p.missing,
                "non_rotations": p.non_rotations.len(),
            },
        })
        .to_string())
    })
}

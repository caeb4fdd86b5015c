//! `arkit_tool.conventions`: the head pose in other tools' conventions (OpenCV, ARKit,
//! Euler angles of each tool, TRG, img2pose) on (N, k) float64 rows, through
//! `arkit_core::conventions`.

use crate::errors::{DataError, py_err, run};
use arkit_core::Error;
use arkit_core::conventions::{AngleConvention, Pose};
use numpy::{IntoPyArray, PyArrayMethods, PyReadonlyArray2};
use pyo3::prelude::*;

/// The rows of `a` (N, K) float64, or `DataError` naming `name` when it has not K columns.
fn fixed_rows<const K: usize>(
    a: &PyReadonlyArray2<'_, f64>,
    name: &str,
) -> PyResult<Vec<[f64; K]>> {
    let v = a.as_array();
    if v.ncols() != K {
        return Err(DataError::new_err(format!(
            "{name}: shape {:?}; expected (N, {K})",
            v.shape()
        )));
    }
    Ok(v.rows()
        .into_iter()
        .map(|r| std::array::from_fn(|k| r[k]))
        .collect())
}

/// Pairs the rows of two inputs, one of which may have a single row that goes with
/// every row of the other.
fn paired<A: Copy, B: Copy>(a: &[A], b: &[B], names: (&str, &str)) -> PyResult<Vec<(A, B)>> {
    match (a.len(), b.len()) {
        (n, m) if n == m => Ok(a.iter().copied().zip(b.iter().copied()).collect()),
        (_, 1) => Ok(a.iter().map(|&x| (x, b[0])).collect()),
        (1, _) => Ok(b.iter().map(|&y| (a[0], y)).collect()),
        (n, m) => Err(DataError::new_err(format!(
            "{} and {}: {n} and {m} rows; expected as many of each, or one of either",
            names.0, names.1
        ))),
    }
}

/// `f` of every item, without the GIL, as an (N, K) float64 array; an error of item
/// `i` of several names it (`pose i: ...`).
fn convert_each<'py, T: Send + Sync, const K: usize>(
    py: Python<'py>,
    items: Vec<T>,
    f: impl Fn(&T) -> arkit_core::Result<[f64; K]> + Send + Sync,
) -> PyResult<Bound<'py, PyAny>> {
    let n = items.len();
    let out = run(py, || {
        let mut out = Vec::with_capacity(n * K);
        for (i, item) in items.iter().enumerate() {
            let row = f(item).map_err(|e| {
                if n > 1 {
                    Error::invalid(format!("pose {i}"), e.reason())
                } else {
                    e
                }
            })?;
            out.extend_from_slice(&row);
        }
        Ok(out)
    })?;
    Ok(out.into_pyarray(py).reshape([n, K])?.into_any())
}

/// A 4x4 matrix from its 16 values row by row (math layout, `x' = M x`).
fn matrix_rows(m: &[f64; 16]) -> nalgebra::Matrix4<f64> {
    nalgebra::Matrix4::from_row_slice(m)
}

/// The 16 values of `m`, row by row.
fn matrix_values(m: &nalgebra::Matrix4<f64>) -> [f64; 16] {
    std::array::from_fn(|k| m[(k / 4, k % 4)])
}

/// OpenCV's `[rvec, tvec]` (N, 6) of release `R_t`s given as (N, 16) rows (each
/// `R_t` row by row; any rigid `R_t`, the face in front of the camera or not).
#[pyfunction]
pub(crate) fn poses_to_opencv<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<16>(&r_t, "R_t")?, |rt| {
        let (r, t) = Pose::from_rigid_rt(rt)?.to_opencv_rvec();
        Ok([r.x, r.y, r.z, t.x, t.y, t.z])
    })
}

/// Release `R_t`s (N, 16) of OpenCV's `[rvec, tvec]` rows (N, 6).
#[pyfunction]
pub(crate) fn poses_from_opencv<'py>(
    py: Python<'py>,
    rvec_tvec: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<6>(&rvec_tvec, "rvec, tvec")?, |v| {
        finite(v, "rvec, tvec")?;
        let pose = Pose::from_opencv_rvec(
            &nalgebra::Vector3::new(v[0], v[1], v[2]),
            &nalgebra::Vector3::new(v[3], v[4], v[5]),
        );
        Ok(pose.to_release_rt())
    })
}

/// Release `R_t`s (N, 16) of ARKit's face anchor transforms seen from camera
/// transforms (each 4x4 in column form, `x_world = M x`, its 16 values row by row;
/// either input may have one row for all).
#[pyfunction]
pub(crate) fn poses_from_arkit<'py>(
    py: Python<'py>,
    face_anchor: PyReadonlyArray2<'py, f64>,
    camera: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let a = fixed_rows::<16>(&face_anchor, "face_anchor_transform")?;
    let c = fixed_rows::<16>(&camera, "camera_transform")?;
    let pairs = paired(&a, &c, ("face_anchor_transform", "camera_transform"))?;
    convert_each(py, pairs, |(a, c)| {
        Ok(Pose::from_arkit(&matrix_rows(a), &matrix_rows(c))?.to_release_rt())
    })
}

/// ARKit's face anchor transforms (N, 16, column form row by row) of release `R_t`s
/// (N, 16) seen from camera transforms (N or 1, 16).
#[pyfunction]
pub(crate) fn poses_to_arkit<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
    camera: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let p = fixed_rows::<16>(&r_t, "R_t")?;
    let c = fixed_rows::<16>(&camera, "camera_transform")?;
    let pairs = paired(&p, &c, ("R_t", "camera_transform"))?;
    convert_each(py, pairs, |(rt, c)| {
        let anchor = Pose::from_rigid_rt(rt)?.to_arkit(&matrix_rows(c))?;
        Ok(matrix_values(&anchor))
    })
}

/// The Euler angles (N, 3) of release `R_t`s (N, 16) in `convention` (`official`,
/// `wcpa`, `trg`, `6drepnet`, `img2pose`): that tool's order and unit.
#[pyfunction]
pub(crate) fn pose_angles<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
    convention: &str,
) -> PyResult<Bound<'py, PyAny>> {
    let c: AngleConvention = convention.parse().map_err(py_err)?;
    convert_each(py, fixed_rows::<16>(&r_t, "R_t")?, |rt| {
        Ok(c.angles(&Pose::from_rigid_rt(rt)?))
    })
}

/// Release `R_t`s (N, 16) of Euler angles (N or 1, 3) in `convention` and the
/// release's translations `R_t[3,:3]` (N or 1, 3).
#[pyfunction]
pub(crate) fn poses_from_angles<'py>(
    py: Python<'py>,
    angles: PyReadonlyArray2<'py, f64>,
    translation: PyReadonlyArray2<'py, f64>,
    convention: &str,
) -> PyResult<Bound<'py, PyAny>> {
    let c: AngleConvention = convention.parse().map_err(py_err)?;
    let a = fixed_rows::<3>(&angles, "angles")?;
    let t = fixed_rows::<3>(&translation, "translation")?;
    let pairs = paired(&a, &t, ("angles", "translation"))?;
    convert_each(py, pairs, |(a, t)| {
        finite(a, "angles")?;
        finite(t, "translation")?;
        Ok(c.from_angles(*a, nalgebra::Vector3::from(*t))
            .to_release_rt())
    })
}

/// TRG's row-vector `R_t`s (N, 16: `[[R'^T, 0], [t'^T, 1]]`, `R' = F R F`, `t' = F t`)
/// of release `R_t`s (N, 16).
#[pyfunction]
pub(crate) fn poses_to_trg<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<16>(&r_t, "R_t")?, |rt| {
        let (r, t) = Pose::from_rigid_rt(rt)?.to_trg();
        Ok(Pose::new(r, t).to_release_rt())
    })
}

/// Release `R_t`s (N, 16) of TRG's row-vector `R_t`s (N, 16).
#[pyfunction]
pub(crate) fn poses_from_trg<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<16>(&r_t, "TRG R_t")?, |rt| {
        let trg = Pose::from_rigid_rt(rt)?;
        Ok(Pose::from_trg(&trg.rotation(), &trg.translation_m()).to_release_rt())
    })
}

/// img2pose's `[rvec, t]` 6-vectors (N, 6) of release `R_t`s (N, 16).
#[pyfunction]
pub(crate) fn poses_to_img2pose<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<16>(&r_t, "R_t")?, |rt| {
        Ok(Pose::from_rigid_rt(rt)?.to_img2pose())
    })
}

/// Release `R_t`s (N, 16) of img2pose's `[rvec, t]` 6-vectors (N, 6).
#[pyfunction]
pub(crate) fn poses_from_img2pose<'py>(
    py: Python<'py>,
    dof: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<6>(&dof, "img2pose pose")?, |v| {
        finite(v, "img2pose pose")?;
        Ok(Pose::from_img2pose(v).to_release_rt())
    })
}

/// `DataError` (through `Error`) when a value of `v` is NaN or infinite.
fn finite(v: &[f64], name: &str) -> arkit_core::Result<()> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(k) => Err(Error::invalid(
            name,
            format!("non-finite value {} at [{k}]", v[k]),
        )),
        None => Ok(()),
    }
}

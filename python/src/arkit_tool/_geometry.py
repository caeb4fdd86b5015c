"""PnP with OpenCV's conventions (`solve_pnp_ransac`), the release's projection
(`project`) and the paper's metrics (`evaluate`): argument checks here, the work in Rust."""

from __future__ import annotations

import json
import os
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

from . import _native
from ._native import DataError
from .types import Key, Metrics, PathLike

_F64 = npt.NDArray[np.float64]


def solve_pnp_ransac(
    object_points: npt.ArrayLike,
    image_points: npt.ArrayLike,
    camera_matrix: npt.ArrayLike,
    dist_coeffs: Optional[npt.ArrayLike] = None,
    reprojection_error: float = 8.0,
    iterations_count: int = 100,
    confidence: float = 0.99,
    seed: int = 0,
) -> Tuple[bool, Optional[_F64], Optional[_F64], Optional[npt.NDArray[np.int32]]]:
    """PnP with RANSAC, OpenCV's conventions (`cv2.solvePnPRansac`'s arguments and
    result): `X_cam = R X + t`. `object_points` (N, 3), `image_points` (N, 2) (or
    OpenCV's (N, 1, 3) and (N, 1, 2)); any other shape, a transposed (3, N) among
    them, is refused (`DataError`). Returns `(success, rvec, tvec, inliers)`, rvec and
    tvec (3, 1) float64, inliers (k, 1) int32; `(False, None, None, None)` on failure.
    Distortion is not modelled: `dist_coeffs` must be None or zeros. Points with a NaN or
    infinite coordinate are left out (never inliers; indices are the caller's)."""
    if dist_coeffs is not None and np.any(np.asarray(dist_coeffs) != 0):
        raise DataError("dist_coeffs: lens distortion is not supported; undistort the points first")
    obj = _points("object_points", object_points, 3)
    img = _points("image_points", image_points, 2)
    if len(obj) != len(img):
        raise DataError(f"object_points and image_points: {len(obj)} and {len(img)} points; expected as many of each")
    k = np.ascontiguousarray(np.asarray(camera_matrix, dtype=np.float64))
    if k.shape != (3, 3):
        raise DataError(f"camera_matrix: shape {k.shape}; expected (3, 3)")
    return _native.solve_pnp_ransac(
        obj, img, k, float(reprojection_error), int(iterations_count), float(confidence), int(seed)
    )


def _points(name: str, value: npt.ArrayLike, width: int) -> _F64:
    """(N, width) float64 points; OpenCV's (N, 1, width) accepted; anything else refused."""
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 3 and a.shape[1] == 1:
        a = a[:, 0, :]
    if a.ndim != 2 or a.shape[1] != width:
        hint = " (transposed? pass the points as rows)" if a.ndim == 2 and a.shape[0] == width else ""
        raise DataError(f"{name}: shape {a.shape}; expected (N, {width}){hint}")
    return np.ascontiguousarray(a)


def _pose(name: str, value: npt.ArrayLike) -> _F64:
    """A 4x4 float64 pose from (4, 4) or its 16 values row by row."""
    a = np.asarray(value, dtype=np.float64)
    if a.shape == (16,):
        a = a.reshape(4, 4)
    if a.shape != (4, 4):
        raise DataError(f"{name}: shape {a.shape}; expected (4, 4) or 16 values row by row")
    return np.ascontiguousarray(a)


def project(verts: npt.ArrayLike, R_t: npt.ArrayLike, width: int, height: int) -> _F64:
    """Canonical points (N, 3) to image pixels (N, 2) with the release's row-vector
    `R_t` (4, 4), or its 16 values row by row (the samples table's flat form), and
    camera, for a `width x height` image. Any other shape (transposed points among
    them) is refused (`DataError`)."""
    v = _points("verts", verts, 3)
    m = _pose("R_t", R_t)
    return _native.project(v, m, int(width), int(height))


def evaluate(
    dataset: PathLike,
    predictions: Union[PathLike, Dict[Key, Any], Iterable[Tuple[str, str, str, Any]]],
    split: Optional[str] = None,
) -> Metrics:
    """The paper's metrics (what `arkit-tool eval --json` prints) of `predictions`: a
    predictions file (Parquet or CSV), a dict `{(subject_id, facial_action, img_id):
    R_t}` or rows `(subject_id, facial_action, img_id, R_t)`; an `R_t` (4 x 4, or its
    16 values row by row) of None is a failed prediction."""
    if isinstance(predictions, (str, os.PathLike)):
        text = _native.evaluate(os.fspath(dataset), None, os.fspath(predictions), split)
        metrics: Metrics = json.loads(text)
        return metrics
    items: Sequence[Any] = list(predictions.items()) if isinstance(predictions, dict) else list(predictions)
    rows: List[Tuple[str, str, str, Optional[List[float]]]] = []
    for item in items:
        if isinstance(predictions, dict):
            (s, a, i), rt = item
        else:
            s, a, i, rt = item
        flat = None if rt is None else [float(x) for x in _pose(f"R_t of {(s, a, i)}", rt).reshape(-1)]
        rows.append((str(s), str(a), str(i), flat))
    metrics = json.loads(_native.evaluate(os.fspath(dataset), rows, None, split))
    return metrics

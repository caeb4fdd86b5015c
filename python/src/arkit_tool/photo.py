"""Head poses from a photo, as the official `demo.py` finds them, without torch.

The same path as `arkit-tool predict --image` (docs/photos.md): the photo padded with
black to a square and resized to 800 px (`cv2.resize`'s bilinear rule), each face box
`[x0, y0, x1, y1]` (photo pixels) cut by the 0.75 x max(w, h) rule into the network's
crop (`cv2.warpAffine`'s rule) and ImageNet-normalised, the network's mask, chosen
pixels and correspondences, and our PnP in the demo's camera (or the photo's own with
`focal_px` / `fov_deg`). Every step but the network runs in arkit-tool's Rust core.

The network is any object with an `input_size` and a `predict(inputs, seeds)` that
returns, for a `(N, 3, S, S)` float32 batch and one seed per crop, an object with
`choose` (`(N, M)` flat crop pixel indices `y * S + x`, chosen from its mask with the
seed), `points` (`(N, M, 3)` canonical metres) and `vertices` (`(N, V, 3)` canonical
metres): `arkit_tool.onnx.OnnxPerspNet` (an exported model run by onnxruntime) is one.

    >>> from arkit_tool.onnx import OnnxPerspNet
    >>> from arkit_tool.photo import detect_faces, predict_photo, read_photo
    >>> photo = read_photo("group.jpg")
    >>> faces = predict_photo(photo, network=OnnxPerspNet("tiny-onnx"))
    >>> faces[0]["angles"]  # yaw, pitch, roll in degrees (the official convention)

Face `k` of a photo uses `seed ^ k` for its chosen pixels, and `seed` for RANSAC, as
`predict --image` does for its first photo: with the same weights (run by candle or by
onnxruntime) the two give the same poses up to the runtimes' float differences.
"""

from __future__ import annotations

import math
import os
from typing import Any, Dict, List, Optional, Protocol, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

from . import _native, conventions
from ._native import DataError
from .types import PhotoFace

DEMO_SIDE = 800
"""The side of the official demo's square."""

__all__ = [
    "DEMO_SIDE",
    "CropNetwork",
    "CropPrediction",
    "detect_faces",
    "predict_photo",
    "read_photo",
]


class CropPrediction(Protocol):
    """What a network's `predict` returns (see the module docs)."""

    @property
    def choose(self) -> npt.NDArray[np.int64]: ...

    @property
    def points(self) -> npt.NDArray[np.float32]: ...

    @property
    def vertices(self) -> npt.NDArray[np.float32]: ...


class CropNetwork(Protocol):
    """What `predict_photo` needs of a network (see the module docs)."""

    @property
    def input_size(self) -> int: ...

    def predict(self, image: npt.NDArray[np.float32], seeds: Sequence[int]) -> CropPrediction: ...


def read_photo(path: Union[str, "os.PathLike[str]"]) -> npt.NDArray[np.uint8]:
    """A PNG, JPEG or WebP file as an `(H, W, 3)` RGB uint8 array, turned upright by
    its EXIF orientation as `arkit-tool predict --image` turns it (its size checked
    from its header first; a truncated JPEG refused; `DataError` names the file and the
    problem)."""
    return _native.read_photo_upright(os.fspath(path))


def detect_faces(
    photo: npt.NDArray[np.uint8], min_face_px: int = 40, score_threshold: float = 2.0
) -> List[Tuple[List[float], float]]:
    """Faces found by SeetaFace's frontal detector (embedded in the package; roughly
    frontal faces of at least `min_face_px` pixels): `[(box, score), ...]` left to
    right, boxes `[x0, y0, x1, y1]` in the photo's pixels; `[]` when there is none."""
    return [
        (list(b), s)
        for b, s in _native.detect_faces(np.ascontiguousarray(photo), min_face_px, score_threshold)
    ]


def _camera_focal(
    width: int, focal_px: Optional[float], fov_deg: Optional[float]
) -> Optional[float]:
    if focal_px is not None and fov_deg is not None:
        raise DataError("give the photo's camera once: focal_px or fov_deg")
    if fov_deg is not None:
        if not 1.0 < fov_deg < 179.0:
            raise DataError(f"fov_deg {fov_deg}: a horizontal field of view lies in (1, 179)")
        return width / 2.0 / math.tan(math.radians(fov_deg) / 2.0)
    return focal_px


def predict_photo(
    photo: npt.NDArray[np.uint8],
    boxes: Optional[Sequence[Sequence[float]]] = None,
    *,
    network: CropNetwork,
    focal_px: Optional[float] = None,
    fov_deg: Optional[float] = None,
    seed: int = 0,
    threshold_px: float = 8.0,
    angles: conventions.Convention = "official",
    min_face_px: int = 40,
) -> List[PhotoFace]:
    """The pose of each face of `photo` (`(H, W, 3)` RGB uint8); `boxes` as the demo
    takes them, or found by `detect_faces` when `None`. One dict per face: `box`,
    `crop` (`(S, S, 3)` uint8, what the network saw), `choose`, `points`, `status`
    (`"ok"` or `"pnp failed"`) and, when posed, `R_t` (`(4, 4)`, the release's
    convention, the camera's metres), `angles` (`{name: value}` in `angles`'
    convention, order and unit), `translation_m`, `rvec` and `tvec_m` (OpenCV's),
    `inliers` and `vertices_m` (`(V, 3)` in camera space, the release's frame)."""
    photo = np.ascontiguousarray(photo)
    if photo.ndim != 3 or photo.shape[2] != 3 or photo.dtype != np.uint8:
        raise DataError(f"photo: expected (H, W, 3) uint8, got {photo.shape} {photo.dtype}")
    h, w = int(photo.shape[0]), int(photo.shape[1])
    focal = _camera_focal(w, focal_px, fov_deg)
    if boxes is None:
        boxes = [b for b, _ in detect_faces(photo, min_face_px)]
    given: List[List[float]] = [[float(v) for v in b] for b in boxes]
    for b in given:
        if len(b) != 4:
            raise DataError(f"face box {b}: expected [x0, y0, x1, y1]")
    if not given:
        return []
    size = int(network.input_size)
    crops = [_native.photo_crop(photo, b, size, DEMO_SIDE) for b in given]
    inputs = np.stack([c["input"] for c in crops]).astype(np.float32, copy=False)
    out = network.predict(inputs, [seed ^ k for k in range(len(given))])
    names = conventions.order(angles)
    faces: List[PhotoFace] = []
    for k, b in enumerate(given):
        choose = np.asarray(out.choose[k], dtype=np.int64)
        points = np.ascontiguousarray(out.points[k], dtype=np.float32)
        face: PhotoFace = {
            "box": b,
            "crop": crops[k]["crop"],
            "choose": choose,
            "points": points,
            "status": "pnp failed",
        }
        posed = _native.photo_pose(w, h, b, size, choose, points, focal, threshold_px, seed)
        if posed is not None:
            rt = posed["R_t"]
            a = conventions.angles(rt, angles)
            rvec, tvec = conventions.to_opencv(rt)
            face["status"] = "ok"
            face["R_t"] = rt
            face["angles"] = dict(zip(names, (float(x) for x in a.tolist())))
            face["translation_m"] = rt[3, :3].copy()
            face["rvec"] = rvec
            face["tvec_m"] = tvec
            face["inliers"] = int(posed["inliers"])
            v = np.asarray(out.vertices[k], dtype=np.float64)
            face["vertices_m"] = (np.c_[v, np.ones(len(v))] @ rt)[:, :3]
        faces.append(face)
    return faces

"""The head pose in other tools' conventions, computed by arkit-tool's Rust core.

Every function takes the release's row-vector `R_t` (`[x y z 1] @ R_t`, OpenGL camera:
y up, looking down -z), one pose `(4, 4)` or a batch `(N, 4, 4)`, or returns it, and
gives one result or a batch to match. Inputs are any array-likes of numbers, used as
float64; results are float64 numpy arrays. `F = diag(1, -1, -1)`.

- `to_opencv(R_t) -> (rvec, tvec)`, `from_opencv(rvec, tvec) -> R_t`: OpenCV's pose
  (`x_cv = Rodrigues(rvec) X + tvec`, looking down +z, y down); `rvec`, `tvec` are
  `(3,)` (or `(3, 1)` as `cv2.solvePnP` gives them) or `(N, 3)`.
- `from_arkit(face_anchor_transform, camera_transform) -> R_t` and
  `to_arkit(R_t, camera_transform) -> face_anchor_transform`: ARKit's world transforms
  (4x4, column form `x_world = M x`, translation in the last column; a `simd_float4x4`
  dumped as its 16 floats in memory order is column-major: `np.reshape(v, (4, 4)).T`).
  The pose is `inverse(camera) @ face_anchor`. No device-orientation rotation is
  applied: ARKit's camera x axis runs along the device's long side however the device
  is held, and whether the release's images were rotated could not be determined.
- `angles(R_t, convention) -> (3,)` or `(N, 3)`, `from_angles(angles, translation,
  convention) -> R_t`: Euler angles in a tool's order and unit (`CONVENTIONS`):
  `"official"` `[yaw, pitch, roll]` degrees (SciPy's 'yxz' of `R_t[:3,:3].T`),
  `"wcpa"` `[pitch, yaw, roll]` radians (same angles), `"trg"` `[yaw, pitch, roll]`
  degrees ('yxz' of TRG's rotation `F R F`), `"6drepnet"` `[pitch, yaw, roll]` degrees
  (its formula on `R_t[:3,:3]`), `"img2pose"` `[pitch, yaw, roll]` degrees (its AFLW
  conversion). `translation` is the release's `R_t[3,:3]` in metres.
- `to_trg(R_t)`, `from_trg(R_t_trg)`: TRG's row-vector `R_t` (`R' = F R F`, `t' = F t`).
- `to_img2pose(R_t) -> (6,)` or `(N, 6)`, `from_img2pose(pose)`: img2pose's
  `[rvec, t]` (its model frame: y down, z into the head).

Rotation vectors have their angle in `[0, pi]`. Inputs must be rigid (orthonormal
rotation, last column or row `(0, 0, 0, 1)`); the face need not be in front of the
camera. Anything else raises `DataError` naming the value (and the pose of a batch).
See docs/conventions.md.
"""

from __future__ import annotations

from typing import Literal, Tuple, get_args

import numpy as np
import numpy.typing as npt

from . import _native
from ._native import DataError

Convention = Literal["official", "wcpa", "trg", "6drepnet", "img2pose"]
"""The name of a tool's angle convention."""

CONVENTIONS: Tuple[Convention, ...] = get_args(Convention)
"""Every convention `angles` and `from_angles` accept."""

Array = npt.NDArray[np.float64]

__all__ = [
    "CONVENTIONS",
    "Convention",
    "angles",
    "from_angles",
    "from_arkit",
    "from_img2pose",
    "from_opencv",
    "from_trg",
    "order",
    "to_arkit",
    "to_img2pose",
    "to_opencv",
    "to_trg",
    "unit",
]


def _matrices(name: str, value: npt.ArrayLike) -> Tuple[Array, bool]:
    """(N, 16) rows of one (4, 4) matrix or a batch (N, 4, 4), and whether it was one."""
    a = np.asarray(value, dtype=np.float64)
    if a.shape == (4, 4):
        return np.ascontiguousarray(a.reshape(1, 16)), True
    if a.ndim == 3 and a.shape[1:] == (4, 4):
        return np.ascontiguousarray(a.reshape(-1, 16)), False
    raise DataError(f"{name}: shape {a.shape}; expected (4, 4) or (N, 4, 4)")


def _vectors(name: str, value: npt.ArrayLike, width: int) -> Tuple[Array, bool]:
    """(N, width) rows of one vector (width,) or (width, 1), or a batch (N, width) or
    (N, width, 1), and whether it was one."""
    a = np.asarray(value, dtype=np.float64)
    if a.shape in ((width,), (width, 1)):
        return np.ascontiguousarray(a.reshape(1, width)), True
    if a.ndim == 2 and a.shape[1] == width:
        return np.ascontiguousarray(a), False
    if a.ndim == 3 and a.shape[1:] == (width, 1):
        return np.ascontiguousarray(a.reshape(-1, width)), False
    raise DataError(f"{name}: shape {a.shape}; expected ({width},), ({width}, 1), (N, {width}) or (N, {width}, 1)")


def _out(rows: Array, single: bool, shape: Tuple[int, ...]) -> Array:
    """The native (N, k) rows in the caller's shape: one result or a batch."""
    out = rows.reshape((-1, *shape))
    return out[0] if single else out


def _convention(convention: Convention) -> Convention:
    if convention not in CONVENTIONS:
        raise DataError(f"convention: {convention!r}: expected one of {', '.join(CONVENTIONS)}")
    return convention


def to_opencv(R_t: npt.ArrayLike) -> Tuple[Array, Array]:
    """OpenCV's `(rvec, tvec)` of release poses: `(3,)` each, or `(N, 3)` each."""
    m, single = _matrices("R_t", R_t)
    out = _native.poses_to_opencv(m)
    return _out(out[:, :3], single, (3,)), _out(out[:, 3:], single, (3,))


def from_opencv(rvec: npt.ArrayLike, tvec: npt.ArrayLike) -> Array:
    """The release's `R_t` of OpenCV's `rvec` and `tvec` (`(3,)`, `(3, 1)`, `(N, 3)` or
    `(N, 3, 1)`; one of them may be a single vector for a batch of the other)."""
    r, r_single = _vectors("rvec", rvec, 3)
    t, t_single = _vectors("tvec", tvec, 3)
    if len(r) != len(t) and 1 not in (len(r), len(t)):
        raise DataError(f"rvec and tvec: {len(r)} and {len(t)} vectors; expected as many of each")
    r, t = np.broadcast_arrays(r, t)
    return _out(_native.poses_from_opencv(np.ascontiguousarray(np.hstack([r, t]))), r_single and t_single, (4, 4))


def from_arkit(face_anchor_transform: npt.ArrayLike, camera_transform: npt.ArrayLike) -> Array:
    """The release's `R_t` of ARKit's `faceAnchor.transform` seen from
    `camera.transform` (each `(4, 4)` column form, or `(N, 4, 4)`; a single camera
    goes with every anchor): `inverse(camera) @ face_anchor`, no device-orientation
    rotation."""
    a, a_single = _matrices("face_anchor_transform", face_anchor_transform)
    c, c_single = _matrices("camera_transform", camera_transform)
    return _out(_native.poses_from_arkit(a, c), a_single and c_single, (4, 4))


def to_arkit(R_t: npt.ArrayLike, camera_transform: npt.ArrayLike) -> Array:
    """ARKit's `faceAnchor.transform` (column form) of release poses seen from
    `camera_transform` (`(4, 4)` or `(N, 4, 4)`): `camera @ pose`."""
    m, m_single = _matrices("R_t", R_t)
    c, c_single = _matrices("camera_transform", camera_transform)
    return _out(_native.poses_to_arkit(m, c), m_single and c_single, (4, 4))


def angles(R_t: npt.ArrayLike, convention: Convention = "official") -> Array:
    """The Euler angles of release poses in `convention`'s order and unit: `(3,)` or
    `(N, 3)` (see the module docs)."""
    m, single = _matrices("R_t", R_t)
    return _out(_native.pose_angles(m, _convention(convention)), single, (3,))


def from_angles(
    angles: npt.ArrayLike, translation: npt.ArrayLike, convention: Convention = "official"
) -> Array:
    """The release's `R_t` of Euler angles in `convention`'s order and unit (`(3,)` or
    `(N, 3)`) and the release's translation `R_t[3,:3]` in metres (`(3,)` or `(N, 3)`;
    one of the two may be single for a batch of the other)."""
    a, a_single = _vectors("angles", angles, 3)
    t, t_single = _vectors("translation", translation, 3)
    return _out(_native.poses_from_angles(a, t, _convention(convention)), a_single and t_single, (4, 4))


def order(convention: Convention = "official") -> Tuple[str, str, str]:
    """The names of `angles`' three values in `convention`: `("yaw", "pitch", "roll")`
    for `official` and `trg`, `("pitch", "yaw", "roll")` for the others."""
    name = _convention(convention)
    return ("yaw", "pitch", "roll") if name in ("official", "trg") else ("pitch", "yaw", "roll")


def unit(convention: Convention = "official") -> Literal["deg", "rad"]:
    """The unit of `angles`' values in `convention`: radians for `wcpa`, else degrees."""
    return "rad" if _convention(convention) == "wcpa" else "deg"


def to_trg(R_t: npt.ArrayLike) -> Array:
    """TRG's row-vector `R_t` of release poses (what its ARKitFace loader makes of
    them): `(4, 4)` or `(N, 4, 4)`."""
    m, single = _matrices("R_t", R_t)
    return _out(_native.poses_to_trg(m), single, (4, 4))


def from_trg(R_t_trg: npt.ArrayLike) -> Array:
    """The release's `R_t` of TRG's row-vector `R_t` (inverse of `to_trg`)."""
    m, single = _matrices("R_t_trg", R_t_trg)
    return _out(_native.poses_from_trg(m), single, (4, 4))


def to_img2pose(R_t: npt.ArrayLike) -> Array:
    """img2pose's pose `[rvec, t]` of release poses: `(6,)` or `(N, 6)`."""
    m, single = _matrices("R_t", R_t)
    return _out(_native.poses_to_img2pose(m), single, (6,))


def from_img2pose(pose: npt.ArrayLike) -> Array:
    """The release's `R_t` of img2pose's `[rvec, t]` (`(6,)` or `(N, 6)`)."""
    v, single = _vectors("pose", pose, 6)
    return _out(_native.poses_from_img2pose(v), single, (4, 4))

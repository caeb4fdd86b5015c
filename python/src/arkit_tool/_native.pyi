"""Type stubs for `arkit_tool._native`, the Rust extension module (crates/arkit-py).

Checked against the built module by `mypy.stubtest` (python/tests/test_typing.py)."""

import pathlib
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import numpy.typing as npt
from typing_extensions import final

from .conventions import Convention
from .types import Compat, Corr, Item, Mode, PhotoCrop, PhotoPose, SampleRow, Topology
from .types import PathLike as _Path
from .types import SplitKey as _Key

__all__ = [
    "Loader",
    "Dataset",
    "solve_pnp_ransac",
    "project",
    "evaluate",
    "read_image",
    "read_photo_upright",
    "default_crop_store",
    "topology",
    "write_correspondence_matrix_into",
    "photo_crop",
    "photo_pose",
    "detect_faces",
    "poses_to_opencv",
    "poses_from_opencv",
    "poses_from_arkit",
    "poses_to_arkit",
    "pose_angles",
    "poses_from_angles",
    "poses_to_trg",
    "poses_from_trg",
    "poses_to_img2pose",
    "poses_from_img2pose",
    "choose_points",
    "DataError",
    "__version__",
]
__version__: str

class DataError(ValueError): ...

@final
class Loader:
    def __new__(
        cls,
        dir: str,
        split: Optional[str],
        mode: Mode,
        compat: Compat,
        img_size: int,
        n_pts: int,
        seed: int,
        resources: Optional[_Path] = None,
        crop_store: Optional[str] = None,
        cache_dir: Optional[_Path] = None,
        cache_bytes: Optional[int] = None,
        storage_options: Optional[Mapping[str, str]] = None,
    ) -> "Loader": ...
    def __len__(self) -> int: ...
    @property
    def crop_store(self) -> Optional[str]: ...
    @property
    def generation(self) -> str: ...
    @property
    def url(self) -> Optional[str]: ...
    def prefetch(self, indices: Sequence[int]) -> None: ...
    def prefetch_async(self, indices: Sequence[int]) -> None: ...
    def record(self, index: int) -> bytes: ...
    def supply(self, indices: Sequence[int], records: Sequence[bytes]) -> None: ...
    def key(self, index: int) -> _Key: ...
    def item(
        self,
        index: int,
        epoch: int = 0,
        corr: Corr = "dense",
        eval_keys: bool = False,
        extras: bool = False,
    ) -> Item: ...
    def batch(
        self,
        indices: Sequence[int],
        epoch: int = 0,
        corr: Corr = "dense",
        eval_keys: bool = False,
        reuse: Optional[Dict[str, npt.NDArray[Any]]] = None,
    ) -> Dict[str, Any]: ...

@final
class Dataset:
    def __new__(
        cls,
        dir: str,
        cache_dir: Optional[_Path] = None,
        storage_options: Optional[Mapping[str, str]] = None,
    ) -> "Dataset": ...
    def __len__(self) -> int: ...
    def keys(self) -> List[_Key]: ...
    def shard_files(self) -> List[str]: ...
    def manifest_json(self) -> str: ...
    def sample(self, index: int) -> SampleRow: ...

def solve_pnp_ransac(
    object_points: npt.NDArray[np.float64],
    image_points: npt.NDArray[np.float64],
    camera_matrix: npt.NDArray[np.float64],
    reprojection_error: float = 8.0,
    iterations_count: int = 100,
    confidence: float = 0.99,
    seed: int = 0,
) -> Tuple[
    bool, Optional[npt.NDArray[np.float64]], Optional[npt.NDArray[np.float64]], Optional[npt.NDArray[np.int32]]
]: ...
def project(
    verts: npt.NDArray[np.float64], r_t: npt.NDArray[np.float64], width: int, height: int
) -> npt.NDArray[np.float64]: ...
def evaluate(
    dir: _Path,
    predictions: Optional[Sequence[Tuple[str, str, str, Optional[Sequence[float]]]]] = None,
    predictions_path: Optional[_Path] = None,
    split: Optional[str] = None,
) -> str: ...
def default_crop_store(dir: _Path, compat: Compat, img_size: int) -> pathlib.Path: ...
def read_image(path: _Path) -> npt.NDArray[np.uint8]: ...
def read_photo_upright(path: _Path) -> npt.NDArray[np.uint8]: ...
def topology(dir: _Path, resources: Optional[_Path] = None) -> Topology: ...
def write_correspondence_matrix_into(
    out: npt.NDArray[np.float32],
    ids: npt.NDArray[np.int64],
    weights: npt.NDArray[np.float32],
    previous_ids: Optional[npt.NDArray[np.int64]] = None,
) -> None: ...

def photo_crop(
    photo: npt.NDArray[np.uint8],
    box: Sequence[float],
    size: int = 192,
    side: int = 800,
) -> PhotoCrop: ...

def photo_pose(
    width: int,
    height: int,
    box: Sequence[float],
    size: int,
    pixels: npt.NDArray[np.int64],
    points: npt.NDArray[np.float32],
    focal_px: Optional[float] = None,
    threshold_px: float = 8.0,
    seed: int = 0,
) -> Optional[PhotoPose]: ...
def detect_faces(
    photo: npt.NDArray[np.uint8], min_face_px: int = 40, score_threshold: float = 2.0
) -> List[Tuple[List[float], float]]: ...

def poses_to_opencv(r_t: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def poses_from_opencv(rvec_tvec: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def poses_from_arkit(
    face_anchor: npt.NDArray[np.float64], camera: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]: ...
def poses_to_arkit(r_t: npt.NDArray[np.float64], camera: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def pose_angles(r_t: npt.NDArray[np.float64], convention: Convention) -> npt.NDArray[np.float64]: ...
def poses_from_angles(
    angles: npt.NDArray[np.float64], translation: npt.NDArray[np.float64], convention: Convention
) -> npt.NDArray[np.float64]: ...
def poses_to_trg(r_t: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def poses_from_trg(r_t: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def poses_to_img2pose(r_t: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def poses_from_img2pose(dof: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...

# ONNX export: the point choice (arkit_tool.onnx).
def choose_points(mask: npt.NDArray[np.bool_], m: int, seed: int) -> npt.NDArray[np.int64]: ...

"""Types for annotating code that uses arkit_tool: the values its options take
(`Literal`s) and the dicts it returns (`TypedDict`s, with each key's type).

    from arkit_tool.types import Compat, Item

    def crop_of(ds: "arkit_tool.ARKitFaceDataset", i: int) -> Item:
        return ds[i]

The dicts are plain `dict`s at run time; the classes here only describe them. Arrays
are numpy arrays with their dtype (`npt.NDArray[np.float32]`, ...), or torch tensors
where the docs say so (`TensorItem`, `Batch`). Importing this module does not import
torch.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Dict, List, Literal, Optional, Tuple, TypedDict, Union

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    import torch

    from .correspondences import CorrespondenceMatrix

__all__ = [
    "Batch",
    "Compat",
    "Corr",
    "CropSampling",
    "EulerDifference",
    "Item",
    "Key",
    "LoaderState",
    "MaskScores",
    "Metrics",
    "MetricsProblems",
    "MetricsSummary",
    "Mode",
    "PathLike",
    "PhotoCrop",
    "PhotoFace",
    "PhotoPose",
    "Remainder",
    "SampleRow",
    "SamplerState",
    "SplitKey",
    "Targets",
    "TensorItem",
    "Topology",
]

PathLike = Union[str, "os.PathLike[str]"]
"""A file or folder: a `str` or a path object."""

Key = Tuple[str, str, str]
"""A sample's key: `(subject_id, facial_action, img_id)`."""

SplitKey = Tuple[str, str, str, str]
"""A sample's key and split: `(subject_id, facial_action, img_id, split)`."""

Compat = Literal["exact", "official"]
"""The rule set of box, crop, mask, points and UV map: ours (`"exact"`) or the official
loader's (`"official"`)."""

Mode = Literal["train", "eval"]
"""`"train"`: the official augmentation; `"eval"`: none, and the evaluation keys."""

Corr = Literal["dense", "sparse", "both"]
"""The correspondences a sample carries: `corr_mat` (`"dense"`), `corr_ids` and
`corr_weights` (`"sparse"`), or all three (`"both"`)."""

Remainder = Literal["pad", "drop"]
"""What an `EpochSampler` does with an order that does not divide among the ranks."""

CropSampling = Literal["centre", "corner"]
"""Where crop pixel `(i, j)` sits in crop coordinates (a targets row's `crop_sampling`)."""

EulerDifference = Literal["official", "wrapped"]
"""How `evaluate` takes Euler angle differences."""

# Split names are not a Literal: `arkit-tool split` writes train, test and val, but a
# dataset's splits file may name others, and every name it holds is valid.

_F32 = npt.NDArray[np.float32]
_F64 = npt.NDArray[np.float64]
_I64 = npt.NDArray[np.int64]


class _ItemArrays(TypedDict):
    img: _F32
    """3 x S x S, `ToTensor` + `Normalize(ImageNet mean, std)` of the crop."""
    choose: _I64
    """n_pts crop pixel indices `row * S + col` of the sampled face points."""
    model: _F32
    """V x 3, the mesh (metres, canonical frame)."""
    uvmap: _F32
    """3 x S x S UV position map in [-1, 1]."""
    nocs: _F32
    """n_pts x 3, each point's canonical position times 4.5."""
    mask: _I64
    """S x S crop face mask."""


class Item(_ItemArrays, total=False):
    """What `ARKitFaceDataset(tensors=False)` returns for one sample (`ds[i]`,
    `ds.item(i)`): the official `ARKitDataset.get_item`'s keys. Which of the optional
    keys are there depends on the dataset's `corr` and `mode` and on `item(extras=True)`."""

    corr_mat: _F32
    """n_pts x V (`corr="dense"` or `"both"`)."""
    corr_ids: _I64
    """n_pts x 3 vertex ids (`corr="sparse"` or `"both"`)."""
    corr_weights: _F32
    """n_pts x 3 barycentric weights (`corr="sparse"` or `"both"`)."""
    tform_inv: _F64
    """2 x 3, crop pixel `(col, row)` to image point (`mode="eval"`)."""
    R_t: _F64
    """4 x 4, the release's pose (`mode="eval"`)."""
    img_path: str
    subjectid: str
    imgid: str
    facial_action: str
    choose_box: _I64
    """`extras`: the points before mapping (official rules; empty otherwise)."""
    box: _I64
    """`extras`: the official integer box (official rules)."""
    box_clipped: bool
    crop: Tuple[float, float, float, float]
    """`extras`: `(x0, y0, side_x, side_y)` of the crop in the image."""
    image_path: str


class _TensorItemArrays(TypedDict):
    img: torch.Tensor
    choose: torch.Tensor
    model: torch.Tensor
    uvmap: torch.Tensor
    nocs: torch.Tensor
    mask: torch.Tensor


class TensorItem(_TensorItemArrays, total=False):
    """`Item` as `ARKitFaceDataset(tensors=True)` returns it: the arrays as torch
    tensors (sharing their memory), the rest as they are."""

    corr_mat: torch.Tensor
    corr_ids: torch.Tensor
    corr_weights: torch.Tensor
    tform_inv: torch.Tensor
    R_t: torch.Tensor
    img_path: str
    subjectid: str
    imgid: str
    facial_action: str
    choose_box: torch.Tensor
    box: torch.Tensor
    box_clipped: bool
    crop: Tuple[float, float, float, float]
    image_path: str


class _BatchArrays(TypedDict):
    img: torch.Tensor
    choose: torch.Tensor
    model: torch.Tensor
    uvmap: torch.Tensor
    nocs: torch.Tensor
    mask: torch.Tensor


class Batch(_BatchArrays, total=False):
    """A batch of `ARKitFaceDataset` samples as `collate` (`ds.loader`) gives it: `Item`'s
    keys, tensors with a leading batch axis, strings as lists, and `corr_mat` as a
    `CorrespondenceMatrix` (`.to(device)` gives the dense tensor)."""

    corr_mat: CorrespondenceMatrix
    corr_ids: torch.Tensor
    corr_weights: torch.Tensor
    tform_inv: torch.Tensor
    R_t: torch.Tensor
    img_path: List[str]
    subjectid: List[str]
    imgid: List[str]
    facial_action: List[str]


class SampleRow(TypedDict):
    """One row of a converted dataset's samples table (`ConvertedDataset.sample`)."""

    subject_id: str
    facial_action: str
    img_id: str
    split: str
    """The split the dataset assigns (`split`'s, else the release list's)."""
    listed_split: str
    """The release list the sample was converted from."""
    image_path: Optional[str]
    """None when the image is embedded in the table."""
    image_width: int
    image_height: int
    verts: _F32
    """V x 3, the mesh (metres, canonical frame)."""
    R_t: _F64
    """4 x 4, the release's row-vector pose."""
    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    translation_m: _F64
    landmarks_2d: _F32
    """68 x 2 image points."""
    face_box: _F64
    """`[x0, y0, x1, y1]` in the image."""


class _TargetColumns(TypedDict, total=False):
    subject_id: str
    facial_action: str
    img_id: str
    crop_x0: float
    crop_y0: float
    crop_side: float
    crop_side_y: float
    crop_size: int
    crop_sampling: CropSampling
    uv_size: int
    image_width: int
    image_height: int


class Targets(_TargetColumns):
    """One row of `render`'s targets table decoded (`decode_targets`): the row's columns
    that are not blobs as they are (those of schemas/targets.json listed here), and the
    decoded arrays."""

    mask: npt.NDArray[np.bool_]
    """S x S, S = crop_size."""
    corr_vertices: npt.NDArray[np.uint16]
    """k x 3: the visible triangle of each of the k face pixels, row-major."""
    corr_weights: _F32
    """k x 3 barycentric weights."""
    points: _I64
    """n rows of the k face pixels."""
    uv_map: npt.NDArray[np.float16]
    """uv x uv x 3 canonical positions, NaN where no UV triangle covers a texel."""
    full_mask: Optional[npt.NDArray[np.bool_]]
    """image_height x image_width, or None when not rendered."""


class MaskScores(TypedDict):
    accuracy: float
    iou: float
    precision: float


class MetricsSummary(TypedDict):
    """The paper's table and more (docs/eval.md)."""

    samples: int
    pose_failures: int
    missing: int
    euler_difference: EulerDifference
    yaw_mae_deg: float
    pitch_mae_deg: float
    roll_mae_deg: float
    mae_r_deg: float
    tx_mae_mm: float
    ty_mae_mm: float
    tz_mae_mm: float
    mae_t_mm: float
    add_mm: float
    rotation_mean_deg: float
    rotation_median_deg: float
    translation_median_mm: float
    success_5deg5cm_pct: float
    success_5deg10cm_pct: float
    success_10deg5cm_pct: float
    recon_mean_mm: Optional[float]
    recon_median_mm: Optional[float]
    mask: Optional[MaskScores]


class MetricsProblems(TypedDict):
    """Counts of prediction rows not scored as given."""

    unknown: int
    duplicates: int
    missing: int
    non_rotations: int


class Metrics(TypedDict):
    """What `evaluate` returns (`arkit-tool eval --json`'s output)."""

    summary: MetricsSummary
    problems: MetricsProblems


class SamplerState(TypedDict):
    """`EpochSampler.state_dict()`: the next index to be drawn and the order it belongs to."""

    version: int
    epoch: int
    position: int
    seed: int
    size: int
    shuffle: bool
    num_replicas: int
    rank: int
    remainder: Remainder


class LoaderState(SamplerState):
    """`EpochLoader.state_dict()`: the sampler's state at the next batch to hand out."""

    batch_size: int


class Topology(TypedDict):
    """The face topology a dataset was converted with (`_native.topology`)."""

    triangles: npt.NDArray[np.uint32]
    landmarks: npt.NDArray[np.uint32]
    uv: _F32
    vertex_count: int
    source: str


class PhotoCrop(TypedDict):
    """A photo made ready for the network as the official demo makes it
    (`_native.photo_crop`)."""

    square: npt.NDArray[np.uint8]
    input: _F32
    crop: npt.NDArray[np.uint8]
    pad_left: int
    pad_top: int
    scale: float
    box_square: List[float]


class PhotoPose(TypedDict):
    """A face's pose from the network's correspondences (`_native.photo_pose`)."""

    R_t: _F64
    inliers: int
    points: int


class _PhotoFaceBase(TypedDict):
    box: List[float]
    crop: npt.NDArray[np.uint8]
    choose: npt.NDArray[np.int64]
    points: npt.NDArray[np.float32]
    status: Literal["ok", "pnp failed"]


class PhotoFace(_PhotoFaceBase, total=False):
    """One face of `arkit_tool.photo.predict_photo`: always its box, crop, chosen pixels,
    their points and status; when posed (`status == "ok"`) also the pose fields."""

    R_t: _F64
    angles: Dict[str, float]
    translation_m: _F64
    rvec: _F64
    tvec_m: _F64
    inliers: int
    vertices_m: _F64

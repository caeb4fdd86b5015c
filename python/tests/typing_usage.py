"""arkit_tool as a user calls it, with annotations: `test_typing.py` checks this file
with `mypy --strict` against the package's own types (`py.typed`, the annotations,
`_native.pyi`); every line here must type-check as written. Not run."""

from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import numpy as np
import numpy.typing as npt
import torch
from torch.utils.data import DataLoader

import arkit_tool
from arkit_tool import (
    ARKitFaceDataset,
    CorrespondenceMatrix,
    DataError,
    EpochSampler,
    _native,
    collate,
    conventions,
    decode_targets,
    evaluate,
    open_dataset,
    project,
    read_image,
    solve_pnp_ransac,
)
from arkit_tool.photo import CropNetwork, detect_faces, predict_photo, read_photo
from arkit_tool.types import (
    Batch,
    Compat,
    Item,
    Key,
    LoaderState,
    Metrics,
    Mode,
    SampleRow,
    Targets,
    TensorItem,
)

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


# -- a converted dataset ---------------------------------------------------------------


def converted(path: str) -> Tuple[int, Dict[str, int], SampleRow]:
    data = open_dataset(path)
    first: Key = data.keys[0]
    row = data.sample(first)
    verts: F32 = row["verts"]
    r_t: F64 = data.sample(0)["R_t"]
    image: Optional[str] = row["image_path"]
    print(verts.shape, r_t[3, :3], image, data.manifest["version"], data.shard_files)
    return len(data), data.splits, row


def targets(rows: List[Dict[str, object]]) -> Tuple[npt.NDArray[np.bool_], int]:
    t: Targets = decode_targets(rows[0])
    full = t["full_mask"]
    side = t["mask"].shape[0] if full is None else full.shape[0]
    return t["mask"], side + t["crop_size"]


# -- the training and evaluation samples -------------------------------------------------


def samples(path: str, compat: Compat = "official", mode: Mode = "eval") -> F32:
    ds = ARKitFaceDataset(path, split="train", mode=mode, compat=compat, corr="both", n_pts=256)
    item: Item = ds[0]
    again = ds[3, 0]  # (epoch, position)
    img: F32 = item["img"]
    choose: npt.NDArray[np.int64] = again["choose"]
    if "R_t" in item:
        print(item["R_t"] @ np.eye(4), item.get("img_path"))
    extras = ds.item(1, epoch=2, extras=True)
    print(extras.get("crop"), ds.key(0)[3], len(ds), ds.crop_store, choose.dtype)
    ds.set_epoch(5)
    return img


def tensors(path: str) -> torch.Tensor:
    ds = ARKitFaceDataset(path, tensors=True)
    item: TensorItem = ds[0]
    return item["img"].to("cpu")


class Epochs(ARKitFaceDataset):
    """A subclass deriving its epoch otherwise (the docs' example)."""

    def current_epoch(self) -> int:
        return 7


def subclass(path: str) -> F32:
    return Epochs(path)[0]["nocs"]


# -- torch's DataLoader ------------------------------------------------------------------


def train(path: str, device: torch.device) -> LoaderState:
    ds = ARKitFaceDataset(path, compat="official")
    loader = ds.loader(64, shuffle=True, num_workers=2, persistent_workers=True)
    loader.set_epoch(0)
    for batch in loader:
        img = batch["img"].to(device)
        corr = batch["corr_mat"].to(device)
        paths: List[str] = batch.get("img_path", [])
        print(img.shape, corr.shape, paths)
        break
    state = loader.state_dict()
    again = ds.loader(64, shuffle=True)
    again.load_state_dict(state)
    return state


def plain_dataloader(path: str) -> None:
    # The official train.py's way: a plain DataLoader over the dataset.
    ds = ARKitFaceDataset(path, compat="official")
    for batch in DataLoader(ds, batch_size=8, num_workers=0):
        print(batch["img"].shape)
    sampler: EpochSampler = ds.sampler(shuffle=True, seed=3, remainder="drop")
    own = DataLoader(ds, batch_size=8, sampler=sampler, collate_fn=collate)
    print(len(own), sampler.state_dict()["epoch"])


def custom_collate(path: str) -> int:
    ds = ARKitFaceDataset(path)
    loader = ds.loader(4, collate_fn=lambda samples: len(samples))
    return sum(n for n in loader)


def one_batch(path: str) -> Batch:
    ds = ARKitFaceDataset(path, corr="sparse", mode="eval")
    batch = collate(ds.__getitems__([0, 1, 2]))
    m = batch.get("corr_mat")
    if isinstance(m, CorrespondenceMatrix):
        dense: torch.Tensor = m.to("cpu")
        host: np.ndarray = m.numpy()
        print(dense.shape, host.dtype, m.shape[1], m.row(0).vertex_count)
    return batch


# -- poses, PnP and metrics --------------------------------------------------------------


def pose_of(points3d: F64, pixels: F64, k: F64) -> Optional[F64]:
    ok, rvec, tvec, inliers = solve_pnp_ransac(points3d, pixels, k, reprojection_error=4.0, seed=1)
    if not ok or rvec is None or tvec is None:
        return None
    r_t: F64 = conventions.from_opencv(rvec, tvec)
    return r_t


def projected(verts: F64, r_t: F64) -> F64:
    return project(verts, r_t.reshape(-1), 800, 800)


def metrics(path: str, predictions: Dict[Key, Optional[F64]]) -> float:
    m: Metrics = evaluate(path, predictions, split="test")
    from_file = evaluate(path, "predictions.parquet")
    mask = m["summary"]["mask"]
    iou = 0.0 if mask is None else mask["iou"]
    return m["summary"]["mae_r_deg"] + from_file["summary"]["success_5deg5cm_pct"] + iou


def pose_conventions(r_t: F64) -> F64:
    rvec, tvec = conventions.to_opencv(r_t)
    name: conventions.Convention = "6drepnet"
    same: F64 = conventions.from_opencv(rvec, tvec)
    return conventions.angles(same, name) + conventions.to_img2pose(r_t)[:3]


def errors(path: str) -> str:
    try:
        open_dataset(path)
    except DataError as e:  # a ValueError
        error: ValueError = e
        return str(error)
    return ""


# -- photos ------------------------------------------------------------------------------


def photo(path: str, network: CropNetwork) -> List[Tuple[List[float], float]]:
    picture = read_photo(path)
    faces = predict_photo(picture, network=network, angles="trg")
    print(faces[0]["angles"] if faces else None)
    return detect_faces(picture, min_face_px=60)


def photo_without_torch(path: str, exported: str) -> int:
    from arkit_tool.onnx import OnnxPerspNet  # a CropNetwork

    return len(predict_photo(read_photo(path), network=OnnxPerspNet(exported), focal_px=1400.0))


# -- the extension module ----------------------------------------------------------------


def native(path: str) -> str:
    loader = _native.Loader(path, None, "train", "official", 192, 1024, 0)
    store = loader.crop_store
    batch = loader.batch([0, 1], epoch=2, corr="sparse")
    topo = _native.topology(path)
    crop = _native.photo_crop(read_image(path), [10.0, 10.0, 90.0, 90.0])
    print(store, batch.keys(), topo["triangles"].shape, crop["input"].shape, arkit_tool.__version__)
    return _native.evaluate(path, predictions=[("s", "a", "1", None)], split="test")

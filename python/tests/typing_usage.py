"""Calls of the package's typed API as a user writes them; `test_typing.py` checks this
file with mypy against the shipped stubs (`py.typed`, `_native.pyi`). Not run."""

from typing import Dict, List, Optional, Tuple

import numpy as np

import arkit_tool
from arkit_tool import _native


def pose_of(points3d: np.ndarray, points2d: np.ndarray, k: np.ndarray) -> Optional[np.ndarray]:
    ok, rvec, tvec, inliers = _native.solve_pnp_ransac(points3d, points2d, k, reprojection_error=4.0, seed=1)
    return tvec if ok else None


def first_keys(path: str) -> List[Tuple[str, str, str, str]]:
    ds = _native.Dataset(path)
    n: int = len(ds)
    manifest: str = ds.manifest_json()
    return ds.keys()[: min(n, len(manifest))]


def one_batch(path: str) -> Dict[str, object]:
    loader = _native.Loader(path, None, "train", "official", 192, 1024, 0)
    store: Optional[str] = loader.crop_store
    if store is None:
        pass
    return loader.batch([0, 1], epoch=2, corr="sparse")


def image(path: str) -> np.ndarray:
    img = _native.read_image(path)
    return img.astype(np.float32)


def metrics(path: str) -> str:
    return _native.evaluate(path, predictions=[("s", "a", "1", None)], split="test")


def the_error_is_a_value_error(e: _native.DataError) -> ValueError:
    return e


def the_dataset_class() -> type:
    return arkit_tool.ARKitFaceDataset


def corr_mat_usage(batch: "dict[str, object]") -> None:
    import numpy as np
    import torch

    from arkit_tool import CorrespondenceMatrix

    m = batch["corr_mat"]
    assert isinstance(m, CorrespondenceMatrix)
    dense: torch.Tensor = m.to("cpu")
    rows: int = m.shape[1]
    host: np.ndarray = m.numpy()
    print(dense.shape, rows, host.dtype, m.row(0).vertex_count)


def pose_conventions(r_t: np.ndarray) -> np.ndarray:
    from arkit_tool import conventions

    rvec, tvec = conventions.to_opencv(r_t)
    name: conventions.Convention = "6drepnet"
    same: np.ndarray = conventions.from_opencv(rvec, tvec)
    return conventions.angles(same, name) + conventions.to_img2pose(r_t)[:3]

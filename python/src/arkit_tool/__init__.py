"""arkit_tool: the ARKitFace dataset for PyTorch, computed in Rust (the `arkit_data` library).

- `open_dataset(DIR)`: a dataset written by `arkit-tool convert`: its samples table, its
  splits, one sample by position or key.
- `ARKitFaceDataset(DIR, ...)`: a map-style dataset returning what the official
  `ARKitDataset.get_item` returns (same keys, shapes, dtypes and meaning), computed on
  the fly from the release's images and meshes; `compat="official"` follows the official
  loader's rules, `compat="exact"` ours. `ds.loader(batch_size, ...)` is a
  `torch.utils.data.DataLoader` over it whose batches are computed in place (`collate`),
  whose epochs reach every worker, which shards by rank under `torchrun` and which
  resumes mid-epoch (`state_dict` / `load_state_dict`): `EpochLoader`, `EpochSampler`.
- `solve_pnp_ransac`, `project`, `evaluate`: PnP with OpenCV's conventions, the release's
  projection, the paper's metrics.
- `decode_targets(row)`: one row of `arkit-tool render`'s compact targets table as numpy
  arrays (plain numpy; the layouts are in schemas/targets.json).
- `conventions`: the release's `R_t` to and from OpenCV's `rvec`/`tvec`, ARKit's
  transforms, TRG's and img2pose's poses, and each tool's Euler angles.
- `types`: the options' values (`Literal`s) and the dicts returned (`TypedDict`s), for
  annotations; the package is typed (`py.typed`).

Errors are `DataError` (a `ValueError`) with a message naming the file and the problem.
See docs/python.md in the repository.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from . import _native, conventions
from ._collate import ItemBatch, SampleView, collate
from ._converted import ConvertedDataset, open_dataset, read_image
from ._dataset import ARKitFaceDataset
from ._geometry import evaluate, project, solve_pnp_ransac
from ._native import DataError
from ._targets import decode_targets
from .correspondences import CorrespondenceMatrix
from .sampling import EpochSampler, distributed_rank

__all__ = [
    "ARKitFaceDataset",
    "ConvertedDataset",
    "CorrespondenceMatrix",
    "DataError",
    "EpochSampler",
    "ItemBatch",
    "collate",
    "conventions",
    "decode_targets",
    "distributed_rank",
    "evaluate",
    "open_dataset",
    "project",
    "read_image",
    "solve_pnp_ransac",
]
__version__ = _native.__version__

# Named where users import it, so that it pickles: a DataLoader worker sends the
# exception of a sample that fails to the training process (under its Rust module's
# name it could not be found there, and the batch never arrived).
DataError.__module__ = "arkit_tool"

if TYPE_CHECKING:
    from .sampling import EpochLoader as EpochLoader
else:

    def __getattr__(name: str) -> Any:
        # EpochLoader subclasses torch's DataLoader: made on first use, so that importing
        # arkit_tool does not import torch (not in __all__ for the same reason).
        if name == "EpochLoader":
            from .sampling import loader_class

            return loader_class()
        raise AttributeError(f"module 'arkit_tool' has no attribute {name!r}")

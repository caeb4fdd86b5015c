"""Batches for torch's DataLoader: `ItemBatch` (what `ARKitFaceDataset.__getitems__`
returns: per-sample views of one set of batch arrays), `collate` (those arrays handed to
torch without stacking them again), and the same taught to torch's `default_collate`."""

from __future__ import annotations

import sys
from typing import Any, Callable, Dict, Optional, Sequence, Tuple, Type, Union, overload

import numpy as np

from . import _shared_batches
from .correspondences import CorrespondenceMatrix
from .types import Batch

# torch's `default_collate_fn_map`: a type to the function that collates its values.
_CollateFnMap = Dict[Union[Type[Any], Tuple[Type[Any], ...]], Callable[..., Any]]


class SampleView(dict[str, Any]):
    """One sample of an `ItemBatch`: a plain dict (`ds[i]`'s keys and values) whose
    arrays are views of the batch's arrays. Its type is what lets torch's default collate
    recognise a whole batch that needs no stacking (`collate`)."""

    __slots__ = ()


class ItemBatch(list[SampleView]):
    """The samples of one batch (`ARKitFaceDataset.__getitems__`): a list of per-sample
    dicts (`SampleView`), as torch's default collate expects, whose arrays are views of
    one set of batch arrays, `arrays` (the batch axis first; strings as lists)."""

    def __init__(
        self, arrays: Dict[str, Any], tensors: bool = False, segment: Optional[_shared_batches.Segment] = None
    ) -> None:
        if tensors:
            arrays = {k: _as_torch(v) for k, v in arrays.items()}
        self.arrays = arrays
        # The shared memory the arrays live in, in a DataLoader worker (else None).
        self.segment = segment
        b = len(arrays["img"])
        super().__init__(SampleView((k, v[i]) for k, v in arrays.items()) for i in range(b))
        self._views: Tuple[SampleView, ...] = tuple(self)

    def intact(self) -> bool:
        """Whether the list still holds exactly the samples it was made with, each with
        its original values (the same objects): then its batch arrays are what stacking
        its samples would give. A sample replaced, added, removed or reordered, or a
        value rebound (`s["img"] = s["img"] * 2`), makes it False. (Writing into a
        sample's array in place writes into the batch array, which stays equal.)"""
        if len(self) != len(self._views) or any(a is not b for a, b in zip(self, self._views)):
            return False
        arrays = self.arrays
        for i, sample in enumerate(self):
            if sample.keys() != arrays.keys():
                return False
            for k, v in sample.items():
                whole = arrays[k]
                if isinstance(whole, list):
                    if v is not whole[i]:
                        return False
                elif not _is_row(v, whole, i):
                    return False
        return True


def _as_torch(v: Any) -> Any:
    """A batch value as torch gives it: arrays as tensors sharing their memory, a
    `CorrespondenceMatrix` over tensors, lists as they are."""
    import torch

    if isinstance(v, np.ndarray):
        return torch.from_numpy(v)
    if isinstance(v, CorrespondenceMatrix) and isinstance(v.ids, np.ndarray):
        return CorrespondenceMatrix(torch.from_numpy(v.ids), torch.from_numpy(v.weights), v.vertex_count)
    return v


def _is_row(v: Any, whole: Any, i: int) -> bool:
    """Whether `v` is row `i` of the array (numpy) or tensor `whole`, unchanged: the
    same memory, shape and dtype (an index into a batch array makes a new view object
    each time, so identity cannot be asked)."""
    if isinstance(whole, CorrespondenceMatrix):
        return (
            type(v) is CorrespondenceMatrix
            and v.vertex_count == whole.vertex_count
            and _is_row(v.ids, whole.ids, i)
            and _is_row(v.weights, whole.weights, i)
        )
    if type(v) is not type(whole) or v.shape != whole.shape[1:] or v.dtype != whole.dtype:
        return False
    if isinstance(whole, np.ndarray):
        if v.base is not whole and v.base is not whole.base:
            return False
        at = v.__array_interface__["data"][0]
        start = whole.__array_interface__["data"][0]
        row: bool = at == start + i * whole.strides[0] and v.strides == whole.strides[1:]
        return row
    row = (
        v.untyped_storage().data_ptr() == whole.untyped_storage().data_ptr()
        and v.storage_offset() == whole.storage_offset() + i * whole.stride(0)
        and v.stride() == whole.stride()[1:]
    )
    return row


@overload
def collate(batch: ItemBatch) -> Batch: ...


@overload
def collate(batch: Any) -> Any: ...


def collate(batch: Any) -> Any:
    """A DataLoader `collate_fn`: for an intact `ItemBatch` its batch arrays as torch
    tensors (no copy; strings as lists), the same keys, shapes, dtypes and values as
    `torch.utils.data.default_collate` of its samples; anything else goes to
    `default_collate`.

    Importing torch with arkit_tool also teaches torch's own `default_collate` the same
    (`SampleView` in `torch.utils.data._utils.collate.default_collate_fn_map`, torch's
    documented way to extend it), so a plain `DataLoader(ds, batch_size=B)`, such as the
    official train.py's, gets its batches without the stacking copy too."""
    import torch

    _teach_default_collate()
    if isinstance(batch, ItemBatch) and batch.intact():
        # torch.as_tensor shares a numpy array's memory and returns a tensor as it is.
        out = {
            k: list(v) if isinstance(v, list) else _as_torch(v) if isinstance(v, CorrespondenceMatrix)
            else torch.as_tensor(v)
            for k, v in batch.arrays.items()
        }
        if batch.segment is not None:
            # In a worker: pickled as the shared memory's name, not copied.
            return _shared_batches.SharedBatch(out, batch.segment)
        return out
    return torch.utils.data.default_collate(_plain(batch))


def _plain(batch: Any) -> Any:
    """`batch` with its `SampleView`s as plain dicts (what default_collate stacks; a
    `CorrespondenceMatrix` is stacked in its sparse form, `_collate_correspondences`)."""
    if isinstance(batch, list) and batch and isinstance(batch[0], SampleView):
        return [dict(s) for s in batch]
    return batch


def _collate_correspondences(
    batch: Sequence[Any], *, collate_fn_map: Optional[_CollateFnMap] = None
) -> CorrespondenceMatrix:
    """torch's `default_collate` for `CorrespondenceMatrix` samples: one
    `CorrespondenceMatrix` of the stacked sparse forms (stacked as torch stacks tensors:
    in a worker, into shared memory)."""
    import torch
    from torch.utils.data._utils.collate import collate as torch_collate

    first = batch[0]
    if any(not isinstance(m, CorrespondenceMatrix) or m.vertex_count != first.vertex_count for m in batch):
        raise TypeError("default_collate: a batch mixing correspondence matrices with other values")
    ids = torch_collate([torch.as_tensor(m.ids) for m in batch], collate_fn_map=collate_fn_map)
    weights = torch_collate([torch.as_tensor(m.weights) for m in batch], collate_fn_map=collate_fn_map)
    return CorrespondenceMatrix(ids, weights, first.vertex_count)


def _collate_sample_views(
    batch: Sequence[Any], *, collate_fn_map: Optional[_CollateFnMap] = None
) -> Any:
    """torch's `default_collate` for a batch whose first sample is a `SampleView`:
    `collate(batch)` when it is an intact `ItemBatch`, else each key stacked as
    `default_collate` stacks a dict's values."""
    if isinstance(batch, ItemBatch) and batch.intact():
        return collate(batch)
    from torch.utils.data._utils.collate import collate as torch_collate

    return torch_collate([dict(s) for s in batch], collate_fn_map=collate_fn_map)


def _teach_default_collate() -> None:
    """Registers `SampleView` with torch's `default_collate` (once; when torch is
    imported)."""
    torch_collate = sys.modules.get("torch.utils.data._utils.collate")
    if torch_collate is None:
        try:
            import torch.utils.data._utils.collate as torch_collate
        except ImportError:
            return
    fn_map = getattr(torch_collate, "default_collate_fn_map", None)
    if fn_map is not None and SampleView not in fn_map:
        fn_map[SampleView] = _collate_sample_views
        fn_map[CorrespondenceMatrix] = _collate_correspondences

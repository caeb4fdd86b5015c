"""`CorrespondenceMatrix`: the official dense `corr_mat`, carried in its sparse form.

The official loader's `corr_mat` is `n_pts x 1220` float32 per sample (5 MB at 1,024
points), of which three values a row are not zero: a point's barycentric weights at its
triangle's three vertex columns. A batch hands it over as those three vertex ids and
weights (24 KB a sample) and builds the dense matrix where the model reads it:
`batch["corr_mat"].to(device)`, the call the official `set_input` makes, returns a plain
`torch.Tensor` on `device`, bit for bit the official matrix (built there: a GPU never
receives the zeros). On the CPU the matrix goes into a buffer reused once nothing refers
to it, rewritten at the previous matrix's columns only when torch says nothing wrote it
since (see `_Slot`).

What it supports, beside `.to(...)`: `.shape`, `.dtype`, `.ndim`, `len()`, `.device`,
`.size()`, `.dim()`, `.cpu()`, `.cuda()`, `.float()`, `.numpy()`, `.dense()`,
`.pin_memory()`, `np.asarray(m)`, indexing (an integer on the batch axis keeps the
sparse form; anything else indexes the dense matrix), every `torch.*` function
(`torch.equal(m, x)`, `torch.bmm(m, v)`: the dense matrix is built first, through
`__torch_function__`), arithmetic operators, and any other tensor method or attribute
by name (on the dense matrix). It is not a `torch.Tensor`: `isinstance(m,
torch.Tensor)` is False, and an API that checks that type (a `TensorDataset`, a
`torch.jit` trace) needs `m.dense()` (or `m.to(device)`) first. In-place methods
(`m.mul_(2)`) act on a dense copy and are lost: call them on `m.to(device)`.
"""

from __future__ import annotations

import mmap
import os
import sys
import threading
from typing import TYPE_CHECKING, Any, Dict, Iterator, List, Optional, Tuple

import numpy as np

from . import _native

if TYPE_CHECKING:
    import torch

__all__ = ["CorrespondenceMatrix", "dense_matrix", "scatter_matrix"]


def dense_matrix(ids: Any, weights: Any, vertex_count: int) -> Any:
    """The dense correspondence matrix of `ids` (..., n, 3) and `weights` (..., n, 3)
    (torch tensors on one device, or numpy arrays): (..., n, vertex_count) float32,
    zeros but for each row's three weights at its three vertex columns; where a
    triangle repeats a vertex the later weight stays, as the official loader assigns
    them. On the CPU Rust writes it (`_native.write_correspondence_matrix_into`) into a
    buffer reused once nothing refers to it (see `_Slot`); on another device torch
    builds it there (`scatter_`, one column at a time, so no assignment has two values
    for one place: the same bits on any device)."""
    return _dense(ids, weights, vertex_count, tracked=True)


def _dense(ids: Any, weights: Any, vertex_count: int, tracked: bool) -> Any:
    """`dense_matrix`; `tracked=False`: the caller hands the matrix on in a form whose
    writes torch does not count (a numpy array), so the buffer's contents are not known
    afterwards and its next use writes it whole."""
    if not (isinstance(ids, np.ndarray) or ids.device.type == "cpu"):
        return scatter_matrix(ids, weights, vertex_count)
    numpy_in = isinstance(ids, np.ndarray)
    ids_np = np.asarray(ids if numpy_in else ids.numpy(), dtype=np.int64)
    weights_np = np.asarray(weights if isinstance(weights, np.ndarray) else weights.numpy(), dtype=np.float32)
    slot = _cpu_slot(tuple(ids_np.shape[:-1]) + (int(vertex_count),))
    try:
        _native.write_correspondence_matrix_into(slot.buf, ids_np, weights_np, slot.clean_ids())
        if numpy_in or slot.tensor is None or not tracked:
            # Writes through a numpy array (or a tensor made anew on it) are counted
            # nowhere: the next use writes the buffer whole.
            slot.written = None
        else:
            slot.written = (ids_np.copy(), slot.tensor._version)
        if numpy_in:
            return slot.buf
        if slot.tensor is None:
            import torch

            return torch.from_numpy(slot.buf)
        return slot.tensor
    except BaseException:
        slot.written = None
        raise
    finally:
        slot.busy = False


def scatter_matrix(ids: "torch.Tensor", weights: "torch.Tensor", vertex_count: int) -> "torch.Tensor":
    """`dense_matrix` built by torch on the tensors' device: zeros, then each of the
    three columns assigned in turn (what the official loader's three assignments do)."""
    import torch

    out = torch.zeros(tuple(ids.shape[:-1]) + (vertex_count,), dtype=torch.float32, device=ids.device)
    ids = ids.long()
    weights = weights.to(dtype=torch.float32)
    for k in range(3):
        out.scatter_(-1, ids[..., k : k + 1], weights[..., k : k + 1])
    return out


class _Slot:
    """A dense CPU matrix buffer (`buf`, numpy) and the one tensor handed out on it
    (`tensor`, made once, where torch is imported and tells how many tensors use a
    storage), with what was last written into it: `written` = (the ids, the tensor's
    version counter just after), or None when its contents are not known (new, or
    handed out in a form whose writes torch does not count)."""

    __slots__ = ("buf", "tensor", "written", "busy", "refs")

    def __init__(self, shape: Tuple[int, ...]) -> None:
        self.buf = _private_buffer(shape)
        self.written: Optional[Tuple[np.ndarray, int]] = None
        self.busy = True
        torch = sys.modules.get("torch")
        self.tensor: Any = None
        if torch is not None and _storage_users is not None:
            self.tensor = torch.from_numpy(self.buf)
        # The references when nobody else holds the buffer, as counted here: the
        # slot's own (and the tensor's storage's) to `buf`; the tensor and the storage
        # object asked for, among the storage's users.
        self.refs = (sys.getrefcount(self.buf) - 1, self._users())

    def _users(self) -> int:
        if self.tensor is None:
            return 0
        return int(_storage_users(self.tensor.untyped_storage()._cdata))

    def free(self) -> bool:
        """Nobody else refers to the buffer: not through numpy (a view holds `buf`), not
        through torch (the tensor itself, or a view of it or its `.numpy()`, which share
        its storage)."""
        if self.busy or sys.getrefcount(self.buf) - 1 > self.refs[0]:
            return False
        return self.tensor is None or (sys.getrefcount(self.tensor) <= 2 and self._users() <= self.refs[1])

    def clean_ids(self) -> Optional[np.ndarray]:
        """The ids the buffer holds the matrix of, when nothing has written the tensor
        since (torch counts every in-place write to it and its views), so that only
        their columns need clearing; None: write it whole."""
        if self.written is None:  # only ever set where the slot has its tensor
            return None
        ids, version = self.written
        return ids if self.tensor._version == version else None


# Linux's madvise(MADV_WIPEONFORK) (4.14+; Python's mmap does not name it).
_MADV_WIPEONFORK = 18


def _private_buffer(shape: Tuple[int, ...]) -> np.ndarray:
    """A float32 array for the training process alone. On Linux its memory is not shared
    with processes forked later (DataLoader workers, forked at every epoch): they see
    zeros there, and the training process's next write into it is not a copy-on-write
    fault a page (170 ms for a batch of 64 here, every epoch). Elsewhere, or where the
    kernel refuses, an ordinary array."""
    nbytes = int(np.prod(shape, dtype=np.int64)) * 4
    if sys.platform.startswith("linux") and nbytes > 0:
        try:
            region = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE)
            region.madvise(_MADV_WIPEONFORK)
            # One array on the region: every view of it names it as its base.
            return np.ndarray(shape, dtype=np.float32, buffer=region)
        except (OSError, ValueError, AttributeError):
            pass
    return np.empty(shape, dtype=np.float32)


def _forget_buffers() -> None:
    """In a forked child: the buffers' memory reads as zeros there, and is not its."""
    global _buffers_lock
    _buffers.clear()
    _buffers_lock = threading.Lock()


def _find_storage_users() -> Any:
    torch = sys.modules.get("torch")
    return getattr(getattr(torch, "_C", None), "_storage_Use_Count", None)


# Dense CPU matrices handed out, by shape: one is written over again only once nothing
# refers to it. Two a shape: a training step holds the previous batch's matrix while the
# next is built. Where torch (2.x) tells how many tensors use a storage, each buffer's
# tensor is handed out again and again, and a buffer whose tensor nobody wrote is
# rewritten at its non-zero columns only (24 bytes a row, not 4.9 KB); where it does not,
# a new tensor is made on the buffer each time and the buffer is written whole. A write
# torch does not count (through `.numpy()` or `.data` of the tensor, after which it is
# dropped) would leave its values in the next matrix: torch's own autograd has the same
# blind spot, and the package never writes that way.
_buffers: Dict[Tuple[int, ...], List[_Slot]] = {}
_buffers_lock = threading.Lock()
_BUFFERS_PER_SHAPE = 2
_storage_users: Any = None
# Counted for tests: buffers made.
buffer_stats = {"made": 0}
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_buffers)


def _cpu_slot(shape: Tuple[int, ...]) -> _Slot:
    """A free buffer of `shape` (marked busy until `_dense` has written it)."""
    global _storage_users
    with _buffers_lock:
        if _storage_users is None:
            _storage_users = _find_storage_users()
        kept = _buffers.setdefault(shape, [])
        for i in range(len(kept)):
            slot = kept[i]
            # A buffer made before torch was imported is replaced by one with a tensor.
            if slot.free() and (slot.tensor is not None or _storage_users is None):
                kept.insert(0, kept.pop(i))
                slot.busy = True
                return slot
        slot = _Slot(shape)
        buffer_stats["made"] += 1
        kept.insert(0, slot)
        del kept[_BUFFERS_PER_SHAPE:]
        return slot


def _is_tensor(x: Any) -> bool:
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _device_of(args: Tuple[Any, ...], kwargs: Dict[str, Any]) -> Any:
    """The device a `Tensor.to(...)` call names, or None (a dtype only)."""
    import torch

    device = kwargs.get("device")
    for a in args:
        if isinstance(a, (str, torch.device)) or (isinstance(a, int) and not isinstance(a, bool)):
            device = a
        elif isinstance(a, torch.Tensor):
            device = a.device
    return None if device is None else torch.device(device)


class CorrespondenceMatrix:
    """The dense `corr_mat` (`..., n_pts, vertex_count` float32) of a batch or sample,
    held as each point's three vertex ids (`ids`, int64) and barycentric weights
    (`weights`, float32) until it is read. `m.to(device)` builds the dense tensor on
    `device`; see the module's docs for the rest of the API and where it stops."""

    __slots__ = ("ids", "weights", "vertex_count")

    def __init__(self, ids: Any, weights: Any, vertex_count: int) -> None:
        if tuple(ids.shape) != tuple(weights.shape) or len(ids.shape) < 2 or ids.shape[-1] != 3:
            raise ValueError(
                f"CorrespondenceMatrix: ids {tuple(ids.shape)} and weights {tuple(weights.shape)}: "
                "expected two (..., n, 3) arrays of one shape"
            )
        self.ids = ids
        self.weights = weights
        self.vertex_count = int(vertex_count)

    # -- what it is ------------------------------------------------------------------
    @property
    def shape(self) -> Tuple[int, ...]:
        dims = tuple(self.ids.shape[:-1]) + (self.vertex_count,)
        if _is_tensor(self.ids):
            import torch

            return torch.Size(dims)
        return dims

    @property
    def dtype(self) -> Any:
        if _is_tensor(self.ids):
            import torch

            return torch.float32
        return np.dtype(np.float32)

    @property
    def ndim(self) -> int:
        return len(self.ids.shape)

    @property
    def device(self) -> Any:
        return self.ids.device if _is_tensor(self.ids) else None

    def size(self, dim: Optional[int] = None) -> Any:
        shape = self.shape
        return shape if dim is None else shape[dim]

    def dim(self) -> int:
        return self.ndim

    def __len__(self) -> int:
        return len(self.ids)

    def __repr__(self) -> str:
        kind = "tensors" if _is_tensor(self.ids) else "numpy"
        return f"CorrespondenceMatrix(shape={tuple(self.shape)}, dtype=float32, sparse {kind})"

    # -- the dense matrix ------------------------------------------------------------
    def dense(self) -> Any:
        """The dense matrix where the sparse form is: a torch tensor on its device, or a
        numpy array when the sparse form is numpy."""
        return _dense(self.ids, self.weights, self.vertex_count, tracked=True)

    def _tensors(self) -> Tuple["torch.Tensor", "torch.Tensor"]:
        import torch

        if _is_tensor(self.ids):
            return self.ids, self.weights
        return torch.as_tensor(self.ids), torch.as_tensor(self.weights)

    def to(self, *args: Any, **kwargs: Any) -> "torch.Tensor":
        """`Tensor.to`'s arguments: the dense matrix built on the device named (this
        one's when none), then converted as asked (a dtype, `copy`, ...). A plain
        `torch.Tensor`."""
        ids, weights = self._tensors()
        device = _device_of(args, kwargs)
        if device is not None and device != ids.device:
            blocking = {"non_blocking": kwargs["non_blocking"]} if "non_blocking" in kwargs else {}
            ids = ids.to(device, **blocking)
            weights = weights.to(device, **blocking)
        out: torch.Tensor = dense_matrix(ids, weights, self.vertex_count)
        return out.to(*args, **kwargs)

    def cuda(self, *args: Any, **kwargs: Any) -> "torch.Tensor":
        import torch

        return self.to(torch.device("cuda", *args) if args else "cuda", **kwargs)

    def cpu(self) -> "torch.Tensor":
        return self.to("cpu")

    def float(self) -> "torch.Tensor":
        return self.to("cpu") if not _is_tensor(self.ids) else self.dense()

    def numpy(self) -> np.ndarray:
        out = _dense(self.ids, self.weights, self.vertex_count, tracked=False)
        return out if isinstance(out, np.ndarray) else out.numpy()

    def pin_memory(self, *args: Any) -> "CorrespondenceMatrix":
        """The sparse form in pinned memory (what a DataLoader's `pin_memory=True` asks);
        `.to("cuda", non_blocking=True)` then copies it without blocking."""
        ids, weights = self._tensors()
        return CorrespondenceMatrix(ids.pin_memory(*args), weights.pin_memory(*args), self.vertex_count)

    def __array__(self, dtype: Any = None, copy: Optional[bool] = None) -> np.ndarray:
        out = self.numpy()
        return out if dtype is None else out.astype(dtype)

    def row(self, i: int) -> "CorrespondenceMatrix":
        """Sample `i` of a batch (the sparse form's rows: no dense matrix built)."""
        return CorrespondenceMatrix(self.ids[i], self.weights[i], self.vertex_count)

    def __getitem__(self, index: Any) -> Any:
        if isinstance(index, (int, np.integer)) and not isinstance(index, bool) and self.ndim > 2:
            return self.row(int(index))
        return self.dense()[index]

    def __iter__(self) -> Iterator[Any]:
        if self.ndim > 2:
            return (self.row(i) for i in range(len(self)))
        return iter(self.dense())

    # Everything else a tensor has, on the dense matrix.
    def __getattr__(self, name: str) -> Any:
        # Only what a tensor has (or numpy's array, for a numpy-held matrix): a probe for
        # anything else (`hasattr(m, "_fields")`) must not build the dense matrix.
        torch = sys.modules.get("torch")
        kind = torch.Tensor if torch is not None and _is_tensor(self.ids) else np.ndarray
        if name.startswith("__") or not hasattr(kind, name):
            raise AttributeError(f"'CorrespondenceMatrix' object has no attribute {name!r}")
        # `.data` and the like write past torch's version counter: not tracked.
        return getattr(_dense(self.ids, self.weights, self.vertex_count, tracked=False), name)

    @classmethod
    def __torch_function__(cls, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        kwargs = kwargs or {}
        return func(*_densify(args), **_densify(kwargs))

    def __reduce__(self) -> Tuple[Any, ...]:
        return (CorrespondenceMatrix, (self.ids, self.weights, self.vertex_count))


def _densify(value: Any) -> Any:
    if isinstance(value, CorrespondenceMatrix):
        return value.dense()
    if isinstance(value, (list, tuple)):
        return type(value)(_densify(v) for v in value)
    if isinstance(value, dict):
        return {k: _densify(v) for k, v in value.items()}
    return value


def _operator(name: str) -> Any:
    def op(self: "CorrespondenceMatrix", *args: Any) -> Any:
        return getattr(self.dense(), name)(*_densify(args))

    op.__name__ = name
    return op


for _name in (
    "__add__", "__radd__", "__sub__", "__rsub__", "__mul__", "__rmul__", "__truediv__",
    "__rtruediv__", "__matmul__", "__rmatmul__", "__neg__", "__pos__", "__abs__", "__pow__",
    "__eq__", "__ne__", "__lt__", "__le__", "__gt__", "__ge__", "__bool__",
):
    setattr(CorrespondenceMatrix, _name, _operator(_name))
CorrespondenceMatrix.__hash__ = None  # type: ignore[assignment]
del _name

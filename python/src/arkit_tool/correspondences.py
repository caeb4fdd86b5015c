"""`CorrespondenceMatrix`: the official dense `corr_mat`, carried in its sparse form.

The official loader's `corr_mat` is `n_pts x 1220` float32 per sample (5 MB at 1,024
points), of which three values a row are not zero: a point's barycentric weights at its
triangle's three vertex columns. A batch hands it over as those three vertex ids and
weights (24 KB a sample) and builds the dense matrix where the model reads it:
`batch["corr_mat"].to(device)`, the call the official `set_input` makes, returns a plain
`torch.Tensor` on `device`, bit for bit the official matrix (built there: a GPU never
receives the zeros).

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
    them. On the CPU Rust writes it (`_native.write_correspondence_matrix_into`, into a
    buffer reused once nothing refers to it: a fresh 5 MB a sample costs more in page
    faults than writing it); on another device torch builds it there (`scatter_`, one
    column at a time, so no assignment has two values for one place: the same bits on
    any device)."""
    if isinstance(ids, np.ndarray) or ids.device.type == "cpu":
        numpy_in = isinstance(ids, np.ndarray)
        ids_np = ids if numpy_in else ids.numpy()
        weights_np = weights if isinstance(weights, np.ndarray) else weights.numpy()
        out = _cpu_buffer(tuple(ids_np.shape[:-1]) + (int(vertex_count),))
        _native.write_correspondence_matrix_into(
            out, np.asarray(ids_np, dtype=np.int64), np.asarray(weights_np, dtype=np.float32)
        )
        if numpy_in:
            return out
        import torch

        return torch.from_numpy(out)
    return scatter_matrix(ids, weights, vertex_count)


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


# Dense CPU matrices handed out, by shape: one is written over again only once nothing
# refers to it (each numpy view and tensor made from it holds a reference to it). Two a
# shape: a training step holds the previous batch's matrix while the next is built.
_buffers: Dict[Tuple[int, ...], List[np.ndarray]] = {}
_buffers_lock = threading.Lock()
_BUFFERS_PER_SHAPE = 2
# Counted for tests: buffers made.
buffer_stats = {"made": 0}


def _cpu_buffer(shape: Tuple[int, ...]) -> np.ndarray:
    with _buffers_lock:
        kept = _buffers.setdefault(shape, [])
        for i in range(len(kept)):
            # The list's reference and getrefcount's own: nobody else holds it.
            if sys.getrefcount(kept[i]) <= 2:
                buf = kept.pop(i)
                kept.insert(0, buf)
                return buf
        buf = np.empty(shape, dtype=np.float32)
        buffer_stats["made"] += 1
        kept.insert(0, buf)
        del kept[_BUFFERS_PER_SHAPE:]
        return buf


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
        return dense_matrix(self.ids, self.weights, self.vertex_count)

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
        out = dense_matrix(ids, weights, self.vertex_count)
        return out.to(*args, **kwargs)

    def cuda(self, *args: Any, **kwargs: Any) -> "torch.Tensor":
        import torch

        return self.to(torch.device("cuda", *args) if args else "cuda", **kwargs)

    def cpu(self) -> "torch.Tensor":
        return self.to("cpu")

    def float(self) -> "torch.Tensor":
        return self.to("cpu") if not _is_tensor(self.ids) else self.dense()

    def numpy(self) -> np.ndarray:
        out = self.dense()
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
        return getattr(self.dense(), name)

    @classmethod
    def __torch_function__(cls, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        kwargs = kwargs or {}
        return func(*_densify(args), **_densify(kwargs))

    def __reduce__(self) -> Tuple:
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

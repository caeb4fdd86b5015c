"""Batches computed in DataLoader workers, handed to the training process without a copy.

torch sends every tensor a worker returns through shared memory: a tensor not already
there is copied into fresh shared pages, its file descriptor crosses a socket, and the
training process maps it anew and faults its pages in, batch after batch. Here a worker
computes each batch straight into a *segment* (a `memfd` shared-memory file it keeps
and reuses), and what crosses the queue is the segment's name and layout (a few hundred
bytes: `SharedBatch.__reduce__`). The training process maps each segment once
(`/proc/<worker>/fd/<fd>`, checked against a random token in the segment's header) and
keeps the mapping; the tensors it receives are views of it. When the last of them is
gone (`_Lease.__del__`), the segment's header says so and the worker writes its next
batch there.

A segment's state byte: `FREE` (the worker may write it), `SENT` (set when the batch is
pickled for the queue; the training process may hold it). The worker takes a segment
when no object of its own refers to it any more and the byte is `FREE`.

Segments outlive their workers. A DataLoader that is not persistent (train.py's) starts
new workers every epoch, and fresh shared pages cost more than computing the samples
(on the machines measured, about 2 ms a MB in page faults). The training process keeps
every segment it has mapped, and a worker forked from it inherits those mappings: it
*adopts* a free one of the layout it needs whose owner (the pid in its header) has
ended, under a lock all forked workers share, and writes its header's owner. The batch
it sends names the segment as the training process first mapped it, so nothing is
opened again. Spawned workers inherit nothing and make their own.

Linux only (memfd and /proc); elsewhere, or with `ARKIT_TOOL_SHARED_BATCHES=0`,
batches go the usual way (torch's shared memory, one copy).
"""

from __future__ import annotations

import mmap
import multiprocessing
import os
import secrets
import struct
import sys
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .correspondences import CorrespondenceMatrix

MAGIC = b"ARKITBAT"
HEADER = 64  # bytes before the first array
ALIGN = 64
STATE_AT = 16
OWNER_AT = 20  # the pid of the process that writes the segment (u32)
FREE, SENT = 0, 1
ENV = "ARKIT_TOOL_SHARED_BATCHES"

# The arrays a batch is computed into (what `Loader.batch` takes as `reuse`).
SEGMENT_KEYS = ("img", "uvmap", "mask", "choose", "model", "nocs", "corr_ids", "corr_weights", "corr_mat")

# Counters for tests and benches: segments made and bytes mapped, in this process.
stats = {"segments_created": 0, "segment_bytes_created": 0, "mappings_opened": 0, "segments_adopted": 0}

# Serialises adoptions among the processes forked from this one (made at import, so that
# every forked worker shares it; made for fork, so it is an unnamed semaphore that needs
# no resource tracker whatever the default start method).
try:
    _adopt_lock: Any = multiprocessing.get_context("fork").Lock()
except (OSError, ImportError, ValueError):  # no fork or no POSIX semaphores: workers never adopt
    _adopt_lock = None


def enabled() -> bool:
    """Whether batches computed in a worker go through segments."""
    return (
        sys.platform.startswith("linux")
        and hasattr(os, "memfd_create")
        and os.environ.get(ENV, "1") not in ("0", "false", "no")
    )


def in_worker() -> bool:
    """Whether this process is a torch DataLoader worker."""
    torch = sys.modules.get("torch")
    if torch is None:
        return False
    info = torch.utils.data.get_worker_info()
    return info is not None


Layout = Tuple[Tuple[str, str, Tuple[int, ...], int], ...]  # (key, dtype, shape, offset)


def _layout(shapes: Dict[str, Tuple[str, Tuple[int, ...]]]) -> Tuple[Layout, int]:
    at = HEADER
    entries = []
    for key in SEGMENT_KEYS:
        if key not in shapes:
            continue
        dtype, shape = shapes[key]
        nbytes = int(np.dtype(dtype).itemsize * int(np.prod(shape, dtype=np.int64)))
        entries.append((key, dtype, tuple(int(s) for s in shape), at))
        at += (nbytes + ALIGN - 1) // ALIGN * ALIGN
    return tuple(entries), at


class Segment:
    """A worker's shared-memory file holding one batch's arrays: made by the worker, or
    adopted (`Segment.adopt`) from those the training process had mapped when the
    worker was forked."""

    def __init__(self, layout: Layout, size: int, mapping: Optional["_Mapping"] = None):
        self.layout = layout
        self.size = size
        if mapping is None:
            fd = os.memfd_create("arkit-tool-batch", os.MFD_CLOEXEC)
            try:
                os.ftruncate(fd, size)
                self.map = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
            except BaseException:
                os.close(fd)
                raise
            token = secrets.randbits(64)
            self.map[: len(MAGIC)] = MAGIC
            struct.pack_into("<Q", self.map, 8, token)
            struct.pack_into("<I", self.map, OWNER_AT, os.getpid())
            self.map[STATE_AT] = FREE
            # How the training process finds it: (pid, fd, token), the fd kept open.
            self.key = (os.getpid(), fd, token)
            stats["segments_created"] += 1
            stats["segment_bytes_created"] += size
        else:
            self.map = mapping.map
            self.key = mapping.key
            stats["segments_adopted"] += 1
        self.root = np.frombuffer(self.map, dtype=np.uint8)
        self.arrays = {
            key: self.root[at : at + np.dtype(dtype).itemsize * int(np.prod(shape, dtype=np.int64))]
            .view(dtype)
            .reshape(shape)
            for key, dtype, shape, at in layout
        }

    @staticmethod
    def adopt(layout: Layout, size: int) -> Optional["Segment"]:
        """A free segment of `layout` that the training process had mapped when this
        worker was forked and whose owner has ended, now this process's; or None."""
        if _adopt_lock is None:
            return None
        me = os.getpid()
        with _adopt_lock:
            for m in list(_mappings.values()):
                if m.layout != layout or m.size != size or m.map[STATE_AT] != FREE:
                    continue
                owner = struct.unpack_from("<I", m.map, OWNER_AT)[0]
                if owner == me or _alive(owner):
                    continue
                struct.pack_into("<I", m.map, OWNER_AT, me)
                return Segment(layout, size, m)
        return None

    def free(self) -> bool:
        """No object of this process refers to the segment's arrays but its own, and the
        training process holds nothing of it."""
        # The root is referred to by this object and by each of its own arrays; any other
        # view (numpy's or a tensor's, through the arrays) adds a reference to an array or
        # to the root.
        if sys.getrefcount(self.root) > 2 + len(self.arrays):
            return False
        for a in self.arrays.values():
            # The dict's reference, the loop's and getrefcount's own.
            if sys.getrefcount(a) > 3:
                return False
        return self.map[STATE_AT] == FREE

    def sent(self) -> None:
        self.map[STATE_AT] = SENT

    def descriptor(self) -> Tuple[int, int, int, int, Layout]:
        pid, fd, token = self.key
        return (pid, fd, token, self.size, self.layout)


class SegmentPool:
    """A worker's segments, reused once free."""

    def __init__(self) -> None:
        self.pid = os.getpid()
        self.segments: List[Segment] = []
        # Per-sample shapes learnt from a first batch: (corr, eval) -> {key: (dtype, shape)}.
        self.shapes: Dict[Any, Dict[str, Tuple[str, Tuple[int, ...]]]] = {}

    def acquire(self, shapes: Dict[str, Tuple[str, Tuple[int, ...]]]) -> Segment:
        layout, size = _layout(shapes)
        for seg in self.segments:
            if seg.layout == layout and seg.free():
                return seg
        seg = Segment.adopt(layout, size) or Segment(layout, size)
        self.segments.append(seg)
        return seg


def batch_shapes(per_sample: Dict[str, Tuple[str, Tuple[int, ...]]], b: int) -> Dict[str, Tuple[str, Tuple[int, ...]]]:
    return {k: (dtype, (b,) + shape) for k, (dtype, shape) in per_sample.items()}


def per_sample_shapes(arrays: Dict[str, Any]) -> Dict[str, Tuple[str, Tuple[int, ...]]]:
    return {
        k: (arrays[k].dtype.str, tuple(arrays[k].shape[1:]))
        for k in SEGMENT_KEYS
        if isinstance(arrays.get(k), np.ndarray)
    }


class SharedBatch(dict[str, Any]):
    """A collated batch (a dict) whose arrays live in a worker's segment: pickled as the
    segment's name and layout, rebuilt in the training process as a plain dict of tensors
    viewing the segment (`receive`)."""

    __slots__ = ("segment",)

    def __init__(self, values: Dict[str, Any], segment: Segment) -> None:
        super().__init__(values)
        self.segment = segment

    def __reduce__(self) -> Tuple[Any, ...]:
        import torch

        seg = self.segment
        where: Dict[str, Tuple[str, Tuple[int, ...], int]] = {}
        for key, dtype, shape, at in seg.layout:
            where[key] = (dtype, shape, at)
        base = seg.root.ctypes.data
        items: List[Tuple[str, str, Any]] = []
        for k, v in self.items():
            if isinstance(v, torch.Tensor) and _in_segment(v, where.get(k), base):
                items.append((k, "segment", k))
            elif (
                isinstance(v, CorrespondenceMatrix)
                and isinstance(v.ids, torch.Tensor)
                and _in_segment(v.ids, where.get("corr_ids"), base)
                and _in_segment(v.weights, where.get("corr_weights"), base)
            ):
                items.append((k, "corr", v.vertex_count))
            elif isinstance(v, torch.Tensor) and v.device.type == "cpu" and v.numel() * v.element_size() <= 4096:
                # Small arrays (the evaluation's tform_inv and R_t) travel in the pickle.
                items.append((k, "inline", v.numpy()))
            else:
                items.append((k, "value", v))
        seg.sent()
        return (receive, (seg.descriptor(), items))


def _in_segment(t: Any, entry: Optional[Tuple[str, Tuple[int, ...], int]], base: int) -> bool:
    """Whether tensor `t` is the segment's array `entry` as it was laid out."""
    if entry is None:
        return False
    dtype, shape, at = entry
    inside: bool = (
        t.device.type == "cpu"
        and tuple(t.shape) == shape
        and t.is_contiguous()
        and t.data_ptr() == base + at
        and t.numpy().dtype.str == dtype
    )
    return inside


# -- the training process's side ----------------------------------------------------------

# Open mappings, by (pid, fd, token) of the worker that made the segment: a segment is
# mapped once and kept for the rest of the run (workers forked later adopt them).
_mappings: Dict[Tuple[int, int, int], _Mapping] = {}


class _Mapping:
    def __init__(self, pid: int, fd: int, token: int, size: int, layout: Layout = ()):
        self.key = (pid, fd, token)
        self.size = size
        self.layout = layout
        path = f"/proc/{pid}/fd/{fd}"
        try:
            f = os.open(path, os.O_RDWR | os.O_CLOEXEC)
        except OSError as e:
            raise RuntimeError(
                f"arkit_tool: a batch from DataLoader worker {pid}: cannot open its shared memory "
                f"({path}: {e.strerror}); set {ENV}=0 to send batches through torch's shared memory"
            ) from None
        try:
            actual = os.fstat(f).st_size
            if actual < size or size < HEADER:
                raise RuntimeError(f"arkit_tool: {path}: {actual} bytes, the batch needs {size}")
            self.map = mmap.mmap(f, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        finally:
            os.close(f)
        if bytes(self.map[: len(MAGIC)]) != MAGIC or struct.unpack_from("<Q", self.map, 8)[0] != token:
            raise RuntimeError(f"arkit_tool: {path}: not the shared memory of the batch sent (token differs)")
        self.root = np.frombuffer(self.map, dtype=np.uint8)
        self.base = self.root.ctypes.data
        stats["mappings_opened"] += 1


class _Lease:
    """Held by every array of one received batch; frees the segment when the last goes."""

    __slots__ = ("mapping", "__weakref__")

    def __init__(self, mapping: _Mapping) -> None:
        self.mapping = mapping

    def __del__(self) -> None:
        try:
            self.mapping.map[STATE_AT] = FREE
        except (ValueError, TypeError):  # the mapping closed at interpreter exit
            pass


class _View:
    """An array of a received batch (numpy's `__array_interface__`), keeping its lease."""

    __slots__ = ("__array_interface__", "lease")

    def __init__(self, lease: _Lease, at: int, dtype: str, shape: Tuple[int, ...]) -> None:
        self.lease = lease
        self.__array_interface__ = {
            "data": (lease.mapping.base + at, False),
            "shape": shape,
            "typestr": dtype,
            "version": 3,
        }


def _mapping(pid: int, fd: int, token: int, size: int, layout: Layout) -> _Mapping:
    key = (pid, fd, token)
    m = _mappings.get(key)
    if m is not None:
        if m.size != size or m.layout != layout:
            raise RuntimeError(f"arkit_tool: a batch from DataLoader worker {pid}: its shared memory "
                               "is described otherwise than when it was first mapped")
        return m
    m = _Mapping(pid, fd, token, size, layout)
    _mappings[key] = m
    return m


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def receive(
    descriptor: Tuple[int, int, int, int, Layout], items: Sequence[Tuple[str, str, Any]]
) -> Dict[str, Any]:
    """The batch a worker sent (`SharedBatch.__reduce__`): a plain dict of tensors."""
    import torch

    pid, fd, token, size, layout = descriptor
    mapping = _mapping(pid, fd, token, size, layout)
    lease = _Lease(mapping)
    tensors: Dict[str, torch.Tensor] = {}
    for key, dtype, shape, at in layout:
        nbytes = np.dtype(dtype).itemsize * int(np.prod(shape, dtype=np.int64))
        if at < HEADER or at + nbytes > size:
            raise RuntimeError(f"arkit_tool: a batch's array '{key}' lies outside its shared memory")
        tensors[key] = torch.from_numpy(np.asarray(_View(lease, at, dtype, shape)))
    out: Dict[str, Any] = {}
    for k, kind, value in items:
        if kind == "segment":
            out[k] = tensors[value]
        elif kind == "corr":
            out[k] = CorrespondenceMatrix(tensors["corr_ids"], tensors["corr_weights"], value)
        elif kind == "inline":
            out[k] = torch.from_numpy(value)
        else:
            out[k] = value
    # A batch nothing refers to any more frees its segment at once.
    del lease, tensors
    return out

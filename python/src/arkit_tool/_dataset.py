"""`ARKitFaceDataset`: what the official `ARKitDataset.get_item` returns, computed on
the fly by the Rust loader (`_native.Loader`), one sample (`item`) or a whole batch
into one set of arrays (`__getitems__`); its epoch in shared memory, its samplers and
loaders (`sampling`)."""

from __future__ import annotations

import collections
import multiprocessing
import multiprocessing.context
import os
import queue
import sys
import threading
import weakref
from typing import (
    TYPE_CHECKING,
    Any,
    Callable,
    Dict,
    Generic,
    List,
    Literal,
    Mapping,
    Optional,
    Sequence,
    Tuple,
    Union,
    cast,
    overload,
)

import numpy as np

from . import _native, _shared_batches
from ._storage import is_url
from ._collate import ItemBatch, _teach_default_collate, collate
from ._native import DataError
from .correspondences import CorrespondenceMatrix
from .sampling import EpochSampler, _check_u64, _position
from .types import Batch, Compat, Corr, Item, Mode, PathLike, Remainder, SplitKey, TensorItem

if TYPE_CHECKING:
    from torch.utils.data import DataLoader, Dataset
    from typing_extensions import TypeVar

    from .sampling import EpochLoader

    _ItemT = TypeVar("_ItemT", bound=Union[Item, TensorItem], default=Item)
    _BatchT = TypeVar("_BatchT")

    class _DatasetBase(Dataset[_ItemT], Generic[_ItemT]):
        """To type checkers, a torch `Dataset` (what DataLoader takes); at run time
        `Generic` (torch is imported only when it is used)."""

else:
    from typing import TypeVar

    _ItemT = TypeVar("_ItemT")
    _DatasetBase = Generic


class _ChangedLoader:
    """Stands for a native loader whose folder was rewritten under the job: every use
    raises the `DataError` it was made with."""

    def __init__(self, message: str) -> None:
        self._message = message

    def __getattr__(self, name: str) -> Any:
        raise DataError(self._message)

    def __len__(self) -> int:
        raise DataError(self._message)


class ARKitFaceDataset(_DatasetBase[_ItemT]):
    """What the official `ARKitDataset.get_item` returns, computed on the fly.

    Keys: `img` (3 x S x S float32, normalised as the official transform), `choose`
    (n_pts int64 crop pixel indices), `model` (1220 x 3 float32), `uvmap` (3 x S x S in
    [-1, 1]), `nocs` (n_pts x 3), `mask` (S x S int64), `corr_mat` (n_pts x 1220 float32;
    with `corr="sparse"` instead `corr_ids` (n_pts x 3 int64) and `corr_weights`
    (n_pts x 3 float32); `"both"` gives all three), and in `mode="eval"` also
    `tform_inv` (2 x 3), `R_t` (4 x 4), `img_path`, `subjectid`, `imgid`, `facial_action`.

    `compat="official"` follows the official loader's rules (its integer box, cv2's
    affine warp, its rasterizer's screen-space weights, its UV map and point choice);
    `"exact"` follows ours. In `mode="train"` the official augmentation (box jitter,
    colour jitter) is drawn from `(seed, epoch, index)`; the same batches come out
    whatever the number of DataLoader workers.

    Epochs: `ds[i]` is `ds.item(i, ds.current_epoch())`, and `ds[epoch, i]` (what
    `EpochSampler` yields, the epoch travelling with the index) is `ds.item(i, epoch)`.
    With `ds.loader(...)` the epoch advances by itself at each pass (or
    `loader.set_epoch(e)`). With a DataLoader of your own, call `ds.set_epoch(e)` before
    each epoch's pass: the epoch is held in shared memory, so worker processes see it,
    persistent or not, fork or spawn. A subclass may override `current_epoch()` to
    derive the epoch otherwise (from the worker's seed, say); indices that carry an epoch
    are not affected.

    `split` is a split name (`"train"`, `"test"`, ...) or None for every sample;
    `resources` the release's resource folder when the dataset was converted with it and
    that folder moved (by default the folder the conversion recorded).

    `crop_store`: where the crop pixels and meshes come from. `"auto"` (the default):
    the store `arkit-tool crops` writes for this `compat` and `img_size`
    (`DIR/crops/<compat>-<img_size>`) when it is there, else the release's JPEGs and
    `_info.npz` files; a folder: that store (an error when it does not fit the dataset,
    the rules or the size); None: always the release's files. From a store, evaluation
    crops are bit for bit the same; training crops are resampled from the stored window
    around the box (slightly smoother), their geometry the same. See docs/python.md.

    Batches: torch's DataLoader asks for a whole batch at once (`__getitems__`), which
    Rust computes into one set of batch arrays; `ds.loader(batch_size, ...)` is a
    DataLoader whose `collate` hands those arrays to torch without copying them again.

    Types: `ds[i]` is an `arkit_tool.types.Item` (numpy arrays), or a `TensorItem` with
    `tensors=True` (`ARKitFaceDataset[TensorItem]` to type checkers); the batches of
    `ds.loader(...)` are `Batch`es.
    """

    @overload
    def __init__(
        self: ARKitFaceDataset[Item],
        path: PathLike,
        split: Optional[str] = ...,
        mode: Mode = ...,
        compat: Compat = ...,
        img_size: int = ...,
        n_pts: int = ...,
        seed: int = ...,
        resources: Optional[PathLike] = ...,
        corr: Corr = ...,
        tensors: Literal[False] = ...,
        crop_store: Optional[PathLike] = ...,
        cache_dir: Optional[PathLike] = ...,
        cache_bytes: Optional[int] = ...,
        storage_options: Optional[Mapping[str, str]] = ...,
    ) -> None: ...

    @overload
    def __init__(
        self: ARKitFaceDataset[TensorItem],
        path: PathLike,
        split: Optional[str] = ...,
        mode: Mode = ...,
        compat: Compat = ...,
        img_size: int = ...,
        n_pts: int = ...,
        seed: int = ...,
        resources: Optional[PathLike] = ...,
        corr: Corr = ...,
        *,
        tensors: Literal[True],
        crop_store: Optional[PathLike] = ...,
        cache_dir: Optional[PathLike] = ...,
        cache_bytes: Optional[int] = ...,
        storage_options: Optional[Mapping[str, str]] = ...,
    ) -> None: ...

    @overload
    def __init__(
        self: ARKitFaceDataset[Union[Item, TensorItem]],
        path: PathLike,
        split: Optional[str] = ...,
        mode: Mode = ...,
        compat: Compat = ...,
        img_size: int = ...,
        n_pts: int = ...,
        seed: int = ...,
        resources: Optional[PathLike] = ...,
        corr: Corr = ...,
        tensors: bool = ...,
        crop_store: Optional[PathLike] = ...,
        cache_dir: Optional[PathLike] = ...,
        cache_bytes: Optional[int] = ...,
        storage_options: Optional[Mapping[str, str]] = ...,
    ) -> None: ...

    def __init__(
        self,
        path: PathLike,
        split: Optional[str] = "train",
        mode: Mode = "train",
        compat: Compat = "exact",
        img_size: int = 192,
        n_pts: int = 1024,
        seed: int = 0,
        resources: Optional[PathLike] = None,
        corr: Corr = "dense",
        tensors: bool = False,
        crop_store: Optional[PathLike] = "auto",
        cache_dir: Optional[PathLike] = None,
        cache_bytes: Optional[int] = None,
        storage_options: Optional[Mapping[str, str]] = None,
    ) -> None:
        if corr not in ("dense", "sparse", "both"):
            raise DataError(f"corr: {corr!r}: expected 'dense', 'sparse' or 'both'")
        for name, value, low, high in (("img_size", img_size, 1, 1 << 32), ("n_pts", n_pts, 0, 1 << 63)):
            if not isinstance(value, (int, np.integer)) or not low <= value < high:
                raise DataError(f"{name}: {value!r}: expected an integer in [{low}, 2^{(high - 1).bit_length()})")
        try:
            seed = _check_u64("seed", seed)
        except ValueError as e:
            raise DataError(str(e)) from None
        self.path = os.fspath(path)
        self.split = split
        self.mode = mode
        self.compat = compat
        self.img_size = int(img_size)
        self.n_pts = int(n_pts)
        self.seed = int(seed)
        self.resources = None if resources is None else os.fspath(resources)
        self.corr = corr
        self.tensors = bool(tensors)
        self.cache_dir = None if cache_dir is None else os.fspath(cache_dir)
        if cache_bytes is not None and (not isinstance(cache_bytes, (int, np.integer)) or not 0 < cache_bytes < 1 << 63):
            raise DataError(f"cache_bytes: {cache_bytes!r}: expected a positive integer")
        self.cache_bytes = None if cache_bytes is None else int(cache_bytes)
        self.storage_options = None if storage_options is None else {str(k): str(v) for k, v in storage_options.items()}
        self.crop_store = self._find_store(crop_store)
        # The epoch of `ds[i]`, in shared memory: worker processes (forked or spawned,
        # persistent or not) read the value `set_epoch` wrote.
        self._epoch: Any = multiprocessing.RawValue("Q", 0)
        self._samplers: Optional[weakref.WeakSet[EpochSampler]] = weakref.WeakSet()
        self._loader = self._open()
        if is_url(self.path):
            # The store the publication record gave (its URL), as reopened in a worker.
            self.crop_store = self._loader.crop_store
        if self.tensors:
            import torch  # noqa: F401  (fail now, not in a worker)

    def _find_store(self, crop_store: Optional[PathLike]) -> Optional[str]:
        if crop_store is None:
            return None
        if is_url(self.path):
            # Resolved by the native loader against the dataset's publication record.
            return os.fspath(crop_store)
        if isinstance(crop_store, str) and crop_store == "auto":
            folder = os.fspath(_native.default_crop_store(self.path, self.compat, self.img_size))
            return folder if os.path.isfile(os.path.join(folder, "crops.json")) else None
        return os.fspath(crop_store)

    def _open(self) -> _native.Loader:
        return _native.Loader(
            self.path,
            self.split,
            self.mode,
            self.compat,
            self.img_size,
            self.n_pts,
            self.seed,
            self.resources,
            self.crop_store,
            self.cache_dir,
            self.cache_bytes,
            self.storage_options,
        )

    # Pickled for spawn-started workers: the native loader is reopened there, the
    # epoch's shared memory is passed on (only possible while a process is started;
    # any other copy, e.g. copy.deepcopy, gets the value).
    def __getstate__(self) -> Dict[str, Any]:
        state = dict(self.__dict__)
        # What the parent serves: a reopened loader serving anything else is refused.
        state["_generation"] = self._loader.generation if self._loader is not None else None
        state["_loader"] = None
        state["_samplers"] = None
        if multiprocessing.context.get_spawning_popen() is None:
            state["_epoch"] = int(self._epoch.value)
        state.pop("_batch_pool", None)
        state.pop("_segment_pool", None)
        state.pop("_ahead", None)
        return state

    def __setstate__(self, state: Dict[str, Any]) -> None:
        self.__dict__.update(state)
        if isinstance(self._epoch, int):
            self._epoch = multiprocessing.RawValue("Q", self._epoch)
        self._samplers = weakref.WeakSet()
        self._loader = self._open()
        # The folder rewritten (`convert --overwrite`, `render`, `crops`) between the
        # parent's open and this one: serving it would mix two generations.
        # Refused at the first item, so that the DataLoader carries the error (with the
        # folder's name) to the training process instead of a worker dying unpickling.
        parent = self.__dict__.pop("_generation", None)
        if parent is not None and self._loader.generation != parent:
            self._loader = _ChangedLoader(  # type: ignore[assignment]
                f"{self.path}: the dataset changed since this job opened it (dataset.json's "
                "fingerprint or the crop store's crops.json differs): a worker cannot serve "
                "another generation than its parent's; start the job again"
            )

    def __len__(self) -> int:
        return len(self._loader)

    @property
    def epoch(self) -> int:
        """The epoch of `ds[i]` (`set_epoch`)."""
        return int(self._epoch.value)

    @epoch.setter
    def epoch(self, epoch: int) -> None:
        self.set_epoch(epoch)

    def set_epoch(self, epoch: int) -> None:
        """The epoch whose random draws `ds[i]` uses (training mode), seen by worker
        processes too (shared memory). Also the next pass of the `EpochSampler`s made
        for this dataset (`ds.loader`), so either call works. Call it before the pass
        (before `iter(loader)`: persistent workers start prefetching then)."""
        try:
            e = _check_u64("epoch", epoch)
        except ValueError as err:
            raise DataError(str(err)) from None
        self._epoch.value = e
        for sampler in list(self._samplers or ()):
            sampler.set_epoch(e)

    def current_epoch(self) -> int:
        """The epoch of an index that carries none (`ds[i]`, a plain DataLoader's
        sampler): `set_epoch`'s. Override to derive it otherwise."""
        return int(self._epoch.value)

    def _attach_sampler(self, sampler: EpochSampler) -> None:
        if self._samplers is not None:
            self._samplers.add(sampler)

    def _split(self, index: Any) -> Tuple[int, int]:
        """`(epoch, position)` of an index: `i` (the current epoch) or `(epoch, i)`."""
        if isinstance(index, tuple):
            if len(index) != 2:
                raise IndexError(f"index {index!r}: expected a position or (epoch, position)")
            epoch, index = index
            try:
                epoch = _check_u64("epoch", epoch)
            except ValueError as err:
                raise IndexError(f"index: {err}") from None
        else:
            epoch = self.current_epoch()
        return epoch, _position(index, len(self))

    def key(self, index: int) -> SplitKey:
        """`(subject_id, facial_action, img_id, split)` of sample `index`."""
        return self._loader.key(_position(index, len(self)))

    def item(self, index: int, epoch: Optional[int] = None, extras: bool = False) -> _ItemT:
        """Sample `index` (of `epoch`, default the current one). `extras` adds, for
        checks: `choose_box` and `box` (official: the points before mapping, the integer
        box), `box_clipped`, `crop` (x0, y0, side_x, side_y) and `image_path`."""
        index = _position(index, len(self))
        if epoch is None:
            epoch = self.current_epoch()
        else:
            try:
                epoch = _check_u64("epoch", epoch)
            except ValueError as err:
                raise DataError(str(err)) from None
        d: Any = self._loader.item(
            index,
            epoch,
            self.corr,
            self.mode == "eval",
            extras,
        )
        if self.tensors:
            import torch

            d = {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in d.items()}
        return cast(_ItemT, d)

    def __getitem__(self, index: Union[int, np.integer[Any], Tuple[int, int]]) -> _ItemT:
        """`ds[i]`: sample `i` of the current epoch; `ds[epoch, i]`: of `epoch`."""
        epoch, index = self._split(index)
        return self.item(index, epoch)

    def __getitems__(self, indices: Sequence[Any]) -> ItemBatch:
        """Samples `indices` (positions, of the current epoch, or `(epoch, position)`
        pairs, as `EpochSampler` yields; one epoch per batch), computed together into
        batch arrays (what torch's DataLoader calls, since torch 2.0, for a whole batch
        of a map-style dataset). The result is a list of per-sample dicts equal to
        `self[i]`, as the default collate expects, whose arrays are views of the batch
        arrays: `collate` returns those arrays without stacking them again."""
        pairs = [self._split(i) for i in indices]
        epochs = {e for e, _ in pairs}
        if len(epochs) > 1:
            raise ValueError(f"a batch of indices of several epochs {sorted(epochs)}: one epoch per batch")
        epoch = epochs.pop() if epochs else self.current_epoch()
        # The dense matrix is carried as its sparse form (`CorrespondenceMatrix`) and
        # built where it is read: 24 KB a sample instead of 5 MB.
        native_corr: Corr = "sparse" if self.corr in ("dense", "both") else self.corr
        evaluation = self.mode == "eval"
        positions = [i for _, i in pairs]
        if any(isinstance(i, tuple) for i in indices):
            self._prefetch_ahead(epoch, positions)
        else:
            self._prefetch_queued()
        segment: Optional[_shared_batches.Segment] = None
        if _shared_batches.in_worker() and _shared_batches.enabled():
            # In a DataLoader worker: computed straight into shared memory that the
            # training process maps once and reuses (no copy on the way out).
            arrays, segment = self._batch_in_segment(positions, epoch, native_corr, evaluation)
        else:
            pool: List[Dict[str, Any]] = self.__dict__.setdefault("_batch_pool", [])
            reuse = _free_batch(pool, len(pairs))
            arrays = self._loader.batch(positions, epoch, native_corr, evaluation, reuse)
            if reuse is None:
                _keep_batch(pool, arrays)
        arrays = _with_corr_mat(arrays, self.corr)
        if "torch" in sys.modules:
            _teach_default_collate()
        return ItemBatch(arrays, self.tensors, segment)

    def _prefetch_ahead(self, epoch: int, positions: List[int]) -> None:
        """From a bucket, in a DataLoader worker of `ds.loader`: starts fetching the
        records of this worker's next two batches (torch hands a worker every
        `num_workers`-th batch of the sampler's order, which this process can compute),
        so that the network's wait overlaps this batch's work. Bounded: two batches
        ahead, at most 1,024 records held. Nothing for a local dataset, outside a
        worker, or when the order is not this dataset's one `EpochSampler`'s."""
        if not positions or not is_url(self.path) or not _shared_batches.in_worker():
            return
        samplers = list(self._samplers or ())
        if len(samplers) != 1:
            return
        import torch

        info = torch.utils.data.get_worker_info()
        if info is None:
            return
        sampler = samplers[0]
        ahead = self.__dict__.get("_ahead")
        if ahead is None or ahead[0] != (epoch, id(sampler)):
            order = sampler.indices(epoch)
            where: Dict[int, int] = {}
            for k, p in enumerate(order):
                where.setdefault(p, k)
            ahead = self.__dict__["_ahead"] = ((epoch, id(sampler)), order, where)
        _, order, where = ahead
        at = where.get(positions[0])
        if at is None or order[at:at + len(positions)] != positions:
            return
        step = info.num_workers * len(positions)
        for d in (1, 2):
            upcoming = order[at + d * step:at + d * step + len(positions)]
            if upcoming:
                self._loader.prefetch_async(upcoming)

    def _prefetch_queued(self) -> None:
        """From a bucket, in a worker of a plain DataLoader (the official train.py's,
        whose sampler runs in the training process): has `_WorkerLookahead` start each
        batch's fetch as soon as torch assigns the batch to this worker, so that the
        network's wait overlaps the work of the batch before it. Nothing for a local
        dataset, outside a worker, or when torch's worker loop is not the one this was
        written against."""
        if not is_url(self.path) or not _shared_batches.in_worker():
            return
        _WorkerLookahead.of_this_worker(self._prefetch_task)

    def _prefetch_task(self, task: Any) -> None:
        """Starts the fetch of a batch task `(idx, indices)` torch sent this worker."""
        if not (isinstance(task, tuple) and len(task) == 2 and isinstance(task[1], list)):
            return
        n = len(self)
        batch = task[1]
        if batch and all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) and 0 <= i < n
                         for i in batch):
            self._loader.prefetch_async([int(i) for i in batch])

    def _batch_in_segment(
        self, positions: List[int], epoch: int, corr: Corr, evaluation: bool
    ) -> Tuple[Dict[str, Any], _shared_batches.Segment]:
        """A batch computed into one of this worker's shared-memory segments."""
        pool = self.__dict__.get("_segment_pool")
        if pool is None or pool.pid != os.getpid():
            pool = self.__dict__["_segment_pool"] = _shared_batches.SegmentPool()
        shapes = pool.shapes.get((corr, evaluation))
        if shapes is None:
            # An empty batch of these options gives the arrays' shapes.
            empty = self._loader.batch([], epoch, corr, evaluation, None)
            shapes = pool.shapes[(corr, evaluation)] = _shared_batches.per_sample_shapes(empty)
        segment = pool.acquire(_shared_batches.batch_shapes(shapes, len(positions)))
        arrays = self._loader.batch(positions, epoch, corr, evaluation, segment.arrays)
        return arrays, segment

    def sampler(
        self,
        shuffle: bool = True,
        seed: Optional[int] = None,
        num_replicas: Optional[int] = None,
        rank: Optional[int] = None,
        remainder: Remainder = "pad",
        epoch: Optional[int] = None,
    ) -> EpochSampler:
        """An `EpochSampler` over this dataset (seed: the dataset's by default; shard:
        from `torch.distributed` when initialised; first epoch: the dataset's current
        one). `ds.set_epoch` reaches it too."""
        return EpochSampler(
            self,
            shuffle=shuffle,
            seed=self.seed if seed is None else seed,
            num_replicas=num_replicas,
            rank=rank,
            remainder=remainder,
            epoch=self.current_epoch() if epoch is None else epoch,
        )

    @overload
    def loader(
        self,
        batch_size: int = ...,
        shuffle: bool = ...,
        *,
        seed: Optional[int] = ...,
        num_replicas: Optional[int] = ...,
        rank: Optional[int] = ...,
        remainder: Remainder = ...,
        sampler: Any,
        **kwargs: Any,
    ) -> DataLoader[_ItemT]: ...

    @overload
    def loader(
        self,
        batch_size: int = ...,
        shuffle: bool = ...,
        *,
        seed: Optional[int] = ...,
        num_replicas: Optional[int] = ...,
        rank: Optional[int] = ...,
        remainder: Remainder = ...,
        batch_sampler: Any,
        **kwargs: Any,
    ) -> DataLoader[_ItemT]: ...

    @overload
    def loader(
        self,
        batch_size: int = ...,
        shuffle: bool = ...,
        *,
        seed: Optional[int] = ...,
        num_replicas: Optional[int] = ...,
        rank: Optional[int] = ...,
        remainder: Remainder = ...,
        collate_fn: Callable[[Any], _BatchT],
        **kwargs: Any,
    ) -> EpochLoader[_BatchT]: ...

    @overload
    def loader(
        self,
        batch_size: int = ...,
        shuffle: bool = ...,
        *,
        seed: Optional[int] = ...,
        num_replicas: Optional[int] = ...,
        rank: Optional[int] = ...,
        remainder: Remainder = ...,
        **kwargs: Any,
    ) -> EpochLoader[Batch]: ...

    def loader(
        self,
        batch_size: int = 64,
        shuffle: bool = False,
        *,
        seed: Optional[int] = None,
        num_replicas: Optional[int] = None,
        rank: Optional[int] = None,
        remainder: Remainder = "pad",
        **kwargs: Any,
    ) -> Any:
        """An `EpochLoader`: `torch.utils.data.DataLoader(self, batch_size,
        sampler=self.sampler(shuffle, ...), collate_fn=collate, **kwargs)` (`num_workers`,
        `persistent_workers`, `drop_last`, `multiprocessing_context`, ... pass through).

        - Batches are computed in place: the same tensors as the default collate gives.
        - Epochs: every index carries its epoch to the worker that computes it; each pass
          over the loader is the next epoch (the first: the dataset's current epoch),
          or call `loader.set_epoch(e)` (or `ds.set_epoch(e)`) before a pass.
        - Shards: under `torchrun` (`torch.distributed` initialised) each rank gets its
          shard of every epoch's order (`num_replicas`, `rank` override), the same
          number of samples, hence of batches, on every rank. `remainder="pad"` (the
          default, as `DistributedSampler`) repeats the order's first `-len % ranks`
          samples; `"drop"` leaves out its last `len % ranks` samples. With
          `drop_last=True` a rank's incomplete last batch is left out too.
        - Resume: save `loader.state_dict()` with the checkpoint (each rank its own);
          after the restart `loader.load_state_dict(state)` on a loader made the same
          way (any `num_workers`) gives the remaining batches of that epoch, bit for bit
          those of the uninterrupted run, then the next epochs.
        - `shuffle`: a permutation per epoch from `(seed, epoch)` (the dataset's seed by
          default). A `sampler` or `batch_sampler` of your own makes a plain
          DataLoader (no epochs carried, no shards, no resume: call `ds.set_epoch`)."""
        import torch

        kwargs.setdefault("collate_fn", collate)
        if "sampler" in kwargs or "batch_sampler" in kwargs:
            return torch.utils.data.DataLoader(self, batch_size=batch_size, shuffle=shuffle, **kwargs)
        from .sampling import loader_class

        sampler = self.sampler(shuffle, seed, num_replicas, rank, remainder)
        return loader_class()(self, batch_size=batch_size, sampler=sampler, **kwargs)


class _WorkerLookahead:
    """This DataLoader worker's index queue, drained by a thread: torch's worker loop
    (`torch.utils.data._utils.worker._worker_loop`) takes its next task with
    `index_queue.get(...)`; that method of the queue object is replaced by one that hands
    out, in order, the tasks the thread took, and the thread shows each task to
    `on_task` as soon as it arrives (a batch's records are then fetched while the batch
    before it is computed). Found once per process by its frame (the loop's
    `index_queue`); where it is not there (another torch), nothing changes."""

    _this: Optional[Tuple[int, Optional[_WorkerLookahead]]] = None

    def __init__(self, index_queue: Any, on_task: Callable[[Any], None]) -> None:
        self._get = index_queue.get
        self._tasks: queue.Queue[Any] = queue.Queue()
        self._on_task = on_task
        index_queue.get = self.get
        threading.Thread(target=self._drain, name="arkit-lookahead", daemon=True).start()

    def _drain(self) -> None:
        while True:
            try:
                task = self._get(True, 1.0)
            except queue.Empty:
                continue
            except Exception:  # the queue closed as the worker ends
                return
            self._tasks.put(task)
            if task is None:  # torch's final signal
                return
            try:
                self._on_task(task)
            except Exception:  # a fetch ahead only saves time; the item reports errors
                pass

    def get(self, block: bool = True, timeout: Optional[float] = None) -> Any:
        return self._tasks.get(block, timeout)

    @classmethod
    def of_this_worker(cls, on_task: Callable[[Any], None]) -> Optional[_WorkerLookahead]:
        this = cls._this
        if this is not None and this[0] == os.getpid():
            return this[1]
        found: Optional[_WorkerLookahead] = None
        frame = sys._getframe(1)
        while frame is not None:
            if frame.f_code.co_name == "_worker_loop" and "index_queue" in frame.f_locals:
                found = cls(frame.f_locals["index_queue"], on_task)
                break
            frame = frame.f_back  # type: ignore[assignment]
        cls._this = (os.getpid(), found)
        return found


# Batch arrays written over again once nobody holds them (`__getitems__`): arrays of a
# batch's size are fresh pages from the kernel, and touching them (a page fault per 4 KiB,
# 80,000 for a dense batch of 64) cost more than computing the samples. Two batches are
# kept: a training loop holds the previous batch while the next one is computed.
_REUSED = ("img", "uvmap", "mask", "choose", "model", "nocs", "corr_ids", "corr_weights", "corr_mat")
_POOL_SIZE = 2


def _free_batch(pool: List[Dict[str, Any]], b: int) -> Optional[Dict[str, Any]]:
    """A kept batch of `b` samples none of whose arrays is referenced outside `pool`, or
    None. Every view (numpy's, torch's tensors from `collate`) holds a reference to the array
    that owns the memory, so an owner referenced only by the pool is free; the probe, held
    the same way, gives the pool's own count."""
    for kept in pool:
        if kept["img"].shape[0] != b:
            continue
        if all(sys.getrefcount(kept[k]) <= sys.getrefcount(kept["_probe"]) for k in kept if k != "_probe"):
            return kept
    return None


def _keep_batch(pool: List[Dict[str, Any]], arrays: Dict[str, Any]) -> None:
    kept = {k: arrays[k] for k in _REUSED if k in arrays}
    kept["_probe"] = np.empty(0)
    pool.insert(0, kept)
    del pool[_POOL_SIZE:]


def _with_corr_mat(arrays: Dict[str, Any], corr: Corr) -> Dict[str, Any]:
    """A batch computed with sparse correspondences, with `corr_mat` (the dense
    matrix, as a `CorrespondenceMatrix`) where it belongs and `corr_ids` /
    `corr_weights` kept only for `corr="both"`."""
    if corr == "sparse":
        return arrays
    matrix = CorrespondenceMatrix(arrays["corr_ids"], arrays["corr_weights"], arrays["model"].shape[-2])
    out: Dict[str, Any] = {}
    for k, v in arrays.items():
        if k == "corr_ids":
            out["corr_mat"] = matrix
        if k in ("corr_ids", "corr_weights") and corr != "both":
            continue
        out[k] = v
    return out

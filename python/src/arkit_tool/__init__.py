"""arkit_tool: the ARKitFace dataset for PyTorch, computed by the arkit-tool Rust library.

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

Errors are `DataError` (a `ValueError`) with a message naming the file and the problem.
See docs/python.md in the repository.
"""

from __future__ import annotations

import json
import multiprocessing
import multiprocessing.context
import os
import sys
import weakref
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np

from . import _native, _shared_batches, conventions
from ._native import DataError
from .correspondences import CorrespondenceMatrix

# Named where users import it, so that it pickles: a DataLoader worker sends the
# exception of a sample that fails to the training process (under its Rust module's
# name it could not be found there, and the batch never arrived).
DataError.__module__ = "arkit_tool"
from .sampling import EpochSampler, _check_u64, distributed_rank

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


def __getattr__(name):
    # EpochLoader subclasses torch's DataLoader: made on first use, so that importing
    # arkit_tool does not import torch (not in __all__ for the same reason).
    if name == "EpochLoader":
        from .sampling import loader_class

        return loader_class()
    raise AttributeError(f"module 'arkit_tool' has no attribute {name!r}")

Key = Tuple[str, str, str]


class ConvertedDataset:
    """A dataset written by `arkit-tool convert` (the folder holding `dataset.json`)."""

    def __init__(self, path: Union[str, os.PathLike]):
        self.path = os.fspath(path)
        self._native = _native.Dataset(self.path)
        self._keys = self._native.keys()
        self._index: Optional[Dict[Key, int]] = None

    def __len__(self) -> int:
        return len(self._keys)

    def __repr__(self) -> str:
        return f"ConvertedDataset({self.path!r}, {len(self)} samples, splits {self.splits})"

    @property
    def manifest(self) -> Dict[str, Any]:
        """The conversion's manifest (`dataset.json`)."""
        return json.loads(self._native.manifest_json())

    @property
    def keys(self) -> List[Key]:
        """`(subject_id, facial_action, img_id)` of every sample, in order."""
        return [k[:3] for k in self._keys]

    @property
    def splits(self) -> Dict[str, int]:
        """Samples per split (`split`'s assignment when it has run, else the lists')."""
        out: Dict[str, int] = {}
        for k in self._keys:
            out[k[3]] = out.get(k[3], 0) + 1
        return out

    def split_indices(self, split: str) -> List[int]:
        """Positions of the samples of `split`."""
        return [i for i, k in enumerate(self._keys) if k[3] == split]

    def index_of(self, key: Key) -> int:
        """The position of `(subject_id, facial_action, img_id)`."""
        if self._index is None:
            self._index = {k[:3]: i for i, k in enumerate(self._keys)}
        try:
            return self._index[tuple(str(x) for x in key)]
        except KeyError:
            raise DataError(f"{self.path}: no sample {tuple(key)}") from None

    def sample(self, which: Union[int, Key]) -> Dict[str, Any]:
        """One sample's row: verts (1220x3), R_t (4x4), image path and size, keys, pose."""
        index = _position(which, len(self)) if isinstance(which, (int, np.integer)) else self.index_of(which)
        return self._native.sample(index)

    @property
    def shard_files(self) -> List[str]:
        """The samples tables (Parquet), in order."""
        return self._native.shard_files()

    @property
    def samples(self):
        """The samples table: a polars DataFrame when polars is installed, else a pyarrow
        Table (one of the two is needed)."""
        try:
            import polars as pl

            return pl.concat([pl.read_parquet(f) for f in self.shard_files])
        except ImportError:
            pass
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise ImportError(
                "the samples table needs polars or pyarrow: pip install pyarrow"
            ) from None
        return pa.concat_tables([pq.read_table(f) for f in self.shard_files])


def open_dataset(path: Union[str, os.PathLike]) -> ConvertedDataset:
    """Opens a dataset written by `arkit-tool convert`."""
    return ConvertedDataset(path)


class ARKitFaceDataset:
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
    """

    def __init__(
        self,
        path: Union[str, os.PathLike],
        split: Optional[str] = "train",
        mode: str = "train",
        compat: str = "exact",
        img_size: int = 192,
        n_pts: int = 1024,
        seed: int = 0,
        resources: Optional[Union[str, os.PathLike]] = None,
        corr: str = "dense",
        tensors: bool = False,
        crop_store: Optional[Union[str, os.PathLike]] = "auto",
    ):
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
        self.crop_store = self._find_store(crop_store)
        # The epoch of `ds[i]`, in shared memory: worker processes (forked or spawned,
        # persistent or not) read the value `set_epoch` wrote.
        self._epoch = multiprocessing.RawValue("Q", 0)
        self._samplers: "weakref.WeakSet[EpochSampler]" = weakref.WeakSet()
        self._loader = self._open()
        if self.tensors:
            import torch  # noqa: F401  (fail now, not in a worker)

    def _find_store(self, crop_store) -> Optional[str]:
        if crop_store is None:
            return None
        if isinstance(crop_store, str) and crop_store == "auto":
            folder = os.fspath(_native.default_crop_store(self.path, self.compat, self.img_size))
            return folder if os.path.isfile(os.path.join(folder, "crops.json")) else None
        return os.fspath(crop_store)

    def _open(self):
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
        )

    # Pickled for spawn-started workers: the native loader is reopened there, the
    # epoch's shared memory is passed on (only possible while a process is started;
    # any other copy, e.g. copy.deepcopy, gets the value).
    def __getstate__(self):
        state = dict(self.__dict__)
        state["_loader"] = None
        state["_samplers"] = None
        if multiprocessing.context.get_spawning_popen() is None:
            state["_epoch"] = int(self._epoch.value)
        state.pop("_batch_pool", None)
        state.pop("_segment_pool", None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        if isinstance(self._epoch, int):
            self._epoch = multiprocessing.RawValue("Q", self._epoch)
        self._samplers = weakref.WeakSet()
        self._loader = self._open()

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

    def _split(self, index) -> Tuple[int, int]:
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

    def key(self, index: int) -> Tuple[str, str, str, str]:
        """`(subject_id, facial_action, img_id, split)` of sample `index`."""
        return self._loader.key(_position(index, len(self)))

    def item(self, index: int, epoch: Optional[int] = None, extras: bool = False) -> Dict[str, Any]:
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
        d = self._loader.item(
            index,
            epoch,
            self.corr,
            self.mode == "eval",
            extras,
        )
        if self.tensors:
            import torch

            d = {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in d.items()}
        return d

    def __getitem__(self, index) -> Dict[str, Any]:
        """`ds[i]`: sample `i` of the current epoch; `ds[epoch, i]`: of `epoch`."""
        epoch, index = self._split(index)
        return self.item(index, epoch)

    def __getitems__(self, indices: Sequence) -> "ItemBatch":
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
        native_corr = "sparse" if self.corr in ("dense", "both") else self.corr
        evaluation = self.mode == "eval"
        positions = [i for _, i in pairs]
        segment = None
        if _shared_batches.in_worker() and _shared_batches.enabled():
            # In a DataLoader worker: computed straight into shared memory that the
            # training process maps once and reuses (no copy on the way out).
            arrays, segment = self._batch_in_segment(positions, epoch, native_corr, evaluation)
        else:
            pool = self.__dict__.setdefault("_batch_pool", [])
            reuse = _free_batch(pool, len(pairs))
            arrays = self._loader.batch(positions, epoch, native_corr, evaluation, reuse)
            if reuse is None:
                _keep_batch(pool, arrays)
        arrays = _with_corr_mat(arrays, self.corr)
        if "torch" in sys.modules:
            _teach_default_collate()
        return ItemBatch(arrays, self.tensors, segment)

    def _batch_in_segment(self, positions, epoch, corr, evaluation):
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
        remainder: str = "pad",
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

    def loader(
        self,
        batch_size: int = 64,
        shuffle: bool = False,
        *,
        seed: Optional[int] = None,
        num_replicas: Optional[int] = None,
        rank: Optional[int] = None,
        remainder: str = "pad",
        **kwargs,
    ):
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


# Batch arrays written over again once nobody holds them (`__getitems__`): arrays of a
# batch's size are fresh pages from the kernel, and touching them (a page fault per 4 KiB,
# 80,000 for a dense batch of 64) cost more than computing the samples. Two batches are
# kept: a training loop holds the previous batch while the next one is computed.
_REUSED = ("img", "uvmap", "mask", "choose", "model", "nocs", "corr_ids", "corr_weights", "corr_mat")
_POOL_SIZE = 2


def _free_batch(pool, b):
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


def _keep_batch(pool, arrays):
    kept = {k: arrays[k] for k in _REUSED if k in arrays}
    kept["_probe"] = np.empty(0)
    pool.insert(0, kept)
    del pool[_POOL_SIZE:]


class SampleView(dict):
    """One sample of an `ItemBatch`: a plain dict (`ds[i]`'s keys and values) whose
    arrays are views of the batch's arrays. Its type is what lets torch's default collate
    recognise a whole batch that needs no stacking (`collate`)."""

    __slots__ = ()


class ItemBatch(list):
    """The samples of one batch (`ARKitFaceDataset.__getitems__`): a list of per-sample
    dicts (`SampleView`), as torch's default collate expects, whose arrays are views of
    one set of batch arrays, `arrays` (the batch axis first; strings as lists)."""

    def __init__(self, arrays: Dict[str, Any], tensors: bool = False, segment=None):
        if tensors:
            arrays = {k: _as_torch(v) for k, v in arrays.items()}
        self.arrays = arrays
        # The shared memory the arrays live in, in a DataLoader worker (else None).
        self.segment = segment
        b = len(arrays["img"])
        super().__init__(SampleView((k, v[i]) for k, v in arrays.items()) for i in range(b))
        self._views = tuple(self)

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


def _with_corr_mat(arrays: Dict[str, Any], corr: str) -> Dict[str, Any]:
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


def _as_torch(v):
    """A batch value as torch gives it: arrays as tensors sharing their memory, a
    `CorrespondenceMatrix` over tensors, lists as they are."""
    import torch

    if isinstance(v, np.ndarray):
        return torch.from_numpy(v)
    if isinstance(v, CorrespondenceMatrix) and isinstance(v.ids, np.ndarray):
        return CorrespondenceMatrix(torch.from_numpy(v.ids), torch.from_numpy(v.weights), v.vertex_count)
    return v


def _is_row(v, whole, i: int) -> bool:
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
        return at == start + i * whole.strides[0] and v.strides == whole.strides[1:]
    return (
        v.untyped_storage().data_ptr() == whole.untyped_storage().data_ptr()
        and v.storage_offset() == whole.storage_offset() + i * whole.stride(0)
        and v.stride() == whole.stride()[1:]
    )


def collate(batch):
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


def _plain(batch):
    """`batch` with its `SampleView`s as plain dicts (what default_collate stacks; a
    `CorrespondenceMatrix` is stacked in its sparse form, `_collate_correspondences`)."""
    if isinstance(batch, list) and batch and isinstance(batch[0], SampleView):
        return [dict(s) for s in batch]
    return batch


def _collate_correspondences(batch, *, collate_fn_map=None):
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


def _collate_sample_views(batch, *, collate_fn_map=None):
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


def _position(index, n: int) -> int:
    """A sample position from a Python index (negative counts from the end)."""
    if not isinstance(index, (int, np.integer)) or isinstance(index, bool):
        raise TypeError(f"index {index!r}: expected an integer")
    i = int(index)
    if not -n <= i < n:
        raise IndexError(f"index {i} out of range for {n} samples")
    return i + n if i < 0 else i


# Largest mask and UV map a targets row may describe (arkit_core::limits).
_MAX_MASK_PIXELS = 1 << 26
_MAX_UV_SIZE = 4096


def _blob(row: Dict[str, Any], name: str, dtype: str, width: int) -> np.ndarray:
    data = row.get(name)
    if data is None:
        raise DataError(f"targets: column '{name}' is null or missing")
    size = np.dtype(dtype).itemsize * width
    if len(data) % size:
        raise DataError(f"targets: column '{name}': {len(data)} bytes, not whole {size}-byte elements")
    a = np.frombuffer(data, dtype=dtype)
    return a.reshape(-1, width) if width > 1 else a


def _rle(row: Dict[str, Any], name: str, pixels: int) -> np.ndarray:
    runs = _blob(row, name, "<u4", 1)
    if int(runs.sum(dtype=np.uint64)) != pixels:
        raise DataError(f"targets: column '{name}': runs cover {int(runs.sum(dtype=np.uint64))} pixels, expected {pixels}")
    return np.repeat(np.arange(len(runs)) % 2 == 1, runs)


def decode_targets(row: Dict[str, Any]) -> Dict[str, Any]:
    """One row of `render`'s targets table (a dict, e.g. from pyarrow's
    `Table.to_pylist()`) as numpy arrays, decoding the compact layouts of
    schemas/targets.json: `mask` (S x S bool, S = crop_size), `corr_vertices` (k x 3
    uint16: the visible triangle of each of the k face pixels, row-major),
    `corr_weights` (k x 3 float32, the third is 1 - w0 - w1), `points` (n int64: rows of
    the k face pixels), `uv_map` (uv x uv x 3 float16, NaN where no UV triangle covers a
    texel), `full_mask` (image_height x image_width bool, or None when not rendered) and
    the keys and crop fields as they are. Every size is checked before it is used;
    `DataError` names the column. `ARKitFaceDataset` computes the same targets (and
    the crop image) from the samples instead."""
    s, uv = row.get("crop_size"), row.get("uv_size")
    if not isinstance(s, int) or not 0 < s * s <= _MAX_MASK_PIXELS:
        raise DataError(f"targets: column 'crop_size': {s!r} is not a crop side")
    if not isinstance(uv, int) or not 0 < uv <= _MAX_UV_SIZE:
        raise DataError(f"targets: column 'uv_size': {uv!r} is not a UV map side")
    mask = _rle(row, "mask_rle", s * s).reshape(s, s)
    ids = _blob(row, "corr_vertices", "<u2", 3)
    q = _blob(row, "corr_weights", "<u2", 2).astype(np.float32) / 65535.0
    face = int(mask.sum())
    if len(ids) != face or len(q) != face:
        raise DataError(
            f"targets: columns 'corr_vertices', 'corr_weights': {len(ids)} and {len(q)} rows for {face} face pixels"
        )
    weights = np.concatenate([q, 1.0 - q.sum(axis=1, keepdims=True)], axis=1)
    points = _blob(row, "points", "<u4", 1).astype(np.int64)
    if len(points) and (face == 0 or int(points.max()) >= face):
        raise DataError(f"targets: column 'points': an index beyond the {face} face pixels")
    planes = _blob(row, "uv_map_delta", "u1", 1)
    if planes.size != 6 * uv * uv:
        raise DataError(f"targets: column 'uv_map_delta': {planes.size} bytes, expected {6 * uv * uv}")
    planes = planes.reshape(3, 2, uv, uv)
    delta = planes[:, 0].astype(np.uint16) | (planes[:, 1].astype(np.uint16) << 8)
    bits = np.cumsum(delta, axis=2, dtype=np.uint16)  # wrapping sums along each row
    uv_map = np.ascontiguousarray(bits.transpose(1, 2, 0)).view(np.float16)
    full = row.get("full_mask_rle")
    full_mask = None
    if full:
        w, h = row.get("image_width"), row.get("image_height")
        if not isinstance(w, int) or not isinstance(h, int) or not 0 < w * h <= _MAX_MASK_PIXELS:
            raise DataError(f"targets: columns 'image_width', 'image_height': {w!r} x {h!r}")
        full_mask = _rle(row, "full_mask_rle", w * h).reshape(h, w)
    out = {k: v for k, v in row.items() if not isinstance(v, (bytes, bytearray))}
    out.update(mask=mask, corr_vertices=ids, corr_weights=weights, points=points,
               uv_map=uv_map, full_mask=full_mask)
    return out


def solve_pnp_ransac(
    object_points,
    image_points,
    camera_matrix,
    dist_coeffs=None,
    reprojection_error: float = 8.0,
    iterations_count: int = 100,
    confidence: float = 0.99,
    seed: int = 0,
):
    """PnP with RANSAC, OpenCV's conventions (`cv2.solvePnPRansac`'s arguments and
    result): `X_cam = R X + t`. `object_points` (N, 3), `image_points` (N, 2) (or
    OpenCV's (N, 1, 3) and (N, 1, 2)); any other shape, a transposed (3, N) among
    them, is refused (`DataError`). Returns `(success, rvec, tvec, inliers)`, rvec and
    tvec (3, 1) float64, inliers (k, 1) int32; `(False, None, None, None)` on failure.
    Distortion is not modelled: `dist_coeffs` must be None or zeros. Points with a NaN or
    infinite coordinate are left out (never inliers; indices are the caller's)."""
    if dist_coeffs is not None and np.any(np.asarray(dist_coeffs) != 0):
        raise DataError("dist_coeffs: lens distortion is not supported; undistort the points first")
    obj = _points("object_points", object_points, 3)
    img = _points("image_points", image_points, 2)
    if len(obj) != len(img):
        raise DataError(f"object_points and image_points: {len(obj)} and {len(img)} points; expected as many of each")
    k = np.ascontiguousarray(np.asarray(camera_matrix, dtype=np.float64))
    if k.shape != (3, 3):
        raise DataError(f"camera_matrix: shape {k.shape}; expected (3, 3)")
    return _native.solve_pnp_ransac(
        obj, img, k, float(reprojection_error), int(iterations_count), float(confidence), int(seed)
    )


def _points(name: str, value, width: int) -> np.ndarray:
    """(N, width) float64 points; OpenCV's (N, 1, width) accepted; anything else refused."""
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 3 and a.shape[1] == 1:
        a = a[:, 0, :]
    if a.ndim != 2 or a.shape[1] != width:
        hint = " (transposed? pass the points as rows)" if a.ndim == 2 and a.shape[0] == width else ""
        raise DataError(f"{name}: shape {a.shape}; expected (N, {width}){hint}")
    return np.ascontiguousarray(a)


def _pose(name: str, value) -> np.ndarray:
    """A 4x4 float64 pose from (4, 4) or its 16 values row by row."""
    a = np.asarray(value, dtype=np.float64)
    if a.shape == (16,):
        a = a.reshape(4, 4)
    if a.shape != (4, 4):
        raise DataError(f"{name}: shape {a.shape}; expected (4, 4) or 16 values row by row")
    return np.ascontiguousarray(a)


def read_image(path: Union[str, os.PathLike]) -> np.ndarray:
    """An image file decoded as the loader decodes it: (H, W, 3) uint8 RGB."""
    return _native.read_image(os.fspath(path))


def project(verts, R_t, width: int, height: int) -> np.ndarray:
    """Canonical points (N, 3) to image pixels (N, 2) with the release's row-vector
    `R_t` (4, 4), or its 16 values row by row (the samples table's flat form), and
    camera, for a `width x height` image. Any other shape (transposed points among
    them) is refused (`DataError`)."""
    v = _points("verts", verts, 3)
    m = _pose("R_t", R_t)
    return _native.project(v, m, int(width), int(height))


def evaluate(
    dataset: Union[str, os.PathLike],
    predictions: Union[str, os.PathLike, Dict[Key, Any], Iterable[Tuple[str, str, str, Any]]],
    split: Optional[str] = None,
) -> Dict[str, Any]:
    """The paper's metrics (what `arkit-tool eval --json` prints) of `predictions`: a
    predictions file (Parquet or CSV), a dict `{(subject_id, facial_action, img_id):
    R_t}` or rows `(subject_id, facial_action, img_id, R_t)`; an `R_t` (4 x 4, or its
    16 values row by row) of None is a failed prediction."""
    if isinstance(predictions, (str, os.PathLike)):
        text = _native.evaluate(os.fspath(dataset), None, os.fspath(predictions), split)
        return json.loads(text)
    items: Sequence = list(predictions.items()) if isinstance(predictions, dict) else list(predictions)
    rows = []
    for item in items:
        if isinstance(predictions, dict):
            (s, a, i), rt = item
        else:
            s, a, i, rt = item
        flat = None if rt is None else [float(x) for x in _pose(f"R_t of {(s, a, i)}", rt).reshape(-1)]
        rows.append((str(s), str(a), str(i), flat))
    return json.loads(_native.evaluate(os.fspath(dataset), rows, None, split))

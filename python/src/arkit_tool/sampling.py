"""Epochs, shards and resumable positions for `ARKitFaceDataset` in torch's DataLoader.

- `EpochSampler`: the order of one epoch (shuffled from `(seed, epoch)`, or in order),
  this process's shard of it under `torchrun`, and indices that carry their epoch: it
  yields `(epoch, index)` pairs, which `ARKitFaceDataset.__getitem__` / `__getitems__`
  read, so the epoch travels with each index to whichever worker process computes it
  (no worker keeps a stale epoch, persistent or not, fork or spawn). Its epoch advances
  by one at each new pass (or is set with `set_epoch`). It has torchdata's
  `state_dict` / `load_state_dict`.
- `EpochLoader`: what `ARKitFaceDataset.loader` returns, a `torch.utils.data.DataLoader`
  over an `EpochSampler` with `set_epoch`, and a `state_dict` / `load_state_dict` that
  hold the position of the batches handed out (not those prefetched), so a run resumes
  mid-epoch with the same remaining batches, whatever `num_workers` is after the
  restart.

torch is imported only when a loader is made; the sampler itself needs numpy only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Dict, Generic, Iterator, List, Mapping, Optional, Tuple, cast

import numpy as np

from .types import LoaderState, Remainder, SamplerState

if TYPE_CHECKING:
    from torch.utils.data import DataLoader
    from typing_extensions import TypeVar

    from .types import Batch

__all__ = ["EpochSampler", "distributed_rank"]  # and EpochLoader, made on first use (torch)

_STATE_VERSION = 1


def distributed_rank() -> Tuple[int, int]:
    """`(num_replicas, rank)` from `torch.distributed` when it is initialised (as under
    `torchrun` after `init_process_group`), else `(1, 0)`."""
    try:
        import torch.distributed as dist
    except ImportError:
        return 1, 0
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size(), dist.get_rank()
    return 1, 0


class EpochSampler:
    """Indices of one epoch, as `(epoch, index)` pairs, for one process's shard.

    `size`: the dataset's length (or the dataset). `shuffle`: a permutation drawn from
    `(seed, epoch)` (numpy's PCG64), the same on every rank and in every run; else in
    order. `num_replicas` / `rank`: the shard (default: from `torch.distributed` when
    it is initialised, else one shard). As `DistributedSampler` does, every rank gets
    the same number of indices: rank `r` takes positions `r, r + R, r + 2R, ...` of
    the epoch's order; `remainder="pad"` (the default) first repeats the order's first
    indices until its length divides by `R` (every sample is seen, up to `R - 1` twice
    per epoch), `"drop"` leaves out the order's last `len % R` (none twice, those
    unseen this epoch).

    Epochs: each new pass (`iter`) takes the next epoch, starting at `epoch`; `set_epoch(e)`
    makes the next pass epoch `e` (call it before the pass, as for `DistributedSampler`;
    calling it every epoch or never both work). The pass begins when its first index is
    drawn, so an iterator made and never used does not use up an epoch.

    `state_dict()` / `load_state_dict()`: the next index to be drawn (epoch, position in
    this shard's order) with the seed and shard it belongs to; a state of another seed,
    dataset size or shard is refused. Through torchdata's `StatefulDataLoader`, whose
    snapshots account for prefetching, this resumes mid-epoch (with the same
    `num_workers`). `EpochLoader` keeps its own position and also resumes with another
    `num_workers`.
    """

    def __init__(
        self,
        size: Any,
        shuffle: bool = True,
        seed: int = 0,
        num_replicas: Optional[int] = None,
        rank: Optional[int] = None,
        remainder: Remainder = "pad",
        epoch: int = 0,
    ) -> None:
        dataset: Any = None
        if not isinstance(size, (int, np.integer)):
            dataset, size = size, len(size)
        self.size = int(size)
        if self.size < 0:
            raise ValueError(f"size: {size}: expected a dataset length >= 0")
        if remainder not in ("pad", "drop"):
            raise ValueError(f"remainder: {remainder!r}: expected 'pad' or 'drop'")
        if num_replicas is None or rank is None:
            world, r = distributed_rank()
            num_replicas = world if num_replicas is None else num_replicas
            rank = r if rank is None else rank
        if int(num_replicas) < 1 or not 0 <= int(rank) < int(num_replicas):
            raise ValueError(f"rank {rank} of num_replicas {num_replicas}: expected 0 <= rank < num_replicas")
        self.shuffle = bool(shuffle)
        self.seed = _check_u64("seed", seed)
        self.num_replicas = int(num_replicas)
        self.rank = int(rank)
        self.remainder = remainder
        if remainder == "drop":
            self.shard_size = self.size // self.num_replicas
        else:
            self.shard_size = -(-self.size // self.num_replicas)
        if remainder == "pad" and self.size == 0:
            self.shard_size = 0
        # The pass the next `iter` begins: (epoch, position in the shard).
        self._next: Tuple[int, int] = (_check_u64("epoch", epoch), 0)
        # The pass being drawn: [epoch, position of the next index], or None.
        self._live: Optional[List[int]] = None
        self._claimed: Optional[Tuple[int, int]] = None
        self.epoch = self._next[0]
        if dataset is not None and hasattr(dataset, "_attach_sampler"):
            dataset._attach_sampler(self)

    def __len__(self) -> int:
        return self.shard_size

    def indices(self, epoch: int) -> List[int]:
        """This shard's indices of `epoch`, in the order they are drawn."""
        n, r = self.size, self.num_replicas
        if self.shuffle:
            order = np.random.Generator(np.random.PCG64([self.seed, int(epoch)])).permutation(n)
        else:
            order = np.arange(n)
        total = self.shard_size * r
        if total > n:
            order = np.concatenate([order, np.resize(order, total - n)])
        return [int(i) for i in order[self.rank:total:r]]

    def set_epoch(self, epoch: int) -> None:
        """The next pass is epoch `epoch`, from its start."""
        self._next = (_check_u64("epoch", epoch), 0)

    def _claim(self) -> Tuple[int, int]:
        """Begins a pass: its (epoch, start) and the next pass after it."""
        if self._claimed is not None:
            claimed, self._claimed = self._claimed, None
            return claimed
        epoch, start = self._next
        self._next = (epoch + 1, 0)
        self.epoch = epoch
        return epoch, start

    def __iter__(self) -> Iterator[Tuple[int, int]]:
        epoch, start = self._claim()
        order = self.indices(epoch)
        live = self._live = [epoch, start]
        for i in order[start:]:
            live[1] += 1
            yield (epoch, i)
        if self._live is live:
            self._live = None

    def state_dict(self) -> SamplerState:
        """The next index to be drawn: `epoch` and `position` in this shard's order, with
        the order's `seed`, `size`, `shuffle`, `num_replicas`, `rank` and `remainder`."""
        if self._live is not None and self._live[1] < self.shard_size:
            epoch, position = self._live
        else:
            epoch, position = self._next
        return self._state(epoch, position)

    def _state(self, epoch: int, position: int) -> SamplerState:
        return {
            "version": _STATE_VERSION,
            "epoch": int(epoch),
            "position": int(position),
            "seed": self.seed,
            "size": self.size,
            "shuffle": self.shuffle,
            "num_replicas": self.num_replicas,
            "rank": self.rank,
            "remainder": self.remainder,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """The next pass continues at `state`'s epoch and position (a position at the
        end of the shard means the next epoch's start). Refuses a state of another
        order or shard, naming what differs."""
        if not isinstance(state, dict) or state.get("version") != _STATE_VERSION:
            raise ValueError(f"sampler state: not a state saved by EpochSampler (version {_STATE_VERSION}): {state!r}")
        mine = cast(Dict[str, Any], self._state(0, 0))
        differ = [
            f"{k} {state.get(k)!r} (this sampler: {mine[k]!r})"
            for k in ("seed", "size", "shuffle", "num_replicas", "rank", "remainder")
            if state.get(k) != mine[k]
        ]
        if differ:
            raise ValueError(
                "sampler state: saved for another order or shard: " + ", ".join(differ)
                + "; resume with the same dataset, seed, shuffle, remainder and number of processes (each rank its own state)"
            )
        epoch, position = _check_u64("epoch", state["epoch"]), int(state["position"])
        if not 0 <= position <= self.shard_size:
            raise ValueError(f"sampler state: position {position} outside the shard's {self.shard_size} indices")
        self._next = (epoch + 1, 0) if position == self.shard_size else (epoch, position)
        self._live = None
        self._claimed = None


class _Pass:
    """Where one pass of an `EpochLoader` stands: its epoch, start and batches handed out."""

    def __init__(self, epoch: int, start: int) -> None:
        self.epoch, self.start, self.batches, self.finished = epoch, start, 0, False


class _PassIterator:
    """One pass of an `EpochLoader`: the DataLoader's iterator, counting the batches
    handed out (in `pass_`, which the loader keeps; the loader does not keep this
    iterator, so dropping it shuts the workers down as torch's would)."""

    def __init__(self, inner: Iterator[Any], pass_: _Pass) -> None:
        self.inner, self.pass_ = inner, pass_

    def __iter__(self) -> _PassIterator:
        return self

    def __len__(self) -> int:
        return len(self.inner)  # type: ignore[arg-type]  # torch's iterator has a length

    def __next__(self) -> Any:
        try:
            batch = next(self.inner)
        except StopIteration:
            self.pass_.finished = True
            raise
        self.pass_.batches += 1
        return batch


def _make_loader_class() -> Any:
    import torch

    class EpochLoader(torch.utils.data.DataLoader):  # type: ignore[type-arg]
        """A DataLoader over an `EpochSampler` (what `ARKitFaceDataset.loader` returns).

        - `set_epoch(e)`: the next pass is epoch `e` (optional: passes advance by one).
        - `state_dict()`: the position of the batches handed out so far (epoch, position
          in this rank's shard, the order's seed and shard): save it with the
          checkpoint. `load_state_dict(state)` on a new loader (any `num_workers`, same
          dataset, batch size, seed and shard): its next pass yields the remaining
          batches of that epoch, the same as the uninterrupted run's, then the
          following epochs. The names are torchdata's `StatefulDataLoader` protocol, which
          Lightning uses.
        """

        # Annotations only: what this class holds (torch's DataLoader declares wider types).
        sampler: EpochSampler
        batch_size: int
        _pass: Optional[_Pass]

        def __iter__(self) -> _PassIterator:  # type: ignore[override]
            sampler: EpochSampler = self.sampler
            epoch, start = sampler._claim()
            sampler._claimed = (epoch, start)
            try:
                inner = super().__iter__()
            except BaseException:
                sampler._claimed = None
                raise
            self._pass = _Pass(epoch, start)
            return _PassIterator(inner, self._pass)

        def set_epoch(self, epoch: int) -> None:
            """The next pass is epoch `epoch`, from its start."""
            self.sampler.set_epoch(epoch)

        def state_dict(self) -> LoaderState:
            """Where the data stands: the next batch to hand out (see the class)."""
            sampler: EpochSampler = self.sampler
            p: Optional[_Pass] = getattr(self, "_pass", None)
            position = None if p is None else min(p.start + p.batches * self.batch_size, sampler.shard_size)
            if p is not None and not p.finished and position is not None and position < sampler.shard_size:
                state = cast(LoaderState, sampler._state(p.epoch, position))
            else:
                state = cast(LoaderState, sampler._state(*sampler._next))
            state["batch_size"] = self.batch_size
            return state

        def load_state_dict(self, state: Mapping[str, Any]) -> None:
            """The next pass continues where `state` (from `state_dict`) stood."""
            saved = state.get("batch_size") if isinstance(state, dict) else None
            if saved != self.batch_size:
                raise ValueError(
                    f"loader state: saved with batch_size {saved!r}, this loader's is {self.batch_size}; "
                    "resume with the same batch size"
                )
            self.sampler.load_state_dict({k: v for k, v in state.items() if k != "batch_size"})
            self._pass = None

    EpochLoader.__qualname__ = "EpochLoader"
    EpochLoader.__module__ = __name__
    return EpochLoader


_LOADER_CLASS: Any = None


def loader_class() -> Any:
    """The `EpochLoader` class (made on first use, so that importing this module does
    not import torch)."""
    global _LOADER_CLASS
    if _LOADER_CLASS is None:
        _LOADER_CLASS = _make_loader_class()
    return _LOADER_CLASS


if TYPE_CHECKING:
    _BatchT = TypeVar("_BatchT", default=Batch)

    class EpochLoader(DataLoader[Any], Generic[_BatchT]):
        """What type checkers see of `EpochLoader` (made on first use: `loader_class`)."""

        sampler: EpochSampler
        batch_size: int

        def __iter__(self) -> Iterator[_BatchT]: ...  # type: ignore[override]
        def set_epoch(self, epoch: int) -> None: ...
        def state_dict(self) -> LoaderState: ...
        def load_state_dict(self, state: Mapping[str, Any]) -> None: ...

else:

    def __getattr__(name: str) -> Any:
        if name == "EpochLoader":
            return loader_class()
        raise AttributeError(name)


def _check_u64(name: str, value: Any) -> int:
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: {value!r}: expected an integer in [0, 2^64)") from None
    if v != value or not 0 <= v < 1 << 64:
        raise ValueError(f"{name}: {value!r}: expected an integer in [0, 2^64)")
    return v


def _position(index: Any, n: int) -> int:
    """A sample position from a Python index (negative counts from the end)."""
    if not isinstance(index, (int, np.integer)) or isinstance(index, bool):
        raise TypeError(f"index {index!r}: expected an integer")
    i = int(index)
    if not -n <= i < n:
        raise IndexError(f"index {i} out of range for {n} samples")
    return i + n if i < 0 else i

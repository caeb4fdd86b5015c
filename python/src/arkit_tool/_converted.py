"""A dataset written by `arkit-tool convert`, read as it is: `ConvertedDataset` (its
manifest, samples, splits and samples table; `open_dataset`) and `read_image` (an image
decoded as the loader decodes it)."""

from __future__ import annotations

import json
import os
from typing import Any, Dict, List, Mapping, Optional, Union, cast

import numpy as np
import numpy.typing as npt

from . import _native
from ._native import DataError
from .sampling import _position
from .types import Key, PathLike, SampleRow


class ConvertedDataset:
    """A dataset written by `arkit-tool convert` (the folder holding `dataset.json`)."""

    def __init__(
        self,
        path: PathLike,
        cache_dir: Optional[PathLike] = None,
        storage_options: Optional[Mapping[str, str]] = None,
    ) -> None:
        self.path = os.fspath(path)
        options = None if storage_options is None else {str(k): str(v) for k, v in storage_options.items()}
        self._native = _native.Dataset(self.path, None if cache_dir is None else os.fspath(cache_dir), options)
        self._keys = self._native.keys()
        self._index: Optional[Dict[Key, int]] = None

    def __len__(self) -> int:
        return len(self._keys)

    def __repr__(self) -> str:
        return f"ConvertedDataset({self.path!r}, {len(self)} samples, splits {self.splits})"

    @property
    def manifest(self) -> Dict[str, Any]:
        """The conversion's manifest (`dataset.json`)."""
        manifest: Dict[str, Any] = json.loads(self._native.manifest_json())
        return manifest

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
            return self._index[cast(Key, tuple(str(x) for x in key))]
        except KeyError:
            raise DataError(f"{self.path}: no sample {tuple(key)}") from None

    def sample(self, which: Union[int, np.integer[Any], Key]) -> SampleRow:
        """One sample's row: verts (1220x3), R_t (4x4), image path and size, keys, pose."""
        index = _position(which, len(self)) if isinstance(which, (int, np.integer)) else self.index_of(which)
        return self._native.sample(index)

    @property
    def shard_files(self) -> List[str]:
        """The samples tables (Parquet), in order."""
        return self._native.shard_files()

    @property
    def samples(self) -> Any:
        """The samples table: a polars DataFrame when polars is installed, else a pyarrow
        Table (one of the two is needed)."""
        try:
            import polars as pl

            return pl.concat([pl.read_parquet(f) for f in self.shard_files])
        except ImportError:
            pass
        try:
            import pyarrow as pa  # type: ignore[import-untyped,import-not-found,unused-ignore]
            import pyarrow.parquet as pq  # type: ignore[import-untyped,import-not-found,unused-ignore]
        except ImportError:
            raise ImportError(
                "the samples table needs polars or pyarrow: pip install pyarrow"
            ) from None
        return pa.concat_tables([pq.read_table(f) for f in self.shard_files])


def open_dataset(
    path: PathLike,
    cache_dir: Optional[PathLike] = None,
    storage_options: Optional[Mapping[str, str]] = None,
) -> ConvertedDataset:
    """Opens a dataset written by `arkit-tool convert`: its folder, or the URL it was
    published to with `arkit-tool push` (`s3://bucket/prefix`)."""
    return ConvertedDataset(path, cache_dir, storage_options)


def read_image(path: PathLike) -> npt.NDArray[np.uint8]:
    """An image file decoded as the loader decodes it: (H, W, 3) uint8 RGB."""
    return _native.read_image(os.fspath(path))

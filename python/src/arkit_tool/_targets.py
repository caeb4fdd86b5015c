"""One row of `arkit-tool render`'s targets table decoded with plain numpy
(`decode_targets`; the compact layouts are in schemas/targets.json)."""

from __future__ import annotations

from typing import Any, Dict, Mapping, Optional, cast

import numpy as np
import numpy.typing as npt

from ._native import DataError
from .types import Targets

# Largest mask and UV map a targets row may describe (arkit_core::limits).
_MAX_MASK_PIXELS = 1 << 26
_MAX_UV_SIZE = 4096


def _blob(row: Mapping[str, Any], name: str, dtype: str, width: int) -> npt.NDArray[Any]:
    data = row.get(name)
    if data is None:
        raise DataError(f"targets: column '{name}' is null or missing")
    size = np.dtype(dtype).itemsize * width
    if len(data) % size:
        raise DataError(f"targets: column '{name}': {len(data)} bytes, not whole {size}-byte elements")
    a = np.frombuffer(data, dtype=dtype)
    return a.reshape(-1, width) if width > 1 else a


def _rle(row: Mapping[str, Any], name: str, pixels: int) -> npt.NDArray[np.bool_]:
    runs = _blob(row, name, "<u4", 1)
    if int(runs.sum(dtype=np.uint64)) != pixels:
        raise DataError(f"targets: column '{name}': runs cover {int(runs.sum(dtype=np.uint64))} pixels, expected {pixels}")
    return np.repeat(np.arange(len(runs)) % 2 == 1, runs)


def decode_targets(row: Mapping[str, Any]) -> Targets:
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
    full_mask: Optional[npt.NDArray[np.bool_]] = None
    if full:
        w, h = row.get("image_width"), row.get("image_height")
        if not isinstance(w, int) or not isinstance(h, int) or not 0 < w * h <= _MAX_MASK_PIXELS:
            raise DataError(f"targets: columns 'image_width', 'image_height': {w!r} x {h!r}")
        full_mask = _rle(row, "full_mask_rle", w * h).reshape(h, w)
    out: Dict[str, Any] = {k: v for k, v in row.items() if not isinstance(v, (bytes, bytearray))}
    out.update(mask=mask, corr_vertices=ids, corr_weights=weights, points=points,
               uv_map=uv_map, full_mask=full_mask)
    return cast(Targets, out)

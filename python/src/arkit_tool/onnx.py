"""PerspNet exported by `arkit-tool export-onnx`, run with onnxruntime (no torch).

`arkit-tool export-onnx --model DIR --output FOLDER` writes `dense.onnx`,
`points.onnx` and `onnx.json` (docs/onnx.md). `OnnxPerspNet(FOLDER)` runs a batch of
normalised crops through the three steps `predict --model` takes:

1. `dense.onnx`: crops -> segmentation logits, UV map, image and UV features;
2. the point choice: the mask (logit 1 >= logit 0), and M of its pixels picked with a
   seed by the same sampler as the Rust side (`_native.choose_points`);
3. `points.onnx`: features and chosen pixels -> assignment, `M X`, vertices.

With the same crop and seed, the chosen pixels are `predict`'s and the outputs equal
`predict --dump`'s to the tolerance stated in docs/onnx.md. The points and vertices are
returned in canonical metres (the graphs' outputs divided by `uv_scale`, 9) ready for
PnP (`arkit_tool._native.solve_pnp_ransac`), and as the graphs give them.

Needs `onnxruntime` (imported when an `OnnxPerspNet` is made) and numpy.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

from . import _native

__all__ = ["OnnxPerspNet", "OnnxPrediction"]

_Path = Union[str, "os.PathLike[str]"]
_Seeds = Union[int, Sequence[int]]


@dataclass
class OnnxPrediction:
    """What `OnnxPerspNet.predict` returns for a batch of B crops (S x S, M points, V
    vertices). Arrays are numpy, float32 unless stated."""

    mask: npt.NDArray[np.bool_]
    """(B, S, S): the predicted face mask, `seg_logits[:, 1] >= seg_logits[:, 0]`."""
    choose: npt.NDArray[np.int64]
    """(B, M): the chosen pixels, flat indices `y * S + x` into the crop."""
    points: npt.NDArray[np.float32]
    """(B, M, 3): the canonical point each chosen pixel shows (`M X / 9`), metres."""
    vertices: npt.NDArray[np.float32]
    """(B, V, 3): the predicted canonical vertices (`X / 9`), metres."""
    seg_logits: npt.NDArray[np.float32]
    """(B, 2, S, S): dense.onnx's segmentation logits (class 1 = face)."""
    uv_map: npt.NDArray[np.float32]
    """(B, 3, S, S): dense.onnx's UV map (tanh), 9 x canonical metres."""
    assignment: npt.NDArray[np.float32]
    """(B, M, V): points.onnx's soft assignment (rows sum to 1)."""
    points_raw: npt.NDArray[np.float32]
    """(B, M, 3): points.onnx's `points` (`M X`), 9 x canonical metres."""
    vertices_raw: npt.NDArray[np.float32]
    """(B, V, 3): points.onnx's `vertices` (X), 9 x canonical metres."""


class OnnxPerspNet:
    """The two graphs of an `export-onnx` folder in onnxruntime sessions.

    `folder`: where `export-onnx` wrote `dense.onnx`, `points.onnx` and `onnx.json`.
    `providers`: onnxruntime execution providers (default: `["CPUExecutionProvider"]`).
    `session_options`: an `onnxruntime.SessionOptions` for both sessions (e.g. to set
    the thread count).

    Attributes read from `onnx.json`: `manifest` (all of it), `input_size` (S),
    `points` (M), `vertices` (V), `mean` and `std` (the ImageNet normalisation),
    `uv_scale` (9).
    """

    def __init__(
        self,
        folder: _Path,
        providers: Optional[Sequence[str]] = None,
        session_options: Optional[Any] = None,
    ) -> None:
        try:
            import onnxruntime as ort  # type: ignore[import-untyped,import-not-found,unused-ignore]
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise ImportError(
                "arkit_tool.onnx needs onnxruntime: pip install onnxruntime"
            ) from e
        self.folder = os.fspath(folder)
        with open(os.path.join(self.folder, "onnx.json"), encoding="utf-8") as f:
            self.manifest: Dict[str, Any] = json.load(f)
        m = self.manifest
        self.input_size: int = int(m["input_size"])
        self.points: int = int(m["points"])
        self.vertices: int = int(m["vertices"])
        self.mean = np.asarray(m["normalisation_mean"], dtype=np.float32)
        self.std = np.asarray(m["normalisation_std"], dtype=np.float32)
        self.uv_scale: float = float(m["uv_scale"])
        chosen: List[str] = list(providers) if providers is not None else ["CPUExecutionProvider"]
        self.dense_session = ort.InferenceSession(
            os.path.join(self.folder, m["dense"]["file"]), sess_options=session_options, providers=chosen
        )
        self.points_session = ort.InferenceSession(
            os.path.join(self.folder, m["points_graph"]["file"]), sess_options=session_options, providers=chosen
        )

    def normalise(self, crops: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """uint8 RGB crops `(B, S, S, 3)` (or one `(S, S, 3)`) as the network's input
        `(B, 3, S, S)`: `(rgb / 255 - mean) / std`, channels first."""
        a = np.asarray(crops)
        if a.ndim == 3:
            a = a[None]
        s = self.input_size
        if a.ndim != 4 or a.shape[1:] != (s, s, 3):
            raise ValueError(f"crops must be (B, {s}, {s}, 3) RGB, got {a.shape}")
        x = (a.astype(np.float32) / np.float32(255.0) - self.mean) / self.std
        return np.ascontiguousarray(x.transpose(0, 3, 1, 2), dtype=np.float32)

    def _image(self, image: npt.ArrayLike) -> npt.NDArray[np.float32]:
        x = np.asarray(image, dtype=np.float32)
        if x.ndim == 3:
            x = x[None]
        s = self.input_size
        if x.ndim != 4 or x.shape[1:] != (3, s, s):
            raise ValueError(f"image must be (B, 3, {s}, {s}) normalised crops, got {x.shape}")
        return np.ascontiguousarray(x)

    def dense(self, image: npt.ArrayLike) -> Dict[str, npt.NDArray[np.float32]]:
        """dense.onnx on normalised crops `(B, 3, S, S)`: `seg_logits`, `uv_map`,
        `image_features`, `uv_features`."""
        names = [o.name for o in self.dense_session.get_outputs()]
        outs = self.dense_session.run(names, {"image": self._image(image)})
        return dict(zip(names, outs))

    def choose(self, seg_logits: npt.ArrayLike, seeds: _Seeds = 0) -> npt.NDArray[np.int64]:
        """The pixels `predict` reads for each crop, `(B, M)` int64: from the mask
        `seg_logits[:, 1] >= seg_logits[:, 0]` (every pixel when it is empty), M picked
        with the crop's seed (`seeds`: one int for all crops, or one per crop; `predict`
        seeds sample i of shard k with `seed ^ ((k << 32) | i)`)."""
        logits = np.asarray(seg_logits)
        if logits.ndim != 4 or logits.shape[1] != 2:
            raise ValueError(f"seg_logits must be (B, 2, S, S), got {logits.shape}")
        b = logits.shape[0]
        per = [int(seeds)] * b if isinstance(seeds, (int, np.integer)) else [int(s) for s in seeds]
        if len(per) != b:
            raise ValueError(f"{len(per)} seeds for {b} crops")
        mask = logits[:, 1] >= logits[:, 0]
        return np.stack([_native.choose_points(mask[i], self.points, per[i]) for i in range(b)])

    def run_points(
        self, dense: Dict[str, npt.NDArray[np.float32]], choose: npt.ArrayLike
    ) -> Dict[str, npt.NDArray[np.float32]]:
        """points.onnx on dense.onnx's outputs and the chosen pixels `(B, M)`:
        `assignment`, `points`, `vertices` (the last two in 9 x canonical metres)."""
        c = np.ascontiguousarray(np.asarray(choose, dtype=np.int64))
        if c.ndim == 1:
            c = c[None]
        s = self.input_size
        if c.shape != (dense["uv_map"].shape[0], self.points):
            raise ValueError(f"choose must be (B, {self.points}), got {c.shape}")
        if c.size and (c.min() < 0 or c.max() >= s * s):
            raise ValueError(f"choose holds pixels outside the {s} x {s} crop")
        feeds: Dict[str, npt.NDArray[Any]] = {k: dense[k] for k in ("image_features", "uv_features", "uv_map")}
        feeds["choose"] = c
        names = [o.name for o in self.points_session.get_outputs()]
        return dict(zip(names, self.points_session.run(names, feeds)))

    def predict(
        self, image: npt.ArrayLike, seeds: _Seeds = 0, choose: Optional[npt.ArrayLike] = None
    ) -> OnnxPrediction:
        """The whole network on normalised crops `(B, 3, S, S)` (see `normalise`):
        dense.onnx, the point choice (`choose` given: those pixels instead), points.onnx."""
        d = self.dense(image)
        logits = d["seg_logits"]
        mask = logits[:, 1] >= logits[:, 0]
        c = self.choose(logits, seeds) if choose is None else np.asarray(choose, dtype=np.int64).reshape(
            logits.shape[0], -1
        )
        p = self.run_points(d, c)
        scale = np.float32(self.uv_scale)
        return OnnxPrediction(
            mask=mask,
            choose=c,
            points=p["points"] / scale,
            vertices=p["vertices"] / scale,
            seg_logits=logits,
            uv_map=d["uv_map"],
            assignment=p["assignment"],
            points_raw=p["points"],
            vertices_raw=p["vertices"],
        )

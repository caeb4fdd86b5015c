"""See a converted dataset in Rerun: images, the camera, the face mesh at its pose, the
landmarks, the targets and a model's predictions, one sample after another on a timeline.

    python -m arkit_tool.view DATASET [selection] --output samples.rrd   # a file
    python -m arkit_tool.view DATASET [selection] --spawn                # the viewer

From Python: `arkit_tool.view.record(dataset, ..., path="samples.rrd")`. Needs the
optional extra `pip install "arkit-tool[view]"` (rerun-sdk, which ships the viewer).

What is logged per sample (entity paths; the `sample` timeline counts the selection, the
`frame` timeline is the image id where it is a number, so a BIWI sequence or an ARKit
capture plays in order):

- `world`: the release's camera frame, OpenGL (x right, y up, the camera looking down -z:
  `ViewCoordinates.RUB`). `world/camera`: a pinhole with the release's intrinsics for the
  sample's image size (`fx = P[0][0] W/2`, `fy = P[1][1] H/2`, principal point at the
  centre; docs/conventions.md); `world/camera/image` the image,
  `world/camera/image/landmarks` the 68 landmarks (pixels, pixel centres at +0.5 as
  everywhere in arkit-tool), `world/camera/image/crop_box` the targets' crop box.
- `world/mesh/truth`: the face mesh at the ground-truth pose in the camera frame
  (`[x y z 1] @ R_t`); `world/mesh/predicted`: at the predicted pose (the predicted
  vertices when the predictions carry them); `world/landmarks/truth`: the 68 landmark
  vertices.
- with `render`'s targets: `crop/image` (the crop, resampled here for display),
  `crop/mask`, `crop/correspondences` (a few face pixels) and
  `world/mesh/correspondences` (the canonical points they show, at the true pose, same
  colours), `uv_map` (the UV position map, x y z as red green blue).
- `pose` (text: keys, R_t, Euler angles, translation), `pose/yaw_deg`, `pose/pitch_deg`,
  `pose/roll_deg`, `pose/distance_m` and, with predictions, `errors/rotation_deg`,
  `errors/translation_mm`, `errors/add_mm` (scalars).
- an augmented sample (`<img_id>_aug<k>`, `<img_id>_flip`) whose source is in the dataset
  shows that source beside it: `source/image`, `source/landmarks`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union, cast

import numpy as np

from . import DataError, ConvertedDataset, _native, decode_targets, open_dataset, read_image
from . import _recording
from .types import Key, PathLike, SampleRow, Targets

__all__ = ["record", "intrinsics", "select", "sample_errors", "main"]

INSTALL_HINT = (
    'the viewer needs rerun-sdk: pip install "arkit-tool[view]" (or pip install rerun-sdk)'
)

# The release's projection_matrix.txt (P[0][0] = P[1][1]; arkit_core::conventions::camera).
RELEASE_PROJECTION = (
    1.57443701, 0.0, 0.0, 0.0,
    0.0, 1.57443701, 0.0, 0.0,
    0.0, 0.0, -0.99999976, -1.0,
    0.0, 0.0, -0.001, 0.0,
)

_AUGMENTED = re.compile(r"^(?P<source>.+)_(aug\d+|flip)$")


def _rerun() -> Any:
    return _recording.rerun_module(INSTALL_HINT)


def projection_of(dataset: ConvertedDataset) -> np.ndarray:
    """The row-vector projection matrix (4 x 4) the dataset was converted with
    (`conversion.json`), else the release's."""
    path = os.path.join(dataset.path, "conversion.json")
    values: Sequence[float] = RELEASE_PROJECTION
    if os.path.isfile(path):
        try:
            with open(path) as f:
                recorded = json.load(f).get("projection")
        except (OSError, ValueError) as e:
            raise DataError(f"{path}: {e}") from None
        if recorded is not None:
            if len(recorded) != 16:
                raise DataError(f"{path}: 'projection' has {len(recorded)} numbers, expected 16")
            values = recorded
    return np.asarray(values, dtype=np.float64).reshape(4, 4)


def intrinsics(projection: np.ndarray, width: int, height: int) -> np.ndarray:
    """The pinhole matrix K (3 x 3, OpenCV's form, pixels) equivalent to the release's
    projection for a `width x height` image: `fx = P[0][0] W/2`, `fy = P[1][1] H/2`,
    `cx = W/2 (1 - P[2][0])`, `cy = H/2 (1 + P[2][1])`, for points in the camera frame
    turned to x right, y down, z forward (docs/conventions.md)."""
    p = np.asarray(projection, dtype=np.float64).reshape(4, 4)
    w2, h2 = width / 2.0, height / 2.0
    return np.array(
        [[p[0, 0] * w2, 0.0, w2 * (1.0 - p[2, 0])], [0.0, p[1, 1] * h2, h2 * (1.0 + p[2, 1])], [0.0, 0.0, 1.0]]
    )


def to_camera(verts: np.ndarray, r_t: np.ndarray) -> np.ndarray:
    """Canonical points (N, 3) in the camera frame (OpenGL): `[x y z 1] @ R_t`."""
    v = np.asarray(verts, dtype=np.float64)
    m = np.asarray(r_t, dtype=np.float64).reshape(4, 4)
    return v @ m[:3, :3] + m[3, :3]


def sample_errors(verts: np.ndarray, truth: np.ndarray, predicted: Optional[np.ndarray]) -> Dict[str, float]:
    """Per-sample errors of a predicted pose, as `eval` defines them: geodesic rotation
    error (degrees), translation distance (mm), ADD over the true vertices (mm). A
    missing prediction is scored as the identity pose, as `eval` does."""
    gt = np.asarray(truth, dtype=np.float64).reshape(4, 4)
    pr = np.eye(4) if predicted is None else np.asarray(predicted, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(pr)) or pr[3, 2] > 0 or pr[3, 2] < -100:
        pr = np.eye(4)
    r = gt[:3, :3].T @ pr[:3, :3]
    cos = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    add = np.linalg.norm(to_camera(verts, gt) - to_camera(verts, pr), axis=1).mean()
    return {
        "rotation_deg": math.degrees(math.acos(cos)),
        "translation_mm": float(np.linalg.norm(gt[3, :3] - pr[3, :3]) * 1000.0),
        "add_mm": float(add * 1000.0),
    }


def _read_table(path: str, columns: Optional[List[str]] = None) -> Any:
    import pyarrow.parquet as pq  # type: ignore[import-untyped,import-not-found,unused-ignore]

    try:
        return pq.read_table(path, columns=columns)
    except (OSError, ValueError) as e:
        raise DataError(f"{path}: {e}") from None


def read_predictions(path: PathLike) -> Dict[Key, Dict[str, Any]]:
    """A predictions file (Parquet, schemas/predictions.json) as `{key: {"R_t": 4x4 or
    None, "verts": (N, 3) or None}}`."""
    path = os.fspath(path)
    if not path.endswith(".parquet"):
        raise DataError(f"{path}: the viewer reads Parquet predictions (schemas/predictions.json)")
    table = _read_table(path)
    names = set(table.column_names)
    for c in ("subject_id", "facial_action", "img_id", "R_t"):
        if c not in names:
            raise DataError(f"{path}: no column '{c}' (schemas/predictions.json)")
    cols = {c: table.column(c).to_pylist() for c in ("subject_id", "facial_action", "img_id", "R_t")}
    verts = table.column("verts").to_pylist() if "verts" in names else [None] * table.num_rows
    out: Dict[Key, Dict[str, Any]] = {}
    for i in range(table.num_rows):
        key = (str(cols["subject_id"][i]), str(cols["facial_action"][i]), str(cols["img_id"][i]))
        rt = cols["R_t"][i]
        if rt is not None and len(rt) != 16:
            raise DataError(f"{path}: row {i} {key}: R_t has {len(rt)} numbers, expected 16")
        v = verts[i]
        if v is not None and len(v) % 3:
            raise DataError(f"{path}: row {i} {key}: verts has {len(v)} numbers, not whole points")
        out[key] = {
            "R_t": None if rt is None else np.asarray(rt, dtype=np.float64).reshape(4, 4),
            "verts": None if v is None else np.asarray(v, dtype=np.float32).reshape(-1, 3),
        }
    return out


def _pose_columns(dataset: ConvertedDataset) -> Dict[str, np.ndarray]:
    cols = ["yaw_deg", "pitch_deg", "roll_deg", "tz_m"]
    parts = [_read_table(f, cols) for f in dataset.shard_files]
    return {c: np.concatenate([p.column(c).to_numpy() for p in parts]) if parts else np.zeros(0) for c in cols}


def _range(name: str, r: Optional[Sequence[float]]) -> Optional[Tuple[float, float]]:
    if r is None:
        return None
    if len(r) != 2 or not r[0] <= r[1]:
        raise DataError(f"{name}: {list(r)!r}: expected two numbers lo <= hi")
    return float(r[0]), float(r[1])


def select(
    dataset: ConvertedDataset,
    *,
    split: Optional[str] = None,
    subjects: Optional[Iterable[str]] = None,
    actions: Optional[Iterable[str]] = None,
    yaw_range: Optional[Sequence[float]] = None,
    pitch_range: Optional[Sequence[float]] = None,
    roll_range: Optional[Sequence[float]] = None,
    keys: Optional[Iterable[Key]] = None,
) -> List[int]:
    """Positions of the samples that pass every filter given (ranges in degrees,
    inclusive), in dataset order (subject, action, image id: sequences in order)."""
    want_subjects = None if subjects is None else {str(s) for s in subjects}
    want_actions = None if actions is None else {str(a) for a in actions}
    want_keys = None if keys is None else {tuple(str(x) for x in k) for k in keys}
    ranges = [("yaw_deg", _range("yaw_range", yaw_range)), ("pitch_deg", _range("pitch_range", pitch_range)),
              ("roll_deg", _range("roll_range", roll_range))]
    limits = [(c, r) for c, r in ranges if r is not None]
    pose = _pose_columns(dataset) if limits else {}
    out = []
    for i, k in enumerate(dataset._keys):
        if split is not None and k[3] != split:
            continue
        if want_subjects is not None and k[0] not in want_subjects:
            continue
        if want_actions is not None and k[1] not in want_actions:
            continue
        if want_keys is not None and tuple(k[:3]) not in want_keys:
            continue
        if any(not lo <= pose[c][i] <= hi for c, (lo, hi) in limits):
            continue
        out.append(i)
    return out


def _targets_rows(dataset_dir: str, keys: Iterable[Key]) -> Dict[Key, Dict[str, Any]]:
    """The rows of `render`'s targets tables (`DIR/targets/*.parquet`) for `keys`."""
    folder = os.path.join(dataset_dir, "targets")
    wanted = set(keys)
    out: Dict[Key, Dict[str, Any]] = {}
    if not os.path.isdir(folder) or not wanted:
        return out
    for name in sorted(os.listdir(folder)):
        if not name.endswith(".parquet"):
            continue
        path = os.path.join(folder, name)
        ids = _read_table(path, ["subject_id", "facial_action", "img_id"])
        hits = [i for i, k in enumerate(zip(*(ids.column(c).to_pylist() for c in ids.column_names))) if k in wanted]
        if not hits:
            continue
        table = _read_table(path)
        for row in (table.slice(i, 1).to_pylist()[0] for i in hits):
            out[(row["subject_id"], row["facial_action"], row["img_id"])] = row
    return out


def _bilinear_crop(image: np.ndarray, t: Targets) -> np.ndarray:
    """The targets' crop of `image` (for display: bilinear, black outside)."""
    s = int(t["crop_size"])
    side_x, side_y = float(t["crop_side"]), float(t["crop_side_y"] or t["crop_side"])
    offset = 0.5 if t.get("crop_sampling", "centre") == "centre" else 0.0
    grid = np.arange(s) + offset
    # Crop pixel centre -> image coordinates -> continuous pixel index (centres at +0.5).
    x = float(t["crop_x0"]) + grid * side_x / s - 0.5
    y = float(t["crop_y0"]) + grid * side_y / s - 0.5
    h, w = image.shape[:2]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[None, :, None], (y - y0)[:, None, None]
    pad = np.zeros((h + 2, w + 2, 3), dtype=np.float32)
    pad[1:-1, 1:-1] = image
    xi, yi = np.clip(x0 + 1, 0, w + 1), np.clip(y0 + 1, 0, h + 1)
    xj, yj = np.clip(x0 + 2, 0, w + 1), np.clip(y0 + 2, 0, h + 1)
    a, b = pad[yi][:, xi], pad[yi][:, xj]
    c, d = pad[yj][:, xi], pad[yj][:, xj]
    out = (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy
    crop: np.ndarray = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    return crop


def _position_colours(points: np.ndarray, verts: np.ndarray) -> np.ndarray:
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    colours: np.ndarray = (np.clip((points - lo) / span, 0, 1) * 235 + 20).astype(np.uint8)
    return colours


def _pose_text(
    key: Key, split: str, sample: SampleRow, prediction: Optional[Dict[str, Any]], errors: Optional[Dict[str, float]]
) -> str:
    rt = np.asarray(sample["R_t"]).reshape(4, 4)
    lines = [
        f"subject {key[0]}, action {key[1]}, image {key[2]} ({split})",
        f"yaw {sample['yaw_deg']:.2f} deg, pitch {sample['pitch_deg']:.2f} deg, roll {sample['roll_deg']:.2f} deg",
        "translation (m): " + ", ".join(f"{v:.4f}" for v in rt[3, :3]),
        "R_t (row-vector, [x y z 1] @ R_t):",
    ]
    lines += ["  " + " ".join(f"{v:9.5f}" for v in row) for row in rt]
    if prediction is not None:
        p = prediction.get("R_t")
        if p is None:
            lines.append("prediction: none (a PnP failure; scored as the identity pose)")
        else:
            lines.append("predicted R_t:")
            lines += ["  " + " ".join(f"{v:9.5f}" for v in row) for row in p]
    if errors:
        lines.append(", ".join(f"{k} {v:.2f}" for k, v in errors.items()))
    return "\n".join(lines)


def _frame_number(img_id: str) -> Optional[int]:
    return int(img_id) if img_id.isdigit() else None


def _vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (points[triangles[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    out = np.zeros_like(points)
    for k in range(3):
        np.add.at(out, triangles[:, k], n)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    normals: np.ndarray = out / np.maximum(norm, 1e-12)
    return normals


def record(
    dataset: Union[PathLike, ConvertedDataset],
    *,
    split: Optional[str] = None,
    subjects: Optional[Iterable[str]] = None,
    actions: Optional[Iterable[str]] = None,
    yaw_range: Optional[Sequence[float]] = None,
    pitch_range: Optional[Sequence[float]] = None,
    roll_range: Optional[Sequence[float]] = None,
    keys: Optional[Iterable[Key]] = None,
    predictions: Optional[PathLike] = None,
    worst: Optional[int] = None,
    limit: Optional[int] = None,
    correspondences: int = 8,
    resources: Optional[PathLike] = None,
    path: Optional[PathLike] = None,
    spawn: bool = False,
    recording: Any = None,
) -> Dict[str, Any]:
    """Logs a selection of `dataset`'s samples to Rerun (see the module's docs for what
    and where). Selection: the filters of `select`; with `predictions` (a Parquet
    predictions file) and `worst=N`, the N samples of the selection with the largest
    rotation error (as `eval` scores them); `limit` keeps the first N. Output: `path` (an
    `.rrd` file, written to a temporary name and renamed when complete), `spawn=True`
    (start the viewer), or `recording` (a `rerun.RecordingStream` of your own).
    Returns `{"samples": [keys in logged order], "path": ..., "skipped": [...]}`."""
    rr = _rerun()
    ds = dataset if isinstance(dataset, ConvertedDataset) else open_dataset(dataset)
    if worst is not None and predictions is None:
        raise DataError("worst: ranks by prediction error; give predictions too")
    if (path is None) + (not spawn) + (recording is None) != 2:
        raise DataError("give exactly one of path, spawn=True or recording")
    chosen = select(ds, split=split, subjects=subjects, actions=actions, yaw_range=yaw_range,
                    pitch_range=pitch_range, roll_range=roll_range, keys=keys)
    preds = read_predictions(predictions) if predictions is not None else None
    topo = _native.topology(ds.path, None if resources is None else os.fspath(resources))
    triangles = np.asarray(topo["triangles"], dtype=np.uint32)
    landmark_ids = np.asarray(topo["landmarks"], dtype=np.int64)
    projection = projection_of(ds)

    samples: Dict[int, SampleRow] = {}
    errors: Dict[int, Dict[str, float]] = {}

    def sample(i: int) -> SampleRow:
        if i not in samples:
            samples[i] = ds.sample(i)
        return samples[i]

    if preds is not None:
        for i in chosen:
            s = sample(i)
            p = preds.get(ds._keys[i][:3])
            errors[i] = sample_errors(s["verts"], s["R_t"], None if p is None else p["R_t"])
        if worst is not None:
            # Largest rotation error first; ties in dataset order.
            chosen = sorted(chosen, key=lambda i: -errors[i]["rotation_deg"])[: max(int(worst), 0)]
    if limit is not None:
        chosen = chosen[: max(int(limit), 0)]
    chosen_keys = [ds._keys[i][:3] for i in chosen]
    targets = _targets_rows(ds.path, chosen_keys)
    by_key = {k[:3]: i for i, k in enumerate(ds._keys)}

    rec, tmp = _recording.open_recording(rr, "arkit_tool", path, spawn, recording)

    rec.log("world", rr.ViewCoordinates.RUB, static=True)
    rec.log("crop/mask", rr.AnnotationContext([(0, "background", (0, 0, 0, 0)), (1, "face", (40, 200, 90, 140))]),
            static=True)
    logged: List[Key] = []
    skipped: List[str] = []
    rng = np.random.default_rng(0)
    for step, i in enumerate(chosen):
        key = chosen_keys[step]
        split_name = ds._keys[i][3]
        s = sample(i)
        try:
            rec.set_time("sample", sequence=step)
            frame = _frame_number(key[2])
            if frame is not None:
                rec.set_time("frame", sequence=frame)
            w, h = int(s["image_width"]), int(s["image_height"])
            verts = np.asarray(s["verts"], dtype=np.float64)
            rt = np.asarray(s["R_t"], dtype=np.float64).reshape(4, 4)
            k_matrix = intrinsics(projection, w, h)
            rec.log("world/camera", rr.Pinhole(image_from_camera=k_matrix, resolution=[w, h],
                                               camera_xyz=rr.ViewCoordinates.RUB, image_plane_distance=0.2))
            image = None
            image_path = s["image_path"]  # None when the image is embedded
            if image_path:
                image = read_image(image_path)
                rec.log("world/camera/image", rr.Image(image))
            lm = np.asarray(s["landmarks_2d"], dtype=np.float64)
            rec.log("world/camera/image/landmarks", rr.Points2D(lm, colors=(255, 220, 0), radii=1.5))
            cam = to_camera(verts, rt)
            if len(verts) == topo["vertex_count"]:
                rec.log("world/mesh/truth", rr.Mesh3D(vertex_positions=cam, triangle_indices=triangles,
                                                      vertex_normals=_vertex_normals(cam, triangles),
                                                      albedo_factor=(60, 220, 110, 255)))
                rec.log("world/landmarks/truth", rr.Points3D(cam[landmark_ids], colors=(255, 220, 0),
                                                             radii=0.0015))
            else:
                # A BIWI head or another mesh of its own: its points.
                rec.log("world/mesh/truth", rr.Points3D(cam, colors=(60, 220, 110), radii=0.001))
            p = None if preds is None else preds.get(key, {"R_t": None, "verts": None})
            if p is not None and p["R_t"] is not None:
                pv = p["verts"] if p["verts"] is not None and len(p["verts"]) == len(verts) else verts
                pcam = to_camera(pv, p["R_t"])
                if len(pv) == topo["vertex_count"]:
                    rec.log("world/mesh/predicted", rr.Mesh3D(vertex_positions=pcam, triangle_indices=triangles,
                                                              vertex_normals=_vertex_normals(pcam, triangles),
                                                              albedo_factor=(230, 70, 60, 255)))
                else:
                    rec.log("world/mesh/predicted", rr.Points3D(pcam, colors=(230, 70, 60), radii=0.001))
            elif p is not None:
                rec.log("world/mesh/predicted", rr.Clear(recursive=False))
            err = errors.get(i)
            rec.log("pose", rr.TextDocument(_pose_text(key, split_name, s, p, err)))
            for name in ("yaw_deg", "pitch_deg", "roll_deg"):
                rec.log(f"pose/{name}", rr.Scalars(float(s[name])))
            rec.log("pose/distance_m", rr.Scalars(float(-rt[3, 2])))
            if err:
                for name, v in err.items():
                    rec.log(f"errors/{name}", rr.Scalars(v))
            t = targets.get(key)
            if t is not None:
                _log_targets(rr, rec, decode_targets(t), image, verts, rt, correspondences, rng)
            m = _AUGMENTED.match(key[2])
            src = None if m is None else by_key.get((key[0], key[1], m.group("source")))
            if src is not None:
                ss = sample(src)
                source_path = ss["image_path"]
                if source_path:
                    rec.log("source/image", rr.Image(read_image(source_path)))
                rec.log("source/landmarks", rr.Points2D(np.asarray(ss["landmarks_2d"]), colors=(255, 220, 0),
                                                        radii=1.5))
            logged.append(key)
        except (DataError, OSError, ValueError) as e:
            # One bad sample is reported and skipped.
            skipped.append(f"{key}: {e}")
            print(f"arkit_tool.view: skipped {key}: {e}", file=sys.stderr)
    out_path = _recording.finish(rec, tmp, path)
    return {"samples": logged, "path": out_path, "skipped": skipped}


def _log_targets(
    rr: Any,
    rec: Any,
    t: Targets,
    image: Optional[np.ndarray],
    verts: np.ndarray,
    rt: np.ndarray,
    count: int,
    rng: np.random.Generator,
) -> None:
    s = int(t["crop_size"])
    if image is not None:
        rec.log("crop/image", rr.Image(_bilinear_crop(image, t)))
        side_y = float(t["crop_side_y"] or t["crop_side"])
        rec.log("world/camera/image/crop_box", rr.Boxes2D(mins=[t["crop_x0"], t["crop_y0"]],
                                                          sizes=[t["crop_side"], side_y], colors=(80, 160, 255)))
    mask = t["mask"]
    rec.log("crop/mask", rr.SegmentationImage(mask.astype(np.uint8)))
    face = np.flatnonzero(mask.reshape(-1))
    if len(face) and count > 0:
        pick = np.sort(rng.choice(len(face), size=min(count, len(face)), replace=False))
        px = face[pick]
        ids = t["corr_vertices"][pick].astype(np.int64)
        wts = t["corr_weights"][pick].astype(np.float64)
        canon = np.einsum("nk,nkc->nc", wts, verts[ids])
        colours = _position_colours(canon, verts)
        labels = [str(k) for k in range(len(px))]
        crop_xy = np.stack([px % s + 0.5, px // s + 0.5], axis=1)
        rec.log("crop/correspondences", rr.Points2D(crop_xy, colors=colours, radii=2.0, labels=labels))
        rec.log("world/mesh/correspondences", rr.Points3D(to_camera(canon, rt), colors=colours, radii=0.002,
                                                          labels=labels))
    uv = np.asarray(t["uv_map"], dtype=np.float32)
    valid = np.all(np.isfinite(uv), axis=2) & np.any(uv != 0, axis=2)
    picture = np.zeros(uv.shape, dtype=np.uint8)
    picture[valid] = _position_colours(uv[valid], verts)
    rec.log("uv_map", rr.Image(picture))


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m arkit_tool.view",
        description="Write a Rerun recording (.rrd) of a converted dataset's samples, or open the viewer: the "
        "image, the release's camera as a pinhole, the face mesh at its true pose (and at the predicted pose), "
        "the 68 landmarks, the crop with its mask, UV position map and a few correspondences (when `render` "
        "wrote targets), the pose and per-sample errors. Needs pip install \"arkit-tool[view]\".",
        epilog="Example, on `arkit-tool demo --quick --output demo`'s folder: python -m arkit_tool.view "
        "demo/dataset --split test --predictions demo/predictions.parquet --worst 8 --spawn",
    )
    parser.add_argument("dataset", help="a folder written by `arkit-tool convert` (with dataset.json)")
    parser.add_argument("--split", help="only this split (train, test, ...)")
    parser.add_argument("--subject", action="append", help="only this subject id (repeat for more)")
    parser.add_argument("--action", action="append", help="only this facial action (repeat for more)")
    for name in ("yaw", "pitch", "roll"):
        parser.add_argument(f"--{name}-range", nargs=2, type=float, metavar=("LO", "HI"),
                            help=f"only samples with {name} in [LO, HI] degrees")
    parser.add_argument("--predictions", help="a predictions file (Parquet): the predicted meshes and errors")
    parser.add_argument("--worst", type=int, metavar="N",
                        help="only the N samples with the largest rotation error (needs --predictions)")
    parser.add_argument("--limit", type=int, metavar="N", help="at most N samples (the first of the selection)")
    parser.add_argument("--correspondences", type=int, default=8, metavar="K",
                        help="face pixels shown with the canonical point they see (default 8)")
    parser.add_argument("--resources", help="the release's resource folder, if the dataset's recorded one moved")
    out = parser.add_mutually_exclusive_group(required=True)
    out.add_argument("--output", metavar="FILE.rrd", help="write a recording file (open it with `rerun FILE.rrd`)")
    out.add_argument("--spawn", action="store_true", help="start the Rerun viewer and stream to it")
    parser.add_argument("--json", action="store_true", help="print what was logged as JSON")
    a = parser.parse_args(argv)
    try:
        result = record(
            a.dataset, split=a.split, subjects=a.subject, actions=a.action, yaw_range=a.yaw_range,
            pitch_range=a.pitch_range, roll_range=a.roll_range, predictions=a.predictions, worst=a.worst,
            limit=a.limit, correspondences=a.correspondences, resources=a.resources, path=a.output,
            spawn=a.spawn,
        )
    except (DataError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(result, indent=1))
    else:
        where = result["path"] or "the viewer"
        print(f"{len(result['samples'])} samples to {where}; {len(result['skipped'])} skipped")
    if not result["samples"]:
        print("error: no sample matched the selection", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

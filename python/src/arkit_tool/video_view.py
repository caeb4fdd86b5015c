"""See `arkit-tool predict --video`'s poses in Rerun, on a frame timeline.

    python -m arkit_tool.video_view POSES.jsonl --video CLIP.mp4 --mesh MESHES/ --output poses.rrd
    python -m arkit_tool.video_view POSES.jsonl --video CLIP.mp4 --spawn     # the viewer

POSES.jsonl is `predict --video ... --output POSES.jsonl`'s rows (one a frame and track);
`--video` the clip they came from (an MP4/MOV, or the folder of numbered frames);
`--mesh` the folder `predict --video --mesh` wrote. From Python:
`arkit_tool.video_view.record("poses.jsonl", video="clip.mp4", path="poses.rrd")`.
Needs the optional extra `pip install "arkit-tool[view]"` (rerun-sdk). docs/video.md.

Two timelines: `frame` (the row's frame index, a sequence) and `video_time` (its
timestamp, seconds). Entities, `K` a track id:

- `world`: the release's camera frame (x right, y up, looking down -z:
  `ViewCoordinates.RUB`). With `--mesh`, `world/camera` is the frame's pinhole (from the
  mesh files' `camera`), and the image is `world/camera/image`; without, `image`.
- the image: the clip as a video asset (`rr.AssetVideo`, decoded by the viewer) with a
  frame reference per frame, or each frame file of a folder (`rr.EncodedImage`).
- `<image>/track-K/box`: the row's box (`Boxes2D`), labelled with the track and its
  angles; `<image>/track-K/landmarks`: the 68 landmarks' pixels (with `--mesh`).
- `world/track-K/head`: the row's pose (`Transform3D` from `R_t`, shown as axes 5 cm
  long); `world/track-K/mesh` and `world/track-K/landmarks`: the mesh files' camera-space
  mesh and landmarks (with `--mesh`).
- `angles/track-K/NAME` and `raw_angles/track-K/NAME`: the row's angles (in the
  convention `predict --angles` wrote, e.g. yaw, pitch, roll) and the raw ones, degrees;
  `inliers/track-K`: the PnP inliers.

A track absent from a frame, or whose PnP failed there, has its entities cleared at
that frame. Rows are read and logged one frame at a time (memory stays flat however
long the clip); the recording is written under a temporary name and renamed when
complete. A malformed line is reported and skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from typing import Any, Dict, Iterator, List, Optional, Sequence, Set, Tuple, cast

import numpy as np

from . import DataError
from . import _recording
from .types import PathLike

__all__ = ["record", "read_rows", "main"]

INSTALL_HINT = (
    'the video viewer needs rerun-sdk: pip install "arkit-tool[view]" (or pip install rerun-sdk)'
)

_COLOURS = [(255, 200, 0), (0, 200, 255), (255, 80, 200), (120, 255, 80), (255, 120, 40), (160, 120, 255)]
"""A colour per track, as `predict --draw` gives them."""

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp")


def _rerun() -> Any:
    return _recording.rerun_module(INSTALL_HINT)


def read_rows(path: PathLike, skipped: Optional[List[str]] = None) -> Iterator[Dict[str, Any]]:
    """The rows of a `predict --video` JSON-lines file, one at a time. A line that is not
    such a row (not JSON, no integer `frame` or `track`, no 4-number `box`) is reported on
    the standard error, appended to `skipped` and left out."""
    path = os.fspath(path)
    try:
        f = open(path, encoding="utf-8")
    except OSError as e:
        raise DataError(f"{path}: {e.strerror or e}") from None
    with f:
        for n, line in enumerate(f, start=1):
            if not line.strip():
                continue
            why = None
            try:
                row = json.loads(line)
            except ValueError as e:
                row, why = None, f"not JSON ({e})"
            if why is None:
                if not isinstance(row, dict):
                    why = "not a JSON object"
                elif not all(isinstance(row.get(k), int) and row[k] >= 0 for k in ("frame", "track")):
                    why = "no frame or track number (is this predict --video's --output .jsonl?)"
                elif not (isinstance(row.get("box"), list) and len(row["box"]) == 4):
                    why = "no box [x0, y0, x1, y1]"
            if why is not None:
                message = f"{path}: line {n}: {why}; skipped"
                print(f"arkit_tool.video_view: {message}", file=sys.stderr)
                if skipped is not None:
                    skipped.append(message)
                continue
            yield cast(Dict[str, Any], row)


def _by_frame(rows: Iterator[Dict[str, Any]], path: str) -> Iterator[Tuple[int, List[Dict[str, Any]]]]:
    """Consecutive rows grouped by frame (the file lists frames in increasing order)."""
    frame: Optional[int] = None
    group: List[Dict[str, Any]] = []
    for row in rows:
        f = int(row["frame"])
        if frame is not None and f != frame:
            if f < frame:
                raise DataError(f"{path}: frame {f} comes after frame {frame}; the rows must be in frame order")
            yield frame, group
            group = []
        frame = f
        group.append(row)
    if frame is not None:
        yield frame, group


def _frame_number(name: str) -> Optional[int]:
    """The last run of digits in a file's stem, as `predict --video` orders a folder."""
    m = re.search(r"(\d+)\D*$", os.path.splitext(name)[0])
    return int(m.group(1)) if m else None


def _folder_frames(folder: str) -> List[str]:
    """A folder's frame files in `predict --video`'s order (by the number in the name)."""
    numbered = []
    for name in os.listdir(folder):
        p = os.path.join(folder, name)
        if name.lower().endswith(_IMAGE_SUFFIXES) and os.path.isfile(p):
            n = _frame_number(name)
            if n is None:
                raise DataError(f"{p}: a frame file of a video folder needs a number in its name")
            numbered.append((n, p))
    if not numbered:
        raise DataError(f"{folder}: a folder of video frames with no .png, .jpg, .jpeg or .webp file")
    return [p for _, p in sorted(numbered)]


def _first_camera(mesh_dir: str) -> Optional[Dict[str, Any]]:
    """The pinhole of the first landmarks file in `mesh_dir` (all of a video's share it)."""
    try:
        with os.scandir(mesh_dir) as entries:
            for e in entries:
                if e.name.endswith(".landmarks.json") and not e.name.startswith("."):
                    with open(e.path, encoding="utf-8") as f:
                        camera = json.load(f).get("camera")
                    return cast(Optional[Dict[str, Any]], camera)
    except OSError as e:
        raise DataError(f"{mesh_dir}: {e.strerror or e}") from None
    except ValueError as e:
        raise DataError(f"{mesh_dir}: a landmarks file is not JSON ({e})") from None
    return None


def read_obj(path: str) -> Tuple[np.ndarray, np.ndarray]:
    """The vertices `(N, 3)` and triangles `(M, 3)` (0-based) of an OBJ written by
    `predict --mesh` (`v` lines, then `f a/a b/b c/c` lines)."""
    verts: List[List[float]] = []
    tris: List[List[int]] = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                tris.append([int(x.split("/")[0]) - 1 for x in line.split()[1:4]])
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), np.asarray(tris, dtype=np.uint32).reshape(-1, 3)


def _rotation_translation(r_t: Any) -> Tuple[np.ndarray, np.ndarray]:
    """`(R, t)` with camera point `R x + t` from the release's row-vector `R_t`
    (`[x y z 1] @ R_t`)."""
    m = np.asarray(r_t, dtype=np.float64).reshape(4, 4)
    return m[:3, :3].T.copy(), m[3, :3].copy()


def record(
    poses: PathLike,
    *,
    video: Optional[PathLike] = None,
    mesh: Optional[PathLike] = None,
    path: Optional[PathLike] = None,
    spawn: bool = False,
    recording: Any = None,
) -> Dict[str, Any]:
    """Logs `poses` (a `predict --video` JSON-lines file) to Rerun on the `frame` and
    `video_time` timelines (see the module's docs for the entities), with the frames of
    `video` (the clip or folder the rows came from) and the meshes of `mesh` (the folder
    `predict --video --mesh` wrote). Output: `path` (an `.rrd` file, written to a
    temporary name and renamed when complete), `spawn=True` (start the viewer), or
    `recording` (a `rerun.RecordingStream` of your own). Returns `{"frames": N, "rows":
    N, "tracks": [ids], "meshes": N, "path": ..., "skipped": [...]}`."""
    rr = _rerun()
    if (path is None) + (not spawn) + (recording is None) != 2:
        raise DataError("give exactly one of path, spawn=True or recording")
    poses = os.fspath(poses)
    if not os.path.isfile(poses):
        raise DataError(f"{poses}: no such file (predict --video --output POSES.jsonl writes it)")
    mesh_dir = None if mesh is None else os.fspath(mesh)
    if mesh_dir is not None and not os.path.isdir(mesh_dir):
        raise DataError(f"{mesh_dir}: no such folder (predict --video --mesh DIR writes it)")
    video_path = None if video is None else os.fspath(video)
    frames_in_folder: Optional[List[str]] = None
    if video_path is not None:
        if os.path.isdir(video_path):
            frames_in_folder = _folder_frames(video_path)
        elif not os.path.isfile(video_path):
            raise DataError(f"{video_path}: no such file or folder")
    camera = None if mesh_dir is None else _first_camera(mesh_dir)
    asset: Any = None
    timestamps: Optional[np.ndarray] = None
    if video_path is not None and frames_in_folder is None:
        try:
            asset = rr.AssetVideo(path=video_path)
            timestamps = np.asarray(asset.read_frame_timestamps_nanos(), dtype=np.int64)
        except Exception as e:  # rerun's own errors for a file it cannot read
            raise DataError(f"{video_path}: Rerun cannot read this video ({e})") from None

    rec, tmp = _recording.open_recording(rr, "arkit_tool_video", path, spawn, recording)
    rec.log("world", rr.ViewCoordinates.RUB, static=True)
    image = "image"
    if camera is not None:
        image = "world/camera/image"
        k = np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])
        rec.log("world/camera", rr.Pinhole(image_from_camera=k, resolution=[camera["width"], camera["height"]],
                                           camera_xyz=rr.ViewCoordinates.RUB, image_plane_distance=0.3),
                static=True)
    if asset is not None:
        rec.log(image, asset, static=True)

    skipped: List[str] = []
    tracks: Set[int] = set()
    shown: Set[int] = set()
    rows = frames = meshes = 0
    try:
        for frame, group in _by_frame(read_rows(poses, skipped), poses):
            frames += 1
            rec.set_time("frame", sequence=frame)
            time_s = group[0].get("time_s")
            if isinstance(time_s, (int, float)):
                rec.set_time("video_time", duration=float(time_s))
            if frames_in_folder is not None:
                if frame < len(frames_in_folder):
                    rec.log(image, rr.EncodedImage(path=frames_in_folder[frame]))
                else:
                    skipped.append(f"{poses}: frame {frame}: the folder {video_path} has {len(frames_in_folder)} frames")
            elif timestamps is not None:
                if frame < len(timestamps):
                    rec.log(image, rr.VideoFrameReference(nanoseconds=int(timestamps[frame])))
                elif isinstance(time_s, (int, float)):
                    rec.log(image, rr.VideoFrameReference(seconds=float(time_s)))
            here: Set[int] = set()
            for row in group:
                track = int(row["track"])
                rows += 1
                tracks.add(track)
                here.add(track)
                colour = _COLOURS[track % len(_COLOURS)]
                angles = row.get("angles") if row.get("status") == "ok" else None
                label = f"track {track}"
                if isinstance(angles, dict):
                    label += " " + " ".join(f"{k} {float(v):.1f}" for k, v in angles.items())
                rec.log(f"{image}/track-{track}/box", rr.Boxes2D(array=np.asarray(row["box"], dtype=np.float64),
                                                                  array_format=rr.Box2DFormat.XYXY,
                                                                  colors=colour, labels=label))
                if not isinstance(angles, dict) or "R_t" not in row:
                    # The PnP failed: no pose here.
                    rec.log(f"world/track-{track}", rr.Clear(recursive=True))
                    rec.log(f"{image}/track-{track}/landmarks", rr.Clear(recursive=False))
                    continue
                r, t = _rotation_translation(row["R_t"])
                rec.log(f"world/track-{track}/head", rr.Transform3D(translation=t, mat3x3=r),
                        rr.TransformAxes3D(0.05))
                for name, v in angles.items():
                    rec.log(f"angles/track-{track}/{name}", rr.Scalars(float(v)))
                raw = row.get("raw_angles")
                if isinstance(raw, dict):
                    for name, v in raw.items():
                        rec.log(f"raw_angles/track-{track}/{name}", rr.Scalars(float(v)))
                if isinstance(row.get("inliers"), int):
                    rec.log(f"inliers/track-{track}", rr.Scalars(float(row["inliers"])))
                if mesh_dir is not None:
                    stem = os.path.join(mesh_dir, f"frame-{frame:06d}-track-{track}")
                    try:
                        verts, tris = read_obj(stem + ".obj")
                        with open(stem + ".landmarks.json", encoding="utf-8") as f:
                            marks = json.load(f)
                    except (OSError, ValueError) as e:
                        message = f"{stem}.obj: {e}; the mesh of frame {frame}, track {track} skipped"
                        print(f"arkit_tool.video_view: {message}", file=sys.stderr)
                        skipped.append(message)
                        continue
                    rec.log(f"world/track-{track}/mesh", rr.Mesh3D(vertex_positions=verts, triangle_indices=tris,
                                                                    albedo_factor=(*colour, 255)))
                    rec.log(f"world/track-{track}/landmarks",
                            rr.Points3D(np.asarray(marks["points_m"], dtype=np.float64), colors=colour, radii=0.0015))
                    pixels = [p for p in marks["pixels"] if p is not None]
                    rec.log(f"{image}/track-{track}/landmarks",
                            rr.Points2D(np.asarray(pixels, dtype=np.float64).reshape(-1, 2), colors=colour, radii=1.5))
                    meshes += 1
            for gone in shown - here:
                rec.log(f"world/track-{gone}", rr.Clear(recursive=True))
                rec.log(f"{image}/track-{gone}", rr.Clear(recursive=True))
            shown = here
    except BaseException:
        # No half-written recording survives.
        _recording.abandon(rec, tmp)
        raise
    out_path = _recording.finish(rec, tmp, path)
    return {"frames": frames, "rows": rows, "tracks": sorted(tracks), "meshes": meshes, "path": out_path,
            "skipped": skipped}


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m arkit_tool.video_view",
        description="Write a Rerun recording (.rrd) of `arkit-tool predict --video`'s rows, or open the viewer: "
        "on a `frame` timeline (and `video_time`), each track's box on the frame, its pose as axes in the "
        "camera's 3D space, its angles as plots, and with --mesh its mesh and landmarks. Needs pip install "
        "\"arkit-tool[view]\" (rerun-sdk).",
        epilog="Example: arkit-tool predict --model models/tiny-synthetic --video clip.mp4 --output poses.jsonl "
        "--mesh meshes/ && python -m arkit_tool.video_view poses.jsonl --video clip.mp4 --mesh meshes/ "
        "--output poses.rrd && rerun poses.rrd",
    )
    parser.add_argument("poses", help="predict --video's rows: --output POSES.jsonl")
    parser.add_argument("--video", help="the clip the rows came from (MP4/MOV, or the folder of numbered frames)")
    parser.add_argument("--mesh", metavar="DIR", help="the folder predict --video --mesh wrote")
    out = parser.add_mutually_exclusive_group(required=True)
    out.add_argument("--output", metavar="FILE.rrd", help="write a recording file (open it with `rerun FILE.rrd`)")
    out.add_argument("--spawn", action="store_true", help="start the Rerun viewer and stream to it")
    parser.add_argument("--json", action="store_true", help="print what was logged as JSON")
    a = parser.parse_args(argv)
    try:
        result = record(a.poses, video=a.video, mesh=a.mesh, path=a.output, spawn=a.spawn)
    except (DataError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(result, indent=1))
    else:
        where = result["path"] or "the viewer"
        print(f"{result['frames']} frames, {result['rows']} rows in {len(result['tracks'])} tracks, "
              f"{result['meshes']} meshes to {where}; {len(result['skipped'])} skipped")
    if not result["rows"]:
        print(f"error: {a.poses}: no row", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

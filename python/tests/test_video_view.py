"""arkit_tool.video_view: a Rerun recording of `predict --video`'s rows, read back with
Rerun's own reader (`rerun.chunk.RrdReader`).

What is checked, on `synth --video` clips (known poses) through the shipped tiny model:
on the `frame` timeline, each track's angles, raw angles, box and pose equal the JSON
lines' row for row (the same frames, the same track ids); the meshes are the --mesh
files' vertices; the pinhole is the files' camera; the MP4 is logged as a video asset
with one frame reference per frame, a folder as one image per frame; a track missing
from some frames is cleared there; a malformed line is reported and skipped. SKIPPED
without rerun-sdk.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import BIN, ROOT

TINY = str(ROOT / "models" / "tiny-synthetic")


def _reader():
    try:
        import rerun  # noqa: F401
        from rerun.chunk import RrdReader
    except ImportError:
        pytest.skip("SKIPPED: no rerun-sdk with rerun.chunk.RrdReader (pip install rerun-sdk)")
    return RrdReader


def _entities(rrd):
    """`{entity path: {frame (None when static): {component: value}}}`, read back."""
    out = {}
    for chunk in _reader()(str(rrd)).stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        frames = batch.column("frame").to_pylist() if "frame" in names else [None] * batch.num_rows
        comps = [n for n in names if ":" in n]
        for r, frame in enumerate(frames):
            row = out.setdefault(chunk.entity_path, {}).setdefault(frame, {})
            for c in comps:
                v = batch.column(c)[r].as_py()
                if v is not None:
                    row[c] = v
    return out


def _predict(tmp_path, clip, boxes, name):
    rows, meshes = tmp_path / f"{name}.jsonl", tmp_path / f"{name}-meshes"
    subprocess.run([str(BIN), "predict", "--model", TINY, "--video", str(clip), "--boxes", str(boxes),
                    "--output", str(rows), "--mesh", str(meshes)], check=True, capture_output=True)
    return rows, meshes, [json.loads(line) for line in open(rows)]


@pytest.fixture(scope="module")
def crossing(tmp_path_factory):
    """The crossing clip (two tracks), a folder of frames, with its rows and meshes."""
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    _reader()
    base = tmp_path_factory.mktemp("cross")
    clip = base / "cross"
    subprocess.run([str(BIN), "synth", "--video", str(clip), "--clip", "cross", "--size", "480x270"],
                   check=True, capture_output=True)
    return (clip,) + _predict(base, clip, base / "cross.boxes.jsonl", "cross")


def test_the_frame_timeline_holds_every_row(crossing, tmp_path):
    from arkit_tool import video_view

    clip, rows_path, meshes, rows = crossing
    rrd = tmp_path / "cross.rrd"
    result = video_view.record(rows_path, video=clip, mesh=meshes, path=rrd)
    ok = [r for r in rows if r["status"] == "ok"]
    frames = sorted({r["frame"] for r in rows})
    assert result["rows"] == len(rows) and result["frames"] == len(frames)
    assert result["tracks"] == [0, 1] and result["meshes"] == len(ok) and not result["skipped"]
    e = _entities(rrd)
    image = "/world/camera/image"
    # One image per frame of the folder, at the frames of the rows.
    assert sorted(f for f, c in e[image].items() if "EncodedImage:blob" in c) == frames
    for track in (0, 1):
        mine = {r["frame"]: r for r in rows if r["track"] == track}
        posed = {f: r for f, r in mine.items() if r["status"] == "ok"}
        assert len(posed) > 60
        for name in ("yaw", "pitch", "roll"):
            logged = {f: c["Scalars:scalars"][0] for f, c in e[f"/angles/track-{track}/{name}"].items()}
            assert logged == {f: r["angles"][name] for f, r in posed.items()}, (track, name)
            raw = {f: c["Scalars:scalars"][0] for f, c in e[f"/raw_angles/track-{track}/{name}"].items()}
            assert raw == {f: r["raw_angles"][name] for f, r in posed.items()}, (track, name)
        boxes = e[f"{image}/track-{track}/box"]
        assert sorted(boxes) == sorted(mine)
        for f, r in mine.items():
            x0, y0, x1, y1 = r["box"]
            c = boxes[f]
            np.testing.assert_allclose(c["Boxes2D:centers"][0], [(x0 + x1) / 2, (y0 + y1) / 2], atol=1e-3)
            np.testing.assert_allclose(c["Boxes2D:half_sizes"][0], [(x1 - x0) / 2, (y1 - y0) / 2], atol=1e-3)
        heads = e[f"/world/track-{track}/head"]
        meshes_logged = e[f"/world/track-{track}/mesh"]
        assert sorted(meshes_logged) == sorted(posed)
        for f, r in posed.items():
            rt = np.asarray(r["R_t"])
            np.testing.assert_allclose(heads[f]["Transform3D:translation"][0], rt[3, :3], atol=1e-6)
            # Rerun stores 3 x 3 matrices column by column: R's columns, R = R_t[:3, :3]^T.
            np.testing.assert_allclose(np.asarray(heads[f]["Transform3D:mat3x3"][0]).reshape(3, 3).T,
                                       rt[:3, :3].T, atol=1e-6)
        # The meshes are the files' (f32 in the recording).
        f = min(posed)
        verts, tris = video_view.read_obj(str(meshes / f"frame-{f:06d}-track-{track}.obj"))
        logged_verts = np.asarray(meshes_logged[f]["Mesh3D:vertex_positions"])
        assert logged_verts.shape == (1220, 3)
        np.testing.assert_allclose(logged_verts, verts, atol=1e-6)
        assert np.asarray(meshes_logged[f]["Mesh3D:triangle_indices"]).shape == tris.shape
    # The pinhole is the mesh files' camera (K stored column by column).
    marks = json.load(open(meshes / "frame-000000-track-0.landmarks.json"))
    k = np.asarray(e["/world/camera"][None]["Pinhole:image_from_camera"]).reshape(3, 3).T
    cam = marks["camera"]
    np.testing.assert_allclose(k, [[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], atol=1e-3)


def test_a_missing_track_is_cleared_and_a_bad_line_skipped(crossing, tmp_path):
    from arkit_tool import video_view

    _, rows_path, _, rows = crossing
    # Track 1 leaves for frames 40 to 44; line 3 is damaged.
    kept = [r for r in rows if not (r["track"] == 1 and 40 <= r["frame"] <= 44)]
    lines = [json.dumps(r) for r in kept]
    lines.insert(2, '{"frame": 1, "track"')
    cut = tmp_path / "cut.jsonl"
    cut.write_text("\n".join(lines) + "\n")
    rrd = tmp_path / "cut.rrd"
    result = video_view.record(cut, path=rrd)
    assert len(result["skipped"]) == 1 and "line 3" in result["skipped"][0], result["skipped"]
    assert result["rows"] == len(kept)
    e = _entities(rrd)
    # Without a mesh folder there is no pinhole: the frames' 2D space is `image`.
    assert "/world/camera" not in e
    box = e["/image/track-1/box"]
    assert not any(40 <= f <= 44 for f, c in box.items() if "Boxes2D:centers" in c)
    cleared = sorted(f for f, c in e["/world/track-1"].items() if c.get("Clear:is_recursive"))
    assert cleared == [40], cleared
    assert sorted(f for f, c in e["/image/track-1"].items() if c.get("Clear:is_recursive")) == [40]
    # Rows out of frame order: refused, naming the file, and no recording is left.
    jumbled = tmp_path / "jumbled.jsonl"
    jumbled.write_text("\n".join(json.dumps(r) for r in rows[10:] + rows[:10]) + "\n")
    with pytest.raises(video_view.DataError, match="jumbled.jsonl"):
        video_view.record(jumbled, path=tmp_path / "jumbled.rrd")
    assert not list(tmp_path.glob("jumbled.rrd*"))
    # A file Rerun cannot read as a video: refused before anything is written.
    with pytest.raises(video_view.DataError, match="cut.jsonl: Rerun cannot read"):
        video_view.record(cut, video=cut, path=tmp_path / "notvideo.rrd")
    assert not list(tmp_path.glob("notvideo.rrd*"))
    # Track 0 is never cleared.
    assert "/world/track-0" not in e or not any(c.get("Clear:is_recursive") for c in e["/world/track-0"].values())


def test_an_mp4_is_a_video_asset_with_a_frame_reference_per_frame(tmp_path):
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    _reader()
    clip = tmp_path / "turn.mp4"
    subprocess.run([str(BIN), "synth", "--video", str(clip), "--size", "320x240"], check=True, capture_output=True)
    rows_path, _, rows = _predict(tmp_path, clip, tmp_path / "turn.boxes.jsonl", "turn")
    rrd = tmp_path / "turn.rrd"
    out = subprocess.run([sys.executable, "-m", "arkit_tool.video_view", str(rows_path), "--video", str(clip),
                          "--output", str(rrd), "--json"], check=True, capture_output=True, text=True)
    result = json.loads(out.stdout)
    assert result["tracks"] == [0] and result["frames"] == len(rows) and result["path"] == str(rrd)
    e = _entities(rrd)
    assert e["/image"][None]["AssetVideo:media_type"] == ["video/mp4"]
    refs = {f: c["VideoFrameReference:timestamp"] for f, c in e["/image"].items() if f is not None}
    assert sorted(refs) == [r["frame"] for r in rows]
    # The references are the asset's own frame times, within a millisecond of the rows'.
    for r in rows:
        assert abs(refs[r["frame"]][0] / 1e9 - r["time_s"]) < 1e-3, r["frame"]
    assert not (tmp_path / "turn.rrd.partial").exists()
    # Bad input: the error names the file.
    bad = subprocess.run([sys.executable, "-m", "arkit_tool.video_view", str(tmp_path / "none.jsonl"),
                          "--output", str(tmp_path / "x.rrd")], capture_output=True, text=True)
    assert bad.returncode == 2 and "none.jsonl" in bad.stderr

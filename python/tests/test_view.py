"""arkit_tool.view: a Rerun recording of a selection, read back with Rerun's own reader.

What is checked: the entities and their counts; the geometric fact that the logged
mesh's landmark vertices, projected through the logged pinhole (its K and its camera
axes), land on the logged 2D landmarks within half a pixel; the per-sample errors
against hand-made perturbations and against `arkit-tool eval --per-sample`; the N worst
selection; the command line. SKIPPED without rerun-sdk.
"""

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import BIN, make_dataset, run

import arkit_tool
from arkit_tool import _native


def _rerun():
    try:
        import rerun  # noqa: F401
        from rerun.chunk import RrdReader  # noqa: F401
    except ImportError:
        pytest.skip("SKIPPED: no rerun-sdk with rerun.chunk.RrdReader (pip install rerun-sdk)")
    return RrdReader


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """The built-in face, 3 subjects x 4 images, with render's targets."""
    base = tmp_path_factory.mktemp("view")
    data = make_dataset(base, resources=False, size="320x320")
    run(BIN, "render", "--dataset", data, "--size", 64, "--uv-size", 32, "--points", 64)
    return data


def _rotation_y(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _predictions(data, path, angles):
    """Predictions: each sample's true R_t with its rotation turned by `angles[i]`
    degrees about the camera's y axis and its translation moved 1 cm along x (so the
    geodesic rotation error is the angle and the translation error 10 mm)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    ds = arkit_tool.open_dataset(data)
    rows = {"subject_id": [], "facial_action": [], "img_id": [], "R_t": []}
    for i, key in enumerate(ds.keys):
        rt = np.array(ds.sample(i)["R_t"], dtype=np.float64).reshape(4, 4)
        # Row-vector form: [x y z 1] @ R_t, R_t[:3,:3] = R^T; the camera-frame turn G acts
        # on the right: p @ R^T @ G^T.
        rt[:3, :3] = rt[:3, :3] @ _rotation_y(angles[i]).T
        rt[3, 0] += 0.01
        for k, v in zip(("subject_id", "facial_action", "img_id"), key):
            rows[k].append(v)
        rows["R_t"].append(rt.reshape(-1).tolist())
    pq.write_table(pa.table(rows), path)
    return ds.keys


def _entities(rrd):
    """`{entity path: {sample index (or None for static): {component: value}}}` from
    the recording, read with Rerun's reader."""
    RrdReader = _rerun()
    out = {}
    for chunk in RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        steps = batch.column("sample").to_pylist() if "sample" in names else [None] * batch.num_rows
        comps = [n for n in names if ":" in n]
        for r, step in enumerate(steps):
            row = out.setdefault(chunk.entity_path, {}).setdefault(step, {})
            for c in comps:
                v = batch.column(c)[r].as_py()
                if v is not None:
                    row[c] = v
    return out


# Rerun's ViewCoordinates codes (rerun.components.ViewCoordinates): the direction each
# of the camera's x, y, z axes points.
_AXES = {1: (1, -1), 2: (1, 1), 3: (0, 1), 4: (0, -1), 5: (2, 1), 6: (2, -1)}  # up, down, right, left, fwd, back


def _to_rdf(codes):
    """The matrix taking camera points in the logged axes to x right, y down, z forward
    (the frame a pinhole's K applies to)."""
    m = np.zeros((3, 3))
    for col, code in enumerate(codes):
        row, sign = _AXES[code]
        m[row, col] = sign
    return m


def test_the_recording_holds_every_sample_and_the_mesh_projects_onto_the_landmarks(rendered, tmp_path):
    _rerun()
    from arkit_tool import view

    ds = arkit_tool.open_dataset(rendered)
    angles = [3.0 * (i + 1) for i in range(len(ds))]
    keys = _predictions(rendered, tmp_path / "pred.parquet", angles)
    rrd = tmp_path / "all.rrd"
    result = view.record(rendered, predictions=tmp_path / "pred.parquet", correspondences=5, path=rrd)
    n = len(ds)
    assert result["samples"] == [tuple(k) for k in keys] and result["skipped"] == []
    assert result["path"] == os.fspath(rrd) and not os.path.exists(f"{rrd}.partial")
    e = _entities(rrd)
    per_sample = [
        "/world/camera", "/world/camera/image", "/world/camera/image/landmarks", "/world/camera/image/crop_box",
        "/world/mesh/truth", "/world/mesh/predicted", "/world/landmarks/truth", "/world/mesh/correspondences",
        "/crop/image", "/crop/mask", "/crop/correspondences", "/uv_map", "/pose", "/pose/yaw_deg",
        "/pose/distance_m", "/errors/rotation_deg", "/errors/translation_mm", "/errors/add_mm",
    ]
    for path in per_sample:
        assert sorted(s for s in e.get(path, {}) if s is not None) == list(range(n)), path
    assert e["/world"][None]["ViewCoordinates:xyz"] == [[3, 1, 6]]  # RUB: OpenGL's camera frame

    topo = _native.topology(os.fspath(rendered))
    landmark_ids = np.asarray(topo["landmarks"])
    assert len(landmark_ids) == 68
    worst_px = 0.0
    for step in range(n):
        cam = e["/world/camera"][step]
        # Rerun stores the 3x3 matrix column by column.
        k = np.asarray(cam["Pinhole:image_from_camera"][0], dtype=np.float64).reshape(3, 3).T
        w, h = cam["Pinhole:resolution"][0]
        s = ds.sample(step)
        assert (w, h) == (s["image_width"], s["image_height"])
        to_rdf = _to_rdf(cam["Pinhole:camera_xyz"][0])
        mesh = np.asarray(e["/world/mesh/truth"][step]["Mesh3D:vertex_positions"], dtype=np.float64)
        assert mesh.shape == (topo["vertex_count"], 3)
        assert len(e["/world/mesh/truth"][step]["Mesh3D:triangle_indices"]) == len(topo["triangles"])
        q = (to_rdf @ mesh[landmark_ids].T).T
        assert np.all(q[:, 2] > 0), "the face is in front of the camera"
        uv = (k @ (q / q[:, 2:3]).T).T[:, :2]
        logged = np.asarray(e["/world/camera/image/landmarks"][step]["Points2D:positions"])
        assert logged.shape == (68, 2)
        worst_px = max(worst_px, float(np.abs(uv - logged).max()))
        # The correspondences: 5 face pixels of the crop, their 3D points on the mesh.
        assert len(e["/crop/correspondences"][step]["Points2D:positions"]) == 5
        assert len(e["/world/mesh/correspondences"][step]["Points3D:positions"]) == 5
        # The errors: the hand-made turn and the 1 cm shift.
        assert abs(e["/errors/rotation_deg"][step]["Scalars:scalars"][0] - angles[step]) < 1e-6
        assert abs(e["/errors/translation_mm"][step]["Scalars:scalars"][0] - 10.0) < 1e-6
    assert worst_px < 0.5, worst_px
    # Half a pixel tells: the principal point one pixel off, or the camera's y axis
    # taken as pointing down (OpenCV's frame), misses.
    shifted = k.copy()
    shifted[0, 2] += 1.0
    assert np.abs((shifted @ (q / q[:, 2:3]).T).T[:, :2] - logged).max() > 0.5
    flipped = (_to_rdf([3, 2, 5]) @ mesh[landmark_ids].T).T
    assert not np.all(flipped[:, 2] > 0) or np.abs((k @ (flipped / flipped[:, 2:3]).T).T[:, :2] - logged).max() > 0.5


def test_errors_agree_with_eval_per_sample_and_worst_picks_the_largest(rendered, tmp_path):
    _rerun()
    import pyarrow.parquet as pq

    from arkit_tool import view

    ds = arkit_tool.open_dataset(rendered)
    angles = [(7 * i) % 11 + 1.0 for i in range(len(ds))]
    keys = _predictions(rendered, tmp_path / "pred.parquet", angles)
    run(BIN, "eval", "--dataset", rendered, "--predictions", tmp_path / "pred.parquet", "--split", "all",
        "--per-sample", tmp_path / "errors.parquet")
    table = pq.read_table(tmp_path / "errors.parquet").to_pylist()
    by_key = {(r["subject_id"], r["facial_action"], r["img_id"]): r for r in table}
    for i, key in enumerate(keys):
        s = ds.sample(i)
        ours = view.sample_errors(s["verts"], s["R_t"], _predictions_rt(tmp_path / "pred.parquet", key))
        theirs = by_key[tuple(key)]
        assert abs(ours["rotation_deg"] - theirs["rotation_err_deg"]) < 1e-6
        assert abs(ours["translation_mm"] - theirs["translation_err_mm"]) < 1e-6
        assert abs(ours["add_mm"] - theirs["add_mm"]) < 1e-6 * max(1.0, theirs["add_mm"])
    result = view.record(rendered, predictions=tmp_path / "pred.parquet", worst=3, path=tmp_path / "worst.rrd")
    order = sorted(range(len(keys)), key=lambda i: -angles[i])[:3]
    assert result["samples"] == [tuple(keys[i]) for i in order]
    e = _entities(tmp_path / "worst.rrd")
    got = [e["/errors/rotation_deg"][step]["Scalars:scalars"][0] for step in range(3)]
    assert np.allclose(got, [angles[i] for i in order])


def _predictions_rt(path, key):
    return arkit_tool.view.read_predictions(path)[tuple(key)]["R_t"]


def test_selection_by_split_subject_and_pose_range(rendered, tmp_path):
    _rerun()
    from arkit_tool import view

    ds = arkit_tool.open_dataset(rendered)
    test = ds.split_indices("test")
    assert 0 < len(test) < len(ds)
    r = view.record(rendered, split="test", path=tmp_path / "test.rrd")
    assert r["samples"] == [tuple(ds.keys[i]) for i in test]
    subject = ds.keys[0][0]
    yaw = np.array([ds.sample(i)["yaw_deg"] for i in range(len(ds))])
    lo, hi = float(np.median(yaw)), 90.0
    picked = view.select(ds, subjects=[subject], yaw_range=(lo, hi))
    assert picked == [i for i in range(len(ds)) if ds.keys[i][0] == subject and lo <= yaw[i] <= hi]
    e = _entities(tmp_path / "test.rrd")
    assert "/world/mesh/predicted" not in e and "/errors/rotation_deg" not in e
    with pytest.raises(arkit_tool.DataError, match="worst"):
        view.record(rendered, worst=2, path=tmp_path / "x.rrd")
    with pytest.raises(arkit_tool.DataError, match="yaw_range"):
        view.select(ds, yaw_range=(10, -10))


def test_the_command_line_writes_a_recording_and_fails_on_an_empty_selection(rendered, tmp_path):
    _rerun()
    env = dict(os.environ)
    cmd = [sys.executable, "-m", "arkit_tool.view", os.fspath(rendered)]
    out = subprocess.run(cmd + ["--split", "test", "--limit", "2", "--output", os.fspath(tmp_path / "a.rrd"),
                                "--json"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    import json

    assert len(json.loads(out.stdout)["samples"]) == 2
    assert len({s for s in _entities(tmp_path / "a.rrd")["/pose"] if s is not None}) == 2
    out = subprocess.run(cmd + ["--subject", "nobody", "--output", os.fspath(tmp_path / "b.rrd")],
                         capture_output=True, text=True, env=env)
    assert out.returncode == 1 and "no sample matched" in out.stderr


def test_a_missing_rerun_says_how_to_install(monkeypatch, dataset, tmp_path):
    # Runs without rerun-sdk too: the message is what a user without it sees.
    from arkit_tool import view

    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(ImportError, match=r"pip install \"arkit-tool\[view\]\""):
        view.record(dataset, path=tmp_path / "x.rrd")
    assert not (tmp_path / "x.rrd").exists()

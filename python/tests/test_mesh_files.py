"""`arkit-tool predict --image --mesh DIR`'s files read by an independent reader
(trimesh): the vertices are the report's camera-space vertices, the faces the model's
topology's triangles, the UVs its UVs (v flipped upward, as OBJ and PLY count it), in
both the .obj and the .ply."""

import json
import subprocess

import numpy as np
import pytest

from conftest import BIN, ROOT

trimesh = pytest.importorskip("trimesh", reason="trimesh is not installed (pip install trimesh)")

from arkit_tool import _native  # noqa: E402  (the topology the files should carry)

TINY = str(ROOT / "models" / "tiny-synthetic")


def test_obj_and_ply_read_back_by_trimesh(tmp_path, dataset):
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    photo = tmp_path / "group.jpg"
    subprocess.run([str(BIN), "synth", "--group-photo", str(photo), "--faces", "2",
                    "--size", "960x540", "--seed", "2"], check=True, capture_output=True)
    meshes = tmp_path / "meshes"
    out = subprocess.run([str(BIN), "predict", "--model", TINY, "--image", str(photo),
                          "--boxes", str(tmp_path / "group.boxes.json"), "--vertices",
                          "--mesh", str(meshes)], check=True, capture_output=True, text=True)
    report = json.loads(out.stdout)
    topo = _native.topology(str(dataset))  # the built-in face, as the tiny model's
    triangles = np.asarray(topo["triangles"], dtype=np.int64)
    uv_up = np.asarray(topo["uv"], dtype=np.float64).copy()
    uv_up[:, 1] = 1.0 - uv_up[:, 1]
    faces = report["photos"][0]["faces"]
    assert len(faces) == 2
    for face in faces:
        verts = np.asarray(face["vertices_m"])
        for key in ("obj", "ply"):
            path = face["mesh"][key]
            kwargs = {"maintain_order": True} if key == "obj" else {}
            mesh = trimesh.load(path, process=False, **kwargs)
            assert mesh.vertices.shape == (1220, 3), path
            np.testing.assert_allclose(mesh.vertices, verts, rtol=0, atol=1e-12, err_msg=path)
            np.testing.assert_array_equal(mesh.faces, triangles, err_msg=path)
            assert mesh.visual.uv is not None, path
            np.testing.assert_allclose(mesh.visual.uv, uv_up, rtol=0, atol=1e-6, err_msg=path)
        marks = json.load(open(face["mesh"]["landmarks"]))
        ids = np.asarray(marks["vertex_ids"])
        np.testing.assert_array_equal(ids, np.asarray(topo["landmarks"]))
        np.testing.assert_allclose(np.asarray(marks["points_m"]), verts[ids], atol=1e-12)
        assert len(marks["pixels"]) == 68


def test_video_meshes_read_back_by_trimesh(tmp_path, dataset):
    """`predict --video --mesh DIR`: one frame-NNNNNN-track-K set a posed row, each read
    by trimesh with the topology's triangles and UVs, the .obj and .ply the same
    vertices, the landmarks file's points among them; the vertices lie at the row's
    distance from the camera."""
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    clip = tmp_path / "turn.mp4"
    subprocess.run([str(BIN), "synth", "--video", str(clip), "--size", "320x240"], check=True,
                   capture_output=True)
    meshes, rows_path = tmp_path / "meshes", tmp_path / "rows.jsonl"
    subprocess.run([str(BIN), "predict", "--model", TINY, "--video", str(clip),
                    "--boxes", str(tmp_path / "turn.boxes.jsonl"), "--output", str(rows_path),
                    "--mesh", str(meshes)], check=True, capture_output=True)
    rows = [json.loads(line) for line in open(rows_path)]
    posed = [r for r in rows if r["status"] == "ok"]
    assert len(posed) > 50
    assert len(list(meshes.iterdir())) == 3 * len(posed)
    topo = _native.topology(str(dataset))
    triangles = np.asarray(topo["triangles"], dtype=np.int64)
    uv_up = np.asarray(topo["uv"], dtype=np.float64).copy()
    uv_up[:, 1] = 1.0 - uv_up[:, 1]
    for r in (posed[0], posed[len(posed) // 2], posed[-1]):
        stem = meshes / f"frame-{r['frame']:06d}-track-{r['track']}"
        obj = trimesh.load(f"{stem}.obj", process=False, maintain_order=True)
        ply = trimesh.load(f"{stem}.ply", process=False)
        for mesh in (obj, ply):
            assert mesh.vertices.shape == (1220, 3)
            np.testing.assert_array_equal(mesh.faces, triangles)
            np.testing.assert_allclose(mesh.visual.uv, uv_up, rtol=0, atol=1e-6)
        np.testing.assert_allclose(obj.vertices, ply.vertices, rtol=0, atol=1e-12)
        marks = json.load(open(f"{stem}.landmarks.json"))
        assert (marks["frame_index"], marks["track"], marks["pose"]) == (r["frame"], r["track"], "smoothed")
        np.testing.assert_allclose(np.asarray(marks["points_m"]), obj.vertices[np.asarray(topo["landmarks"])],
                                   atol=1e-12)
        # The face sits where the row's pose puts it: its centre within 10 cm of the
        # row's translation (the model's head origin), in front of the camera (-z).
        centre = obj.vertices.mean(axis=0)
        assert np.linalg.norm(centre - np.asarray(r["translation_m"])) < 0.1
        assert centre[2] < 0

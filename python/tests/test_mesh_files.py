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

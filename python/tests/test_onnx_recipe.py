"""docs/onnx.md's recipe, docs/onnx_recipe.py, run with onnxruntime, numpy and OpenCV
only (torch and arkit_tool made unimportable in its process), gives the pose `arkit-tool
predict --image` gives on a face where both PnPs keep every point (the seeded sampler,
the crop and the pixel mapping are then the only way to agree; a different pixel choice
moves the tiny model's pose by degrees, docs/onnx.md).

The interpreter is $ARKIT_ONNX_RECIPE_PYTHON (CI: one with opencv-python-headless 4.6,
the official code's era, and onnxruntime), else this one; the test says SKIPPED when it
lacks cv2 or onnxruntime, or has an OpenCV from 4.11 on, whose resampling differs from
4.6's on a few pixels (and so the crop, the mask and the pose)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import BIN, ROOT

RECIPE = ROOT / "docs" / "onnx_recipe.py"
TINY = str(ROOT / "models" / "tiny-synthetic")
PYTHON = os.environ.get("ARKIT_ONNX_RECIPE_PYTHON", sys.executable)
# The recipe in a process where `import torch` and `import arkit_tool` fail.
ISOLATED = ("import runpy, sys; sys.modules['torch'] = None; sys.modules['arkit_tool'] = None; "
            "sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__')")


def opencv_version():
    out = subprocess.run([PYTHON, "-c", "import cv2, numpy, onnxruntime; print(cv2.__version__)"],
                         capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip(f"SKIPPED: {PYTHON} lacks cv2, numpy or onnxruntime "
                    "(set ARKIT_ONNX_RECIPE_PYTHON to one with opencv-python-headless 4.6 and onnxruntime)")
    return tuple(int(v) for v in out.stdout.strip().split(".")[:2])


def rotation_deg(a, b):
    r = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def test_the_recipe_gives_predicts_pose(tmp_path):
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    version = opencv_version()
    if version >= (4, 11):
        pytest.skip(f"SKIPPED: OpenCV {version} resamples differently from 4.6 (docs/onnx.md)")
    bin_ = str(BIN)
    jpeg, photo = tmp_path / "group.jpg", tmp_path / "group.png"
    subprocess.run([bin_, "synth", "--group-photo", str(jpeg), "--faces", "3", "--size",
                    "1280x720", "--seed", "1"], check=True, capture_output=True)
    # One decoder for both sides: the JPEG's pixels as a PNG.
    subprocess.run([PYTHON, "-c", "import cv2, sys; cv2.imwrite(sys.argv[2], cv2.imread(sys.argv[1]))",
                    str(jpeg), str(photo)], check=True)
    boxes = json.load(open(tmp_path / "group.boxes.json"))
    onnx_dir = tmp_path / "tiny-onnx"
    subprocess.run([bin_, "export-onnx", "--model", TINY, "--output", str(onnx_dir)],
                   check=True, capture_output=True)
    out = subprocess.run([bin_, "predict", "--model", TINY, "--image", str(photo), "--boxes",
                          str(tmp_path / "group.boxes.json")], check=True, capture_output=True, text=True)
    faces = json.loads(out.stdout)["photos"][0]["faces"]
    # Face 0 of photo 0 with --seed 0: the sampler's seed is 0 ^ (0 << 32) ^ 0.
    box = " ".join(str(v) for v in boxes[0])
    out = subprocess.run([PYTHON, "-c", ISOLATED, str(RECIPE), str(onnx_dir), str(photo), box, "0"],
                         check=True, capture_output=True, text=True)
    recipe = json.loads(out.stdout)
    ours = faces[0]
    assert ours["inliers"] == recipe["inliers"] == 256, (ours["inliers"], recipe["inliers"])
    a, b = np.array(ours["R_t"]), np.array(recipe["R_t"])
    assert rotation_deg(a, b) < 0.01, rotation_deg(a, b)
    assert np.linalg.norm(a[3, :3] - b[3, :3]) < 1e-4
    assert np.abs(a - b).max() < 1e-4
    # Another seed chooses other pixels and moves the pose (the point of the sampler's
    # description): by more than 0.5 degrees here.
    out = subprocess.run([PYTHON, "-c", ISOLATED, str(RECIPE), str(onnx_dir), str(photo), box, "1"],
                         check=True, capture_output=True, text=True)
    other = json.loads(out.stdout)
    assert other["choose"] != recipe["choose"]
    assert rotation_deg(a, np.array(other["R_t"])) > 0.5


def test_the_manifests_point_selection_names_functions_that_exist(tmp_path):
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    import re

    from arkit_tool import _native

    subprocess.run([str(BIN), "export-onnx", "--model", TINY, "--output", str(tmp_path / "x")],
                   check=True, capture_output=True)
    text = json.load(open(tmp_path / "x" / "onnx.json"))["point_selection"]
    names = re.findall(r"arkit_tool\._native\.(\w+)", text)
    assert names == ["choose_points"], text
    assert all(hasattr(_native, n) for n in names)

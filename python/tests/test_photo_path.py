"""The photo path without torch: `arkit_tool.photo.predict_photo` with the shipped tiny
model exported to ONNX and run by onnxruntime, against `arkit-tool predict --image` (the
same weights in candle) on a synthetic group photo of three faces of different sizes.

The crops are the same bytes (one Rust function cuts them for both), the chosen pixels
the same (one sampler, the same seeds), and the network's outputs within onnxruntime's
float differences (docs/onnx.md): the poses agree to 1e-4 in every entry of `R_t`."""

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import BIN, ROOT

pytest.importorskip("onnxruntime", reason="onnxruntime is not installed")

TINY = str(ROOT / "models" / "tiny-synthetic")

# The Python side in a process where torch cannot be imported.
WITHOUT_TORCH = r"""
import json, sys
sys.modules["torch"] = None  # any `import torch` now fails
from arkit_tool.onnx import OnnxPerspNet
from arkit_tool.photo import predict_photo, read_photo
folder, photo, boxes = sys.argv[1:4]
faces = predict_photo(read_photo(photo), json.load(open(boxes)), network=OnnxPerspNet(folder))
print(json.dumps([{"R_t": f["R_t"].tolist(), "choose": f["choose"].tolist(),
                   "angles": f["angles"], "inliers": f["inliers"], "status": f["status"],
                   "vertices": len(f["vertices_m"])} for f in faces]))
"""


def test_the_onnx_photo_path_gives_predict_images_poses(tmp_path):
    bin_ = str(BIN)
    photo = tmp_path / "group.jpg"
    subprocess.run([bin_, "synth", "--group-photo", str(photo), "--faces", "3",
                    "--size", "1280x720", "--seed", "1"], check=True, capture_output=True)
    boxes = tmp_path / "group.boxes.json"
    onnx_dir = tmp_path / "tiny-onnx"
    subprocess.run([bin_, "export-onnx", "--model", TINY, "--output", str(onnx_dir)],
                   check=True, capture_output=True)
    table = tmp_path / "faces.csv"
    subprocess.run([bin_, "predict", "--model", TINY, "--image", str(photo), "--boxes",
                    str(boxes), "--output", str(table)], check=True, capture_output=True)
    with open(table) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3 and all(r["status"] == "ok" for r in rows)

    out = subprocess.run([sys.executable, "-c", WITHOUT_TORCH, str(onnx_dir), str(photo), str(boxes)],
                         check=True, capture_output=True, text=True)
    faces = json.loads(out.stdout)
    assert len(faces) == 3
    for row, face in zip(rows, faces):
        assert face["status"] == "ok" and face["vertices"] == 1220
        rt_rust = np.array([float(row[f"r_t_{i // 4}{i % 4}"]) for i in range(16)]).reshape(4, 4)
        rt_onnx = np.array(face["R_t"])
        assert np.abs(rt_onnx - rt_rust).max() < 1e-4, (rt_onnx, rt_rust)
        for name in ("yaw", "pitch", "roll"):
            assert abs(face["angles"][name] - float(row[name])) < 0.01
        assert abs(face["inliers"] - int(row["inliers"])) <= 2


def test_the_photo_path_refuses_bad_input(tmp_path):
    from arkit_tool import photo as ph

    class Never:
        input_size = 64

        def predict(self, image, seeds):  # pragma: no cover - must not be reached
            raise AssertionError("the network ran on bad input")

    img = np.full((100, 200, 3), 90, np.uint8)
    with pytest.raises(ph.DataError, match="outside the 200x100 photo"):
        ph.predict_photo(img, [[300, 10, 350, 60]], network=Never())
    with pytest.raises(ph.DataError, match="face box"):
        ph.predict_photo(img, [[50, 50, 40, 90]], network=Never())
    with pytest.raises(ph.DataError, match="focal_px or fov_deg"):
        ph.predict_photo(img, [[10, 10, 60, 60]], network=Never(), focal_px=500, fov_deg=60)
    with pytest.raises(ph.DataError, match="uint8"):
        ph.predict_photo(img.astype(np.float32), [[10, 10, 60, 60]], network=Never())
    # No box and no face: nothing to predict, the network is not run.
    assert ph.predict_photo(img, None, network=Never()) == []

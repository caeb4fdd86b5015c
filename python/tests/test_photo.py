"""The official demo's preprocessing of a photo (pad to a square, `cv2.resize` to 800,
the 0.75 box rule, `cv2.warpAffine` to 192), reproduced here with numpy and OpenCV from
demo.py's steps, against `_native.photo_crop`.

The official code pins OpenCV 4.5; OpenCV 5's `warpAffine` computes in float and differs
(docs/python.md). With `ARKIT_OPENCV_PYTHON` naming a Python with OpenCV 4.x (CI makes
one) the demo's steps run there; otherwise in this process's OpenCV, with a bound that
allows OpenCV 5's warp."""

import json
import os
import subprocess
import sys
import tempfile

import numpy as np
import pytest

from arkit_tool import _native

DEMO_STEPS = r"""
import json, sys
import numpy as np, cv2

def demo_preprocess(img, box, size=192, side=800):
    h, w, _ = img.shape
    b = np.array(box, dtype=np.float64)
    diff = abs(w - h)
    pad1, pad2 = (diff + 1) // 2, diff // 2
    if w > h:
        img = np.pad(img, ((pad1, pad2), (0, 0), (0, 0)), mode="constant")
        b[[1, 3]] += pad1
    elif h > w:
        img = np.pad(img, ((0, 0), (pad1, pad2), (0, 0)), mode="constant")
        b[[0, 2]] += pad1
    square = cv2.resize(img, (side, side))
    b *= side / img.shape[0]
    xc, yc = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
    s = max(b[2] - b[0], b[3] - b[1])
    left, right, top, bottom = xc - 0.75 * s, xc + 0.75 * s, yc - 0.75 * s, yc + 0.75 * s
    src = np.float32([[left, top], [left, bottom], [right, top]])
    dst = np.float32([[0, 0], [0, size - 1], [size - 1, 0]])
    crop = cv2.warpAffine(square, cv2.getAffineTransform(src, dst), (size, size))
    return square, crop, b

if __name__ == "__main__":
    folder, box = sys.argv[1], json.loads(sys.argv[2])
    square, crop, b = demo_preprocess(np.load(folder + "/photo.npy"), box)
    np.save(folder + "/square.npy", square)
    np.save(folder + "/crop.npy", crop)
    np.save(folder + "/box.npy", b)
    print(cv2.__version__)
"""


def run_demo_steps(img, box):
    """The demo's steps on `img`: (square, crop, box in the square, OpenCV version)."""
    python = os.environ.get("ARKIT_OPENCV_PYTHON") or sys.executable
    if python == sys.executable:
        pytest.importorskip("cv2", reason="OpenCV (opencv-python-headless) is not installed")
    with tempfile.TemporaryDirectory() as d:
        np.save(os.path.join(d, "photo.npy"), img)
        with open(os.path.join(d, "steps.py"), "w") as f:
            f.write(DEMO_STEPS)
        out = subprocess.run([python, os.path.join(d, "steps.py"), d, json.dumps(box)],
                             capture_output=True, text=True, check=True)
        load = lambda name: np.load(os.path.join(d, name))  # noqa: E731
        return load("square.npy"), load("crop.npy"), load("box.npy"), out.stdout.strip()


def photo(h, w, seed):
    # Smooth content with texture (faces are smooth; noise would make every resampling
    # difference look large), as RGB uint8.
    r = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([128 + 100 * np.sin(x / 17.0 + k) * np.cos(y / 23.0 - k) for k in range(3)], -1)
    return np.clip(base + r.normal(0, 12, (h, w, 3)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize(
    "shape, box",
    [
        ((800, 800), [300.0, 280.0, 460.0, 470.0]),  # the release's size: no pad, no resize
        ((480, 640), [200.5, 100.25, 330.0, 260.0]),  # wide: rows padded, upscaled
        ((1001, 600), [100.0, 400.0, 260.0, 590.0]),  # tall, odd difference
        ((1600, 1600), [500.0, 500.0, 900.0, 980.0]),  # a halving (OpenCV's area path)
        ((1234, 1999), [1500.0, 20.0, 1990.0, 600.0]),  # downscaled; the crop leaves the photo
    ],
)
def test_the_crop_is_the_official_demo_s(shape, box):
    # Against OpenCV 4.x (the official code's): the square and the crop bit for bit
    # (OpenCV's fixed-point resize weights and vector rounding, its area path for a
    # halving, and its warp are reproduced). Against OpenCV 5, whose warp computes in
    # float: the square within one grey level, the crop within 3 levels, 0.2 on average.
    img = photo(*shape, seed=sum(shape))
    square, crop, b, version = run_demo_steps(img, box)
    got = _native.photo_crop(img, box)
    np.testing.assert_allclose(got["box_square"], b, rtol=0, atol=1e-9)
    # The network's input: torchvision's ToTensor() then Normalize(ImageNet), in float32.
    mean = np.array([0.485, 0.456, 0.406], np.float32)[:, None, None]
    std = np.array([0.229, 0.224, 0.225], np.float32)[:, None, None]
    expected = (got["crop"].transpose(2, 0, 1).astype(np.float32) / np.float32(255) - mean) / std
    assert got["input"].shape == (3, 192, 192) and got["input"].dtype == np.float32
    np.testing.assert_allclose(got["input"], expected, rtol=0, atol=2e-6)
    if version.startswith("4."):
        assert np.array_equal(got["square"], square), version
        assert np.array_equal(got["crop"], crop), version
        return
    diff = np.abs(got["square"].astype(int) - square.astype(int))
    assert diff.max() <= 1 and diff.mean() < 0.01, (version, diff.max(), diff.mean())
    cdiff = np.abs(got["crop"].astype(int) - crop.astype(int))
    assert cdiff.max() <= 3 and cdiff.mean() < 0.2, (version, cdiff.max(), cdiff.mean())


@pytest.mark.parametrize("box", [[10.0, 10.0, 10.0, 10.0], [50.0, 0.0, 20.0, 30.0], [0.0, float("nan"), 5.0, 5.0]])
def test_a_box_with_no_extent_is_refused(box):
    with pytest.raises(_native.DataError, match="face box"):
        _native.photo_crop(photo(64, 64, 1), box)


def test_a_photo_that_is_not_rgb_is_refused():
    with pytest.raises(_native.DataError, match=r"photo_crop: photo \[8, 8, 4\]"):
        _native.photo_crop(np.zeros((8, 8, 4), np.uint8), [1.0, 1.0, 5.0, 5.0])

"""cv2.warpAffine on exactly the crops `tests/official_crop.rs` writes.

    ARKIT_OPENCV_PYTHON=/path/to/python cargo test --release --test official_crop

(the test runs `$ARKIT_OPENCV_PYTHON tests/official_crop_opencv.py DIR`), or by hand on
a folder it wrote: `python3 tests/official_crop_opencv.py DIR`.

For each dumped case, builds the official loader's transform (cv2.getAffineTransform of
the box corners (left, top), (left, bottom), (right, top) onto (0, 0), (0, S - 1),
(S - 1, 0)), warps the image and the 0/1 mask with cv2.warpAffine's defaults, and counts
the bytes and mask pixels where ours differ. Needs numpy and opencv-python-headless;
CI installs OpenCV 4.6 in a virtual environment for it. Exits with status 1 when any
byte or mask pixel differs. Our reproduction follows OpenCV 4's fixed point (the official code's
era); OpenCV 4.11 and later compute coordinates in float and differ on a few pixels.
"""
import json
import sys

import cv2
import numpy as np


def main(folder):
    meta = json.load(open(f"{folder}/cases.json"))
    w, h = meta["width"], meta["height"]
    image = np.fromfile(f"{folder}/image.bin", np.uint8).reshape(h, w, 3)
    mask = np.fromfile(f"{folder}/mask.bin", np.uint8).reshape(h, w)
    rgb_bad = mask_bad = rgb_total = mask_total = cases_bad = 0
    worst = 0
    for k, c in enumerate(meta["cases"]):
        s = c["size"]
        src = np.float32([[c["left"], c["top"]], [c["left"], c["bottom"]], [c["right"], c["top"]]])
        dst = np.float32([[0, 0], [0, s - 1], [s - 1, 0]])
        t = cv2.getAffineTransform(src, dst)
        want_rgb = cv2.warpAffine(image, t, (s, s))
        want_mask = cv2.warpAffine(mask, t, (s, s)) > 0
        got_rgb = np.fromfile(f"{folder}/rgb_{k}.bin", np.uint8).reshape(s, s, 3)
        got_mask = np.fromfile(f"{folder}/mask_{k}.bin", np.uint8).reshape(s, s) > 0
        d = np.abs(want_rgb.astype(int) - got_rgb.astype(int))
        rgb_bad += int((d > 0).sum())
        worst = max(worst, int(d.max()))
        mask_bad += int((want_mask != got_mask).sum())
        rgb_total += d.size
        mask_total += want_mask.size
        cases_bad += int((d > 0).any() or (want_mask != got_mask).any())
    print(f"OpenCV {cv2.__version__}: {len(meta['cases'])} crops, {cases_bad} with any difference")
    print(f"  image bytes differing: {rgb_bad} of {rgb_total} (largest difference {worst})")
    print(f"  mask pixels differing: {mask_bad} of {mask_total}")
    return cases_bad


if __name__ == "__main__":
    sys.exit(1 if main(sys.argv[1]) else 0)

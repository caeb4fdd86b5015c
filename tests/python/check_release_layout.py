"""Reads a dataset the way the official PyTorch loader does, with numpy alone, and
checks it is consistent. Used by tests/synth_numpy.rs when python3 with numpy exists.

For every row of ARKitFace_{train,test}.csv (ids read as strings): np.load the
_info.npz, take verts and R_t, project exactly as the official loader
(verts_homo @ R_t @ M_proj @ M1, divide by w, y = H - y) and compare with points2d;
check R_t == faceAnchortransform @ inv(cameratransform), tz < 0, translation ==
R_t[3, :3], and that the JPEG exists. Prints 'N passed, M failed'.
Usage: python3 check_release_layout.py DATASET_ROOT WIDTH HEIGHT
"""
import csv
import os
import sys

import numpy as np

root, width, height = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
f = 1.57443701
M_proj = np.array([[f, 0, 0, 0], [0, f, 0, 0], [0, 0, -0.99999976, -1.0], [0, 0, -0.001, 0]], dtype=np.float32)
M1 = np.array([[width / 2, 0, 0, 0], [0, height / 2, 0, 0], [0, 0, 1, 0], [width / 2, height / 2, 0, 1]])
passed = failed = 0
for split in ("train", "test"):
    path = os.path.join(root, "ARKitFace_list", "list", f"ARKitFace_{split}.csv")
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            s, a, i = row["subject_id"], row["facial_action"], row["img_id"]
            npz = os.path.join(root, f"ARKitFace_info_{split}", "info", s, a, f"{i}_info.npz")
            jpg = os.path.join(root, f"ARKitFace_image_{split}", "image", s, a, f"{i}_ar.jpg")
            try:
                M = np.load(npz)
                verts, R_t = M["verts"], M["R_t"]
                assert verts.shape == (1220, 3) and R_t.shape == (4, 4), "shapes"
                assert R_t[3, 2] < 0, "tz"
                homo = np.concatenate([verts, np.ones([1220, 1])], axis=1)
                v = homo @ R_t @ M_proj @ M1
                v = v / v[:, [3]]
                v[:, 1] = height - v[:, 1]
                err = np.abs(v[:, :2] - M["points2d"]).max()
                assert err < 1e-2, f"points2d differs by {err}"
                rt2 = M["faceAnchortransform"] @ np.linalg.inv(M["cameratransform"])
                assert np.abs(rt2 - R_t).max() < 1e-9, "faceAnchortransform"
                assert np.abs(M["translation"] - R_t[3, :3]).max() < 1e-12, "translation"
                assert np.abs(M["projectionMatrix"] - M_proj).max() < 1e-6, "projectionMatrix"
                assert os.path.getsize(jpg) > 0, "jpeg"
                passed += 1
            except Exception as e:  # report and go on
                print(f"{npz}: {e}")
                failed += 1
print(f"{passed} passed, {failed} failed")
sys.exit(1 if failed or not passed else 0)

"""A face's pose from a photo and a face box with onnxruntime, numpy and OpenCV only: no
arkit-tool, no torch. The recipe of docs/onnx.md ("From a photo to a pose, by hand"),
step for step:

    python docs/onnx_recipe.py EXPORT_DIR PHOTO "x0 y0 x1 y1" [SEED]

EXPORT_DIR is what `arkit-tool export-onnx` wrote; the box is in the photo's pixels;
SEED is the pixel sampler's seed (`predict --image --seed`, default 0; face k of photo
p uses SEED ^ (p << 32) ^ k). Prints JSON: `R_t` (the release's 4x4, row vectors),
`rvec`, `tvec_m` (OpenCV's), `inliers`, `choose`.
"""

import json
import sys

import cv2
import numpy as np
import onnxruntime as ort

MASK64 = (1 << 64) - 1
DEMO_SIDE = 800
DEMO_FOCAL = 1.57443701 * DEMO_SIDE / 2  # the release's projection on the 800-px square


# -- The seeded pixel sampler: SplitMix64 seeds xoshiro256++, a partial Fisher-Yates.
def splitmix64(state):
    state = (state + 0x9E3779B97F4A7C15) & MASK64
    z = state
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK64
    return state, z ^ (z >> 31)


def rotl(x, k):
    return ((x << k) | (x >> (64 - k))) & MASK64


class Xoshiro256pp:
    def __init__(self, seed):
        self.s, state = [], seed & MASK64
        for _ in range(4):
            state, value = splitmix64(state)
            self.s.append(value)

    def next_u64(self):
        s = self.s
        result = (rotl((s[0] + s[3]) & MASK64, 23) + s[0]) & MASK64
        t = (s[1] << 17) & MASK64
        s[2] ^= s[0]
        s[3] ^= s[1]
        s[1] ^= s[2]
        s[0] ^= s[3]
        s[2] ^= t
        s[3] = rotl(s[3], 45)
        return result

    def below(self, n):
        return (self.next_u64() * n) >> 64


def sample_points(n, m, seed):
    """M of n candidates: distinct and increasing when n > m, else 0..n-1 wrapped."""
    if n <= m:
        return [k % n for k in range(m)]
    idx, rng = list(range(n)), Xoshiro256pp(seed)
    for k in range(m):
        j = k + rng.below(n - k)
        idx[k], idx[j] = idx[j], idx[k]
    return sorted(idx[:m])


def main(export_dir, photo_path, box_text, seed=0):
    manifest = json.load(open(f"{export_dir}/onnx.json"))
    size, m, uv_scale = manifest["input_size"], manifest["points"], manifest["uv_scale"]
    mean, std = np.array(manifest["normalisation_mean"]), np.array(manifest["normalisation_std"])

    # 1. The photo, upright (cv2.imread applies the EXIF orientation), as RGB.
    photo = cv2.cvtColor(cv2.imread(photo_path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    h, w = photo.shape[:2]
    # 2. demo.py's square: black padding (the odd row or column on the top or left),
    #    resized to 800 px with INTER_LINEAR.
    padded_side = max(w, h)
    pad1 = (padded_side - min(w, h) + 1) // 2
    pad_left, pad_top = (0, pad1) if w > h else (pad1, 0)
    padded = np.zeros((padded_side, padded_side, 3), np.uint8)
    padded[pad_top:pad_top + h, pad_left:pad_left + w] = photo
    scale = DEMO_SIDE / padded_side
    square = cv2.resize(padded, (DEMO_SIDE, DEMO_SIDE), interpolation=cv2.INTER_LINEAR)
    # 3. The box in the square, the 0.75 rule, the crop by getAffineTransform/warpAffine.
    x0, y0, x1, y1 = [float(v) for v in box_text.replace(",", " ").split()]
    x0, x1 = (x0 + pad_left) * scale, (x1 + pad_left) * scale
    y0, y1 = (y0 + pad_top) * scale, (y1 + pad_top) * scale
    cx, cy, half = (x0 + x1) / 2, (y0 + y1) / 2, 0.75 * max(x1 - x0, y1 - y0)
    left, top, right, bottom = cx - half, cy - half, cx + half, cy + half
    src = np.float32([[left, top], [left, bottom], [right, top]])
    dst = np.float32([[0, 0], [0, size - 1], [size - 1, 0]])
    crop = cv2.warpAffine(square, cv2.getAffineTransform(src, dst), (size, size))
    # 4. Normalised, channels first; the dense graph.
    x = ((crop / 255.0 - mean) / std).transpose(2, 0, 1)[None].astype(np.float32)
    dense = ort.InferenceSession(f"{export_dir}/dense.onnx", providers=["CPUExecutionProvider"])
    seg, uv_map, image_features, uv_features = dense.run(
        ["seg_logits", "uv_map", "image_features", "uv_features"], {"image": x})
    # 5. The pixels: the mask's, in flat order (all pixels when empty), M of them.
    mask = (seg[0, 1] >= seg[0, 0]).reshape(-1)
    candidates = np.flatnonzero(mask) if mask.any() else np.arange(size * size)
    choose = candidates[sample_points(len(candidates), m, seed)].astype(np.int64)
    # 6. The points graph: each chosen pixel's canonical point (metres after / uv_scale).
    points_graph = ort.InferenceSession(f"{export_dir}/points.onnx", providers=["CPUExecutionProvider"])
    points = points_graph.run(["points"], {
        "image_features": image_features, "uv_features": uv_features, "uv_map": uv_map,
        "choose": choose[None]})[0][0] / uv_scale
    # 7. Each chosen pixel back in the square: OpenCV's rule, crop pixel i at crop
    #    coordinate i, so pixel 0 is the box's left edge and pixel S - 1 its right edge.
    #    A pixel chosen twice counts once.
    first = np.unique(choose, return_index=True)[1]
    keep = np.sort(first)
    i, j = choose[keep] % size, choose[keep] // size
    image_points = np.stack([left + i * (right - left) / (size - 1),
                             top + j * (bottom - top) / (size - 1)], axis=1)
    object_points = points[keep].astype(np.float64)
    # 8. PnP in the demo's camera (the square's pixels): RANSAC with an 8-px threshold,
    #    then Levenberg-Marquardt on the inliers.
    k = np.array([[DEMO_FOCAL, 0, DEMO_SIDE / 2], [0, DEMO_FOCAL, DEMO_SIDE / 2], [0, 0, 1]])
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        object_points, image_points, k, None, iterationsCount=100, reprojectionError=8.0,
        confidence=0.99, flags=cv2.SOLVEPNP_AP3P)
    if not ok:
        raise SystemExit("PnP failed")
    inliers = inliers[:, 0]
    # Refined on the inliers, the inliers chosen again with the refined pose (within 8
    # px), until they no longer change (as arkit-tool's PnP re-selects them).
    for _ in range(10):
        rvec, tvec = cv2.solvePnPRefineLM(object_points[inliers], image_points[inliers], k,
                                           None, rvec, tvec)
        projected = cv2.projectPoints(object_points, rvec, tvec, k, None)[0][:, 0]
        again = np.flatnonzero(np.linalg.norm(projected - image_points, axis=1) < 8.0)
        if np.array_equal(again, inliers) or len(again) < 4:
            break
        inliers = again
    # 9. The release's R_t from OpenCV's pose: [[R^T, 0], [t^T, 1]] @ diag(1, -1, -1, 1).
    r = cv2.Rodrigues(rvec)[0]
    rt = np.eye(4)
    rt[:3, :3], rt[3, :3] = r.T, tvec[:, 0]
    rt = rt @ np.diag([1.0, -1.0, -1.0, 1.0])
    print(json.dumps({"R_t": rt.tolist(), "rvec": rvec[:, 0].tolist(), "tvec_m": tvec[:, 0].tolist(),
                      "inliers": int(len(inliers)), "choose": choose.tolist()}))


if __name__ == "__main__":
    main(*sys.argv[1:4], *[int(s) for s in sys.argv[4:5]])

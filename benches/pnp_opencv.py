"""OpenCV's solvePnPRansac on exactly the scenes of `cargo bench --bench pnp`.

    PNP_BENCH_DUMP=/tmp/pnp cargo bench --bench pnp
    python3 benches/pnp_opencv.py /tmp/pnp

Prints the same columns as the Rust benchmark (median rotation error in degrees,
median translation error in mm, failures over 5 degrees, median time per solve in
microseconds, one thread), so the two are compared side by side on the same data.
Needs numpy and opencv-python-headless; not part of CI.
"""
import sys
import time

import cv2
import numpy as np


def rot_err_deg(a, b):
    m = a.T @ b
    c = np.clip((np.trace(m) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(c))


def main(folder):
    cv2.setNumThreads(1)
    f = 1.57443701 * 400.0
    k = np.array([[f, 0, 400.0], [0, f, 400.0], [0, 0, 1]])
    for tag in (0, 30):
        obj = np.load(f"{folder}/object_{tag}.npy")
        img = np.load(f"{folder}/image_{tag}.npy")
        truth = np.load(f"{folder}/truth_{tag}.npy")
        rots, trans, times, fails = [], [], [], 0
        for o, i, t in zip(obj, img, truth):
            best = float("inf")
            for _ in range(5):
                s = time.perf_counter()
                ok, rvec, tvec, _ = cv2.solvePnPRansac(o, i, k, None)
                best = min(best, time.perf_counter() - s)
            times.append(best * 1e6)
            if not ok:
                fails += 1
                continue
            r = cv2.Rodrigues(rvec)[0]
            e = rot_err_deg(r, t[:, :3])
            fails += e > 5
            rots.append(e)
            trans.append(np.linalg.norm(tvec[:, 0] - t[:, 3]) * 1e3)
        print(
            f"OpenCV {cv2.__version__} solvePnPRansac {tag}%: "
            f"{np.median(rots):.4f} deg {np.median(trans):.3f} mm "
            f"{fails} failures {np.median(times):.1f} us"
        )


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "/tmp/pnp")

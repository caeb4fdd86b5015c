"""OpenCV's FFmpeg reads an MP4 that arkit-tool wrote (tests/video.rs): the frame count
and each frame against arkit-tool's own decode (PNGs); then writes an MPEG-4 Part 2
('mp4v') clip for the refusal check. Usage: video_opencv.py CLIP.mp4 OURS_DIR OUT.mp4"""

import sys
from pathlib import Path

import cv2
import numpy as np

clip, ours, other = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
cap = cv2.VideoCapture(clip)
frames, worst = 0, 0.0
while True:
    ok, bgr = cap.read()
    if not ok:
        break
    mine = cv2.imread(str(ours / f"frame-{frames:06d}.png"))
    if mine is None or mine.shape != bgr.shape:
        print(f"frame {frames}: shapes differ or no PNG")
        sys.exit(1)
    diff = float(np.abs(mine.astype(np.int16) - bgr.astype(np.int16)).mean())
    worst = max(worst, diff)
    frames += 1
print(f"{frames} frames, fps {cap.get(cv2.CAP_PROP_FPS):.2f}, worst mean abs difference {worst:.3f}")
w = cv2.VideoWriter(other, cv2.VideoWriter_fourcc(*"mp4v"), 30, (64, 48))
for i in range(10):
    w.write(np.full((48, 64, 3), i * 20, np.uint8))
w.release()

"""Frames a second of photo-to-pose on this machine, three runtimes side by side, printed
as `ratio:` lines.

    python python/bench/predict.py [--frames 12] [--official DIR] [--threads 2]

Makes folders of synthetic frames (`arkit-tool synth --group-photo`, 1280x720, 1 and 3
faces, a new scene each frame) and times, for the `tiny` config (the shipped
models/tiny-synthetic) and the `paper` config (random weights: no trained paper model
ships), with the face detector on every frame and on every 5th (boxes carried to the
frames between), each on `--threads` threads, each cell the best of `--rounds` runs
(on a shared machine a run that lost a core is noise, not speed):

- ours: `arkit-tool predict --model M --image FOLDER` (with `--boxes` for the carried
  frames), the whole process: JPEG decode, detector, the network (the faces of a frame
  in one batch, one pass), PnP, the JSON report. Frames a second in the steady state:
  `(N - 1) / (T(N frames) - T(1 frame))`, so the model's loading is left out;
- onnxruntime on our ONNX export (`arkit-tool export-onnx`), through
  `arkit_tool.photo.predict_photo` and `arkit_tool.onnx.OnnxPerspNet` (the same
  decode, detector and PnP, from the Rust core; the faces of a frame in one batch);
- demo.py: the official `demo.py`'s steps per frame in PyTorch on the CPU, with the
  official network (`models/network.py` of a checkout of cbsropenproject/6dof_face, not
  part of this repository: `--official DIR`; skipped without it): OpenCV decode, pad
  and resize to 800 px, `cv2.warpAffine` crops, the dense network for the mask, the
  whole network again, `grid_sample`, softmax, `cv2.solvePnPRansac` per face; the boxes
  from our detector on the same schedule (demo.py has none of its own). The official
  network has one size: the `paper` rows only.

With `--official`, the paper config's random weights are the official network's (made
with `torch.manual_seed(0)`, imported with `arkit-tool import-weights`), so all three
run the same weights; without it, a paper model is trained one step from a synthetic
dataset. The vertex UVs the official network reads its UV map at are a grid here (the
timing does not depend on them).

Then the network alone, ms a crop (random crops, 1 and 3 in a batch; the best of
`--reps`): onnxruntime,
PyTorch (the official network: one pass, and demo.py's two), and candle through
`cargo bench --bench perspnet -- network MODEL` (skipped with `--no-cargo`).

Needs the arkit_tool package with its native module (python/src and a built
_native), onnxruntime, and for the demo.py column torch and cv2.
"""

import argparse
import gc
import itertools
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
EVERY = 5
RUNS = itertools.count()


def sh(*args, env=None):
    r = subprocess.run([str(a) for a in args], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        sys.exit(f"{' '.join(str(a) for a in args)} failed:\n{r.stderr}")
    return r.stdout


def official_network(checkout, seed=0):
    """The official DeformNetUV2 with random weights (its init, `torch.manual_seed(seed)`),
    built on the CPU without the ImageNet download (as tests/python/official_equality.py)."""
    import torch

    to = torch.Tensor.to

    def cpu_to(self, *args, **kw):
        if kw.get("device") == "cuda":
            kw["device"] = "cpu"
        return to(self, *args, **kw)

    torch.Tensor.to = cpu_to
    sys.path.insert(0, str(checkout))
    import models.resnet as resnet

    resnet18 = resnet.resnet18
    resnet.resnet18 = lambda pretrained=False, **kw: resnet18(False, **kw)
    from models.network import DeformNetUV2

    torch.manual_seed(seed)
    side = math.ceil(math.sqrt(1220))
    uv = [((i % side + 0.5) / side, (i // side + 0.5) / side) for i in range(1220)]
    grid = torch.tensor(uv, dtype=torch.float32).mul(2).sub(1).reshape(1, 1, 1220, 2)
    net = DeformNetUV2(grid)
    torch.Tensor.to = to
    net.eval()
    return net


def make_frames(tool, folder, faces, n):
    folder.mkdir(parents=True)
    for i in range(n):
        sh(tool, "synth", "--group-photo", folder / f"frame-{i:04}.jpg", "--faces", faces,
           "--size", "1280x720", "--seed", 1000 + i)
    frames = sorted(folder.glob("*.jpg"))
    for extra in folder.glob("*.json"):
        extra.rename(folder.parent / f"{folder.name}-{extra.name}")
    return frames


def detections(frames):
    from arkit_tool.photo import detect_faces, read_photo

    return [[b for b, _ in detect_faces(read_photo(f))] for f in frames]


def ours(tool, model, frames, found, every, threads, work):
    """Frames a second of `predict --image` on the frames, steady state."""
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))

    def run(subset, tag):
        folder = work / f"ours-{tag}"
        folder.mkdir()
        for f in subset:
            os.symlink(f, folder / f.name)
        args = [tool, "predict", "--model", model, "--image", folder, "--output", work / f"ours-{tag}.json"]
        carried = {f.name: found[(k // every) * every] for k, f in enumerate(subset) if k % every}
        if carried:
            boxes = work / f"ours-{tag}-boxes.json"
            boxes.write_text(json.dumps(carried))
            args += ["--boxes", boxes]
        t = time.perf_counter()
        sh(*args, env=env)
        return time.perf_counter() - t

    tag = str(next(RUNS))
    t1 = min(run(frames[:1], tag + "a"), run(frames[:1], tag + "b"))
    tn = run(frames, tag + "n")
    return (len(frames) - 1) / max(tn - t1, 1e-9)


def onnx_fps(folder, frames, found, every, threads):
    import onnxruntime as ort
    from arkit_tool.onnx import OnnxPerspNet
    from arkit_tool.photo import detect_faces, predict_photo, read_photo

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    net = OnnxPerspNet(folder, session_options=so)
    predict_photo(read_photo(frames[0]), found[0], network=net)  # warm-up
    t = time.perf_counter()
    boxes = None
    for k, f in enumerate(frames):
        photo = read_photo(f)
        if k % every == 0:
            boxes = [b for b, _ in detect_faces(photo)]
        predict_photo(photo, boxes, network=net)
    return len(frames) / (time.perf_counter() - t)


def demo_fps(net, frames, every, threads):
    """demo.py's steps per frame (its own code is not run: it needs CUDA and a
    checkpoint); the boxes from our detector."""
    import cv2
    import torch
    import torch.nn.functional as F
    from arkit_tool.photo import detect_faces

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    size, n_pts, side = 192, 1024, 800
    mean = np.array([0.485, 0.456, 0.406], dtype=np.float32)
    std = np.array([0.229, 0.224, 0.225], dtype=np.float32)
    f = 1.574437 * side / 2
    k_img = np.array([[f, 0, side / 2], [0, f, side / 2], [0, 0, 1]])
    rng = np.random.default_rng(0)

    def frame(path, boxes):
        img = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        h, w, _ = img.shape
        b = np.array(boxes, dtype=np.float64).reshape(-1, 4)
        d = abs(w - h)
        pad = ((d + 1) // 2, d // 2)
        if w > h:
            img = np.pad(img, (pad, (0, 0), (0, 0)))
            b[:, [1, 3]] += pad[0]
        elif h > w:
            img = np.pad(img, ((0, 0), pad, (0, 0)))
            b[:, [0, 2]] += pad[0]
        scale = side / img.shape[0]
        img = cv2.resize(img, (side, side))
        b *= scale
        dst = np.float32([[0, 0], [0, size - 1], [size - 1, 0]])
        crops, inverse = [], []
        for x0, y0, x1, y1 in b:
            cx, cy, s = (x0 + x1) / 2, (y0 + y1) / 2, 0.75 * max(x1 - x0, y1 - y0)
            src = np.float32([[cx - s, cy - s], [cx - s, cy + s], [cx + s, cy - s]])
            crop = cv2.warpAffine(img, cv2.getAffineTransform(src, dst), (size, size))
            crops.append(((crop.astype(np.float32) / 255 - mean) / std).transpose(2, 0, 1))
            inverse.append(cv2.getAffineTransform(dst, src))
        if not crops:
            return
        x = torch.from_numpy(np.stack(crops))
        with torch.no_grad():
            _, seg, _, _ = net.cnn(x)
            masks = torch.argmax(seg, 1).numpy()
            chooses = []
            for m in masks:
                c = m.flatten().nonzero()[0]
                if len(c) > n_pts:
                    keep = np.zeros(len(c), dtype=int)
                    keep[:n_pts] = 1
                    rng.shuffle(keep)
                    c = c[keep.nonzero()]
                else:
                    c = np.pad(c, (0, n_pts - len(c)), "wrap")
                chooses.append(c)
            choose = torch.from_numpy(np.stack(chooses).astype(np.int64))
            assign, _, uv = net(x, choose)
            verts = F.grid_sample(uv, net.grid.expand(len(crops), -1, -1, -1), align_corners=False)
            verts = verts.squeeze(2).permute(0, 2, 1) / 9.0
            points = torch.bmm(F.softmax(assign, dim=2), verts).numpy()
        for i, c in enumerate(choose.numpy()):
            c, idx = np.unique(c, return_index=True)
            pts2d = np.stack([c % size, c // size], 1).astype(np.float64)
            w_, b_ = inverse[i].T[:2], inverse[i].T[2]
            cv2.solvePnPRansac(points[i, idx].astype(np.float64), pts2d @ w_ + b_, k_img, None)

    def boxes_of(path):
        rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        return [b for b, _ in detect_faces(rgb)]

    frame(frames[0], boxes_of(frames[0]))  # warm-up
    t = time.perf_counter()
    boxes = None
    for k, path in enumerate(frames):
        if k % every == 0:
            boxes = boxes_of(path)
        frame(path, boxes)
    return len(frames) / (time.perf_counter() - t)


def best_ms(f, reps):
    """The fastest of `reps` calls, ms: on a shared machine a call that lost its core
    (an OpenMP barrier waiting on a thread that was not running) is noise, not speed."""
    t = []
    for _ in range(reps):
        s = time.perf_counter()
        f()
        t.append((time.perf_counter() - s) * 1e3)
    return min(t)


def network_alone(name, onnx_dir, net, threads, reps, model, cargo):
    """The network alone, ms a crop: each runtime timed with no other runtime's threads
    alive (onnxruntime's spin after a run; so do OpenMP's)."""
    import gc

    import onnxruntime as ort
    from arkit_tool.onnx import OnnxPerspNet

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    o = OnnxPerspNet(onnx_dir, session_options=so)
    s = o.input_size
    rng = np.random.default_rng(0)
    crops = {b: rng.standard_normal((b, 3, s, s)).astype(np.float32) for b in (1, 3)}
    lines = {}
    for b, x in crops.items():
        o.predict(x, list(range(b)))
        lines[b] = (f"network alone {name}, {b} crop(s) a batch, ms a crop: onnxruntime "
                    f"{best_ms(lambda: o.predict(x, list(range(b))), reps) / b:.1f}")
    del o
    gc.collect()
    time.sleep(1)
    if net is not None:
        import torch

        torch.set_num_threads(threads)
        for b, x in crops.items():
            xt = torch.from_numpy(x)
            ch = torch.from_numpy(rng.integers(0, s * s, (b, 1024)))
            with torch.no_grad():
                net(xt, ch)
                one = best_ms(lambda: net(xt, ch), reps) / b
                two = best_ms(lambda: (net.cnn(xt), net(xt, ch)), reps) / b
            lines[b] += f", PyTorch {one:.1f} (demo.py's two passes {two:.1f})"
    print("\n".join(lines.values()))
    if cargo:
        env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
        r = subprocess.run(["cargo", "bench", "--bench", "perspnet", "--", "network", str(model), str(reps)],
                           cwd=ROOT, capture_output=True, text=True, env=env)
        found = [l for l in r.stdout.splitlines() if l.startswith(("network", "ratio"))]
        print("\n".join(found) if found else f"candle: cargo bench failed:\n{r.stderr[-2000:]}")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--faces", default="1,3")
    p.add_argument("--configs", default="tiny,paper")
    p.add_argument("--reps", type=int, default=5, help="repetitions of the network-alone timings (the best is kept)")
    p.add_argument("--rounds", type=int, default=2, help="runs over the frames a cell (the best is kept)")
    p.add_argument("--bin", default=str(pathlib.Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target")) / "release" / "arkit-tool"))
    p.add_argument("--official", metavar="DIR",
                   help="a checkout of the official code (cbsropenproject/6dof_face; not part of this "
                        "repository) for the demo.py column; needs torch and cv2")
    p.add_argument("--no-cargo", action="store_true", help="skip candle's network-alone line")
    a = p.parse_args()
    tool = pathlib.Path(a.bin).resolve()
    if not tool.exists():
        sys.exit(f"no arkit-tool binary at {tool} (cargo build --release, or --bin)")
    work = pathlib.Path(tempfile.mkdtemp(prefix="predict-bench-"))
    faces = [int(x) for x in a.faces.split(",")]
    configs = a.configs.split(",")

    official = official_network(a.official) if a.official else None
    models = {"tiny": ROOT / "models" / "tiny-synthetic"}
    if "paper" in configs:
        models["paper"] = work / "paper-model"
        if official is not None:
            import torch

            torch.save(official.state_dict(), work / "official.pth")
            sh(tool, "import-weights", work / "official.pth", "--config", "paper", "--output", models["paper"])
        else:
            sh(tool, "synth", "--output", work / "synth", "--subjects", "1", "--images-per-subject", "2",
               "--size", "256x256")
            sh(tool, "convert", "--input", work / "synth", "--output", work / "pq")
            sh(tool, "render", "--dataset", work / "pq", "--size", "192", "--points", "1024", "--output", work / "t192")
            sh(tool, "train", "--dataset", work / "pq", "--targets", work / "t192", "--config", "paper",
               "--steps", "1", "--batch", "1", "--output", models["paper"])
    onnx = {}
    for c in configs:
        onnx[c] = work / f"onnx-{c}"
        sh(tool, "export-onnx", "--model", models[c], "--output", onnx[c])

    print(f"{a.frames} frames of 1280x720 a run, {a.threads} threads each; frames a second "
          f"(ms a frame); paper = random weights{' (the official network init, same in all three)' if official is not None else ''}")
    print(f"{'config':6} {'faces':>5} {'detector':>9} | {'ours':>14} | {'onnxruntime':>14} | {'demo.py':>14}")
    ratios = []
    for nf in faces:
        frames = make_frames(tool, work / f"frames-{nf}", nf, a.frames)
        found = detections(frames)
        for c in configs:
            for every in (1, EVERY):
                fo = max(ours(tool, models[c], frames, found, every, a.threads, work) for _ in range(a.rounds))
                fx = max(onnx_fps(onnx[c], frames, found, every, a.threads) for _ in range(a.rounds))
                gc.collect()
                fd = (max(demo_fps(official, frames, every, a.threads) for _ in range(a.rounds))
                      if (official is not None and c == "paper") else None)
                cell = lambda v: f"{v:6.1f} ({1e3 / v:5.0f})" if v else f"{'-':>14}"
                det = "every" if every == 1 else f"every {every}"
                print(f"{c:6} {nf:>5} {det:>9} | {cell(fo)} | {cell(fx)} | {cell(fd)}", flush=True)
                what = f"{c}, {nf} face(s), detector {det}"
                if fd:
                    ratios.append(f"ratio: photo to pose {what}: ours / demo.py frames a second = {fo / fd:.2f}x (goal 3x)")
                ratios.append(f"ratio: photo to pose {what}: ours / onnxruntime frames a second = {fo / fx:.2f}x")
    print("\n".join(ratios))
    for c in configs:
        network_alone(c, onnx[c], official if c == "paper" else None, a.threads, a.reps, models[c], not a.no_cargo)


if __name__ == "__main__":
    main()

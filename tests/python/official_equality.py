"""Holds our PerspNet against the official PyTorch network, weight for weight.

Builds the official `DeformNetUV2` (models/network.py of the official code, which is not
part of this repository: give its folder) with random weights and random batch-norm
statistics, saves its state_dict with torch.save, imports it with `arkit-tool
import-weights --config paper`, runs `arkit-tool predict --model ... --dump` on a small
synthetic dataset, runs the official network in eval mode on the dumped inputs (the
normalised crops and the chosen pixels) and compares the segmentation logits, the UV
map, the assignment matrix and M X. Then `arkit-tool export-weights` of the imported
model is loaded into a fresh official network with strict=True and compared with the
original state_dict, entry for entry.

usage: official_equality.py OFFICIAL_CODE_DIR [--tool target/release/arkit-tool] [--samples N]
       (or OFFICIAL_CODE=DIR). Prints SKIPPED and exits 0 without torch or the code.
Exit status 1 if any output differs by more than --tolerance (default 1e-4) relative
to the largest magnitude of that output.
"""
import argparse
import os
import subprocess
import sys
import tempfile

here = os.path.dirname(os.path.abspath(__file__))


def skip(why):
    print(f"SKIPPED: {why}")
    sys.exit(0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("official", nargs="?", default=os.environ.get("OFFICIAL_CODE"))
    ap.add_argument("--tool", default=os.path.join(here, "..", "..", "target", "release", "arkit-tool"))
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--tolerance", type=float, default=1e-4)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    try:
        import numpy as np
        import torch
        import torch.nn.functional as F
    except ImportError as e:
        skip(f"no torch/numpy ({e})")
    if not a.official or not os.path.isfile(os.path.join(a.official, "models", "network.py")):
        skip("give the official code's folder (with models/network.py) as the argument or OFFICIAL_CODE")
    sys.path.insert(0, here)
    from torch_save_state_dict import read_safetensors

    # The official network builds its position encoding on 'cuda' and downloads
    # ImageNet weights: on a CPU without network, keep the tensor on the CPU and
    # build the encoder without the download (its weights are replaced below anyway).
    to = torch.Tensor.to

    def cpu_to(self, *args, **kw):
        if kw.get("device") == "cuda":
            kw["device"] = "cpu"
        return to(self, *args, **kw)

    torch.Tensor.to = cpu_to
    sys.path.insert(0, a.official)
    import models.resnet as resnet

    resnet18 = resnet.resnet18
    resnet.resnet18 = lambda pretrained=False, **kw: resnet18(False, **kw)
    from models.network import DeformNetUV2

    torch.manual_seed(a.seed)
    work = tempfile.mkdtemp(prefix="perspnet-equality-")
    tool = os.path.abspath(a.tool)

    def run(*args):
        r = subprocess.run([tool, *args], capture_output=True, text=True)
        if r.returncode != 0:
            sys.exit(f"arkit-tool {' '.join(args)} failed:\n{r.stderr}")
        return r

    # A grid is needed to build the network; the real one comes from the dump.
    net = DeformNetUV2(torch.zeros(1, 1, 1220, 2))
    with torch.no_grad():
        for name, p in net.named_parameters():
            p.copy_(torch.randn_like(p) * (0.05 if p.dim() > 1 else 0.2) + (1.0 if name.endswith("bn1.weight") else 0.0))
        for name, b in net.named_buffers():
            if name.endswith("running_mean"):
                b.copy_(torch.randn_like(b) * 0.1)
            elif name.endswith("running_var"):
                b.copy_(torch.rand_like(b) + 0.5)
            elif name.endswith("num_batches_tracked"):
                b.fill_(17)
    state = net.state_dict()
    pth = os.path.join(work, "official.pth")
    torch.save(state, pth)
    model = os.path.join(work, "model")
    run("import-weights", pth, "--config", "paper", "--output", model)

    data = os.path.join(work, "synth")
    pq = os.path.join(work, "pq")
    run("synth", "--output", data, "--subjects", "2", "--images-per-subject", str(max(1, (a.samples + 1) // 2)),
        "--size", "256x256", "--seed", str(a.seed))
    run("convert", "--input", data, "--output", pq)
    dump = os.path.join(work, "dump.npz")
    run("predict", "--model", model, "--dataset", pq, "--split", "all",
        "--output", os.path.join(work, "pred.parquet"), "--dump", dump)

    d = np.load(dump)
    grid = torch.from_numpy(d["vertex_uv"] * 2 - 1).float().reshape(1, 1, -1, 2)
    net.grid = grid
    net.eval()
    keys = sorted({k.rsplit("/", 1)[0] for k in d.files if k != "vertex_uv"})
    worst = {}
    with torch.no_grad():
        for key in keys:
            img = torch.from_numpy(d[key + "/image"]).unsqueeze(0)
            choose = torch.from_numpy(d[key + "/choose"]).long().unsqueeze(0)
            assign, seg, uv = net(img, choose)
            m = F.softmax(assign, dim=2)
            x = F.grid_sample(uv, grid, align_corners=False).squeeze(2).transpose(1, 2)
            theirs = {"seg_logits": seg[0], "uv_map": uv[0], "assignment": m[0], "points": (m @ x)[0]}
            for name, t in theirs.items():
                ours = torch.from_numpy(d[f"{key}/{name}"])
                diff = (ours - t).abs().max().item()
                rel = diff / max(t.abs().max().item(), 1e-30)
                w = worst.get(name, (0.0, 0.0))
                worst[name] = (max(w[0], diff), max(w[1], rel))
    print(f"{len(keys)} samples, paper config, eval mode (batch-norm running statistics)")
    failed = False
    for name, (diff, rel) in worst.items():
        ok = rel <= a.tolerance
        failed |= not ok
        print(f"  {name:11s} max |ours - official| {diff:.3e}  relative to the largest value {rel:.3e}  {'ok' if ok else 'FAIL'}")

    # export -> strict load into a fresh official network, entry for entry.
    exported = os.path.join(work, "exported.safetensors")
    run("export-weights", model, "--output", exported)
    fresh = DeformNetUV2(grid)
    back = read_safetensors(exported)
    fresh.load_state_dict(back, strict=True)
    sd = fresh.state_dict()
    same = all(torch.equal(sd[k], state[k]) for k in state if not k.endswith("num_batches_tracked"))
    print(f"export-weights: {len(back)} entries, strict load_state_dict ok, parameters and statistics {'bit-identical' if same else 'DIFFER'}")
    failed |= not same or len(back) != len(state)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()

"""The official train.py's DataLoader with worker processes, side by side with the official
loader under the same DataLoader, printed as `ratio:` lines.

    python python/bench/dataloader_workers.py --official DIR [--samples 1024]
        [--workers 0,2[,6]] [--batch 16,64] [--rounds 3] [--scaling 1,2]

Makes an 800x800 synthetic dataset with the arkit-tool binary (the real topology when the
resource files are there) and its default crop stores, then times training epochs of
three loaders, each a `torch.utils.data.DataLoader` built as the official
`CustomDatasetDataLoader` builds it (shuffle, `drop_last`, the default collate, workers
started anew each epoch: not persistent):

- `official`: the official `ARKitDataset` (a checkout of cbsropenproject/6dof_face with
  its Cython rasterizers built, `--official DIR`; not part of this repository);
- `train.py path`: the dataset class `python -m arkit_tool.official` gives train.py
  (`ARKitFaceDataset(compat="official", corr="dense")` on the `train` split, which is the
  official loader's train list);
- `ds.loader`: our rules with sparse correspondences through `ds.loader(B, shuffle=True,
  num_workers=W, drop_last=True)`.

The training process does what the official `set_input` does with each batch: `.to(device)`
of every tensor it reads (the CPU here; a `CorrespondenceMatrix` builds its dense matrix
then), keeping them until the next batch's have been made, as the model's attributes
do. Figures, per sample: the epoch's wall time (worker start-up included, as
train.py pays it; the time to the first batch is printed too), the steady state's (from
an epoch's first batch to its last: the rate of an epoch of the release's size, where
the start-up is spread over 11,000 batches), and the training process's own CPU time
(`time.process_time`) spent receiving
batches (`next()` on the loader) and in `set_input`. For each number of workers and batch
size the three loaders run in turn, an epoch each, `--rounds` times (after one warm epoch
each), and the median ratio is printed. `--scaling` times our two loaders alone for each
number of workers listed (samples a second, batch 64). torch threads: 1 in every process.
"""

import argparse
import os
import pathlib
import subprocess
import sys
import tempfile
import time
import types

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))

# What the official PerspNetModel.set_input moves to its device.
SET_INPUT = ["img", "choose", "model", "uvmap", "nocs", "mask", "corr_mat"]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--samples", type=int, default=1024)
    p.add_argument("--resources", default=str(ROOT.parent / "shared" / "arkitface-resources"))
    p.add_argument("--bin", default=str(ROOT / "target" / "release" / "arkit-tool"))
    p.add_argument("--official", metavar="DIR",
                   help="a checkout of the official code with its Cython rasterizers built "
                        "(without it only our loaders are timed, and no ratio is printed)")
    p.add_argument("--workers", default="0,2,6" if (os.cpu_count() or 1) >= 6 else "0,2",
                   help="numbers of DataLoader workers, comma-separated (default 0,2, and 6 (train.py's "
                        "default) on a machine with at least six cores)")
    p.add_argument("--batch", default="16,64", help="batch sizes, comma-separated")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--scaling", default="1,2",
                   help="numbers of workers to time our train.py path alone with (empty: none)")
    a = p.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    import arkit_tool
    from arkit_tool.official import OfficialScriptsDataset
    from dataloader import synthetic_dataset

    tmp = pathlib.Path(tempfile.mkdtemp())
    data, res, n = synthetic_dataset(a.bin, tmp, a.samples, a.resources)
    for compat in ["official", "exact"]:
        subprocess.run([a.bin, "crops", "--dataset", data, "--compat", compat, *res], check=True,
                       stdout=subprocess.DEVNULL)
    print(f"dataset: {n} samples, 800x800, topology: {'real' if res else 'built-in'}, default crop stores; "
          f"{os.cpu_count()} cores; torch {torch.__version__}")

    official = None
    if a.official:
        from dataloader import official_datasets  # noqa: E402

        official = official_datasets(pathlib.Path(a.official), tmp / "release")["train"]
        os.chdir(a.official)  # the official code opens its files relative to its checkout

    def make(kind, workers, batch):
        kw = dict(batch_size=batch, shuffle=True, num_workers=workers, drop_last=True)
        if kind == "official":
            return torch.utils.data.DataLoader(official, **kw), SET_INPUT
        if kind == "train.py path":
            # The class `python -m arkit_tool.official` gives train.py, with the options
            # train.py passes it (a sample the official rules cannot crop is reported and
            # left out, as there).
            opt = types.SimpleNamespace(
                isTrain=True, arkittool_dataset=str(data), arkittool_train_split="train",
                arkittool_test_split="test", arkittool_compat="official", arkittool_seed=0,
                arkittool_crop_store="auto", img_size=192, n_pts=1024, batch_size=batch,
                max_dataset_size=float("inf"), debug=False)
            return torch.utils.data.DataLoader(OfficialScriptsDataset(opt), **kw), SET_INPUT
        ds = arkit_tool.ARKitFaceDataset(data, split="train", mode="train", compat="exact", corr="sparse")
        keys = ["img", "choose", "model", "uvmap", "nocs", "mask", "corr_ids", "corr_weights"]
        return ds.loader(batch, shuffle=True, num_workers=workers, drop_last=True), keys

    kinds = (["official"] if official is not None else []) + ["train.py path", "ds.loader"]
    workers_list = [int(x) for x in a.workers.split(",") if x]
    batches = [int(x) for x in a.batch.split(",") if x]
    for workers in workers_list:
        for batch in batches:
            loaders = {k: make(k, workers, batch) for k in kinds}
            for k in kinds:  # a warm epoch each: imports, first calls, the page cache
                epoch(*loaders[k])
            rounds = {k: [] for k in kinds}
            for _ in range(a.rounds):
                for k in kinds:
                    rounds[k].append(epoch(*loaders[k]))
            for k in kinds:
                walls = sorted(r[0] for r in rounds[k])
                recv = sorted(r[1] for r in rounds[k])
                setin = sorted(r[2] for r in rounds[k])
                start = sorted(r[3] for r in rounds[k])
                steady = sorted(r[4] for r in rounds[k])
                mid = a.rounds // 2
                print(f"{k}, {workers} workers, batch {batch}: {walls[mid]:.3f} ms a sample "
                      f"({1e3 / walls[mid]:.0f} samples/s; rounds {', '.join(f'{w:.3f}' for w in walls)}); "
                      f"steady {steady[mid]:.3f} ms; training process: receiving {recv[mid]:.3f} ms, "
                      f"set_input {setin[mid]:.3f} ms a sample; first batch after {start[mid]:.0f} ms")
            if official is not None:
                for k in kinds[1:]:
                    for what, at in (("epoch", 0), ("steady state", 4)):
                        ratios = sorted(o[at] / r[at] for o, r in zip(rounds["official"], rounds[k]))
                        each = ", ".join(f"{x:.1f}x" for x in ratios)
                        print(f"ratio: official / {k}, {workers} workers, batch {batch}, {what}, in turn "
                              f"(median of {a.rounds}: {each}) = {ratios[a.rounds // 2]:.1f}x")
            del loaders

    scaling = [int(x) for x in a.scaling.split(",") if x]
    for kind in ["train.py path", "ds.loader"] if scaling else []:
        base = None
        for workers in scaling:
            loader, keys = make(kind, workers, 64)
            epoch(loader, keys)
            runs = [epoch(loader, keys) for _ in range(a.rounds)]
            rate = 1e3 / sorted(r[0] for r in runs)[a.rounds // 2]
            steady = 1e3 / sorted(r[4] for r in runs)[a.rounds // 2]  # nan: one batch an epoch
            base = base or (rate, steady)
            print(f"scaling: {kind}, batch 64, {workers} workers: {rate:.0f} samples/s "
                  f"(steady state {steady:.0f})")
            print(f"ratio: {kind} {workers} workers / {scaling[0]} workers, samples a second = "
                  f"{rate / base[0]:.2f} (steady state {steady / base[1]:.2f})")


def epoch(loader, keys):
    """One epoch through `loader` as train.py runs it: (wall ms a sample, the training
    process's CPU ms a sample receiving batches, its CPU ms a sample in set_input, ms
    from the epoch's start to its first batch: the workers' start-up, and the steady
    state's wall ms a sample: between the first batch and the last)."""
    n = 0
    receiving = setting = 0.0
    wall = time.perf_counter()
    first = held = None
    it = iter(loader)
    while True:
        c0 = time.process_time()
        try:
            batch = next(it)
        except StopIteration:
            break
        c1 = time.process_time()
        now = time.perf_counter()
        if first is None:
            first, first_n = now - wall, None
        moved = [batch[k].to("cpu") for k in keys]
        c2 = time.process_time()
        receiving += c1 - c0
        setting += c2 - c1
        n += len(moved[0])
        if first_n is None:
            first_n = n
        last, last_n = now, n
        # The model keeps the batch's tensors (`self.img = ...`) until the next batch's
        # `set_input` has replaced them.
        held = moved  # noqa: F841
        del batch, moved
    end = time.perf_counter()
    del it, held
    # Steady state: from the first batch received to the last, the samples of the
    # batches after the first (an epoch of the release's size runs at this rate).
    steady = (last - (wall + first)) / (last_n - first_n) if last_n > first_n else float("nan")
    return (end - wall) / n * 1e3, receiving / n * 1e3, setting / n * 1e3, first * 1e3, steady * 1e3


if __name__ == "__main__":
    main()

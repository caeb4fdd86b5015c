"""Run by test_cloud.py under `torchrun --standalone --nproc_per_node=2` (gloo, CPU):
on each rank, the loader over the bucket (2 workers) gives the batches of the loader
over the folder (2 workers), two epochs, in the same order; a state saved from the
bucket mid-epoch resumes from the folder. Arguments: FOLDER URL OUT_DIR."""

import json
import sys

import torch
import torch.distributed as dist

from arkit_tool import ARKitFaceDataset

BATCH = 2


def make(path):
    return ARKitFaceDataset(path, split=None, mode="train", compat="official", img_size=64, n_pts=32,
                            corr="sparse")


def loader(path):
    return make(path).loader(BATCH, shuffle=True, num_workers=2, multiprocessing_context="fork")


def same(a, b):
    assert len(a) == len(b), (len(a), len(b))
    for x, y in zip(a, b):
        for k in x:
            assert torch.equal(x[k], y[k]), k


def main():
    folder, url, out = sys.argv[1], sys.argv[2], sys.argv[3]
    dist.init_process_group("gloo")
    rank = dist.get_rank()
    a, b = loader(folder), loader(url)
    compared = 0
    for _ in range(2):
        fa, fb = list(a), list(b)
        same(fa, fb)
        compared += len(fa)
    indices = a.sampler.indices(0)
    # Resume across backends: two batches from the bucket, the rest from the folder.
    c = loader(url)
    it = iter(c)
    head = [next(it) for _ in range(2)]
    state = json.loads(json.dumps(c.state_dict()))
    del it, c
    d = make(folder).loader(BATCH, shuffle=True)
    d.load_state_dict(state)
    want = list(make(folder).loader(BATCH, shuffle=True))
    same(head + list(d), want)
    with open(f"{out}/rank{rank}.json", "w") as f:
        json.dump({"rank": rank, "batches_compared": compared, "indices": indices}, f)
    dist.destroy_process_group()


if __name__ == "__main__":
    main()

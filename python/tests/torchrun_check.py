"""Run by test_torchrun.py under `torchrun --standalone --nproc_per_node=2` (gloo, CPU):
ds.loader without a sampler shards by rank; epochs reach persistent workers; each rank
resumes its own shard; DistributedDataParallel's gradients agree across ranks.
Arguments: DATASET OUT_DIR. Each rank writes OUT_DIR/rank<r>.json; any failed check
raises (torchrun then exits non-zero)."""

import gc
import json
import os
import sys
import time

import torch
import torch.distributed as dist

from arkit_tool import ARKitFaceDataset

BATCH = 2
T0 = time.time()


def equal_to_items(ds, batches, indices, epoch):
    got = {k: torch.cat([b[k] for b in batches]) for k in batches[0]}
    assert len(got["img"]) == len(indices)
    for row, i in enumerate(indices):
        for k, v in ds.item(i, epoch).items():
            assert torch.equal(got[k][row], torch.from_numpy(v)), (epoch, i, k)


def main():
    dataset, out = sys.argv[1], sys.argv[2]
    print(f"rank start {time.time() - T0:.1f} s", file=sys.stderr)
    dist.init_process_group("gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    report = {"rank": rank, "world": world}
    for split, remainder in (("train", "pad"), ("test", "drop"), (None, "pad")):
        ds = ARKitFaceDataset(dataset, split=split, mode="train", n_pts=32, corr="sparse")
        loader = ds.loader(BATCH, shuffle=True, remainder=remainder, num_workers=2,
                           persistent_workers=True, multiprocessing_context="fork")
        assert (loader.sampler.num_replicas, loader.sampler.rank) == (world, rank)
        epochs = []
        for epoch in (0, 1):  # no set_epoch call: each pass is the next epoch
            batches = list(loader)
            indices = loader.sampler.indices(epoch)
            equal_to_items(ds, batches, indices, epoch)
            everyone = [None] * world
            dist.all_gather_object(everyone, {"indices": indices, "batches": len(batches)})
            counts = {len(e["indices"]) for e in everyone}
            assert len(counts) == 1, everyone
            assert len({e["batches"] for e in everyone}) == 1, everyone
            flat = [i for e in everyone for i in e["indices"]]
            if remainder == "drop":
                assert len(set(flat)) == len(flat) == len(ds) - len(ds) % world
            else:
                assert set(flat) == set(range(len(ds)))
                assert len(flat) == len(ds) + (-len(ds)) % world
            epochs.append({"indices": indices, "batches": len(batches)})
            if epoch == 0:
                first = batches
        report[str(split)] = {"size": len(ds), "remainder": remainder, "epochs": epochs}
        # Persistent workers end with their loader (before the next loader forks).
        del loader
        gc.collect()
        print(f"rank {rank}: {split} {time.time() - T0:.1f} s", file=sys.stderr)

    # Resume: k batches of epoch 0 with 2 workers, then a new loader without workers.
    ds = ARKitFaceDataset(dataset, split=None, mode="train", n_pts=32, corr="sparse")
    k = 1
    a = ds.loader(BATCH, shuffle=True, num_workers=2, multiprocessing_context="fork")
    it = iter(a)
    head = [next(it) for _ in range(k)]
    state = json.loads(json.dumps(a.state_dict()))
    assert state["rank"] == rank and state["position"] == k * BATCH, state
    del it, a
    b = ARKitFaceDataset(dataset, split=None, mode="train", n_pts=32, corr="sparse").loader(BATCH, shuffle=True)
    b.load_state_dict(state)
    rest = list(b)
    assert len(head) + len(rest) == len(first)
    for x, y in zip(head + rest, first):
        for key in x:
            assert torch.equal(x[key], y[key]), key
    print(f"rank {rank}: resume {time.time() - T0:.1f} s", file=sys.stderr)
    report["resume"] = {"k": k, "remaining": len(rest), "position": state["position"]}

    # DistributedDataParallel on a tiny model: the gradients after backward are the same
    # on both ranks, and equal the mean of the ranks' own gradients.
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 5, stride=4), torch.nn.ReLU(), torch.nn.Flatten(),
                                torch.nn.LazyLinear(3))
    batch = first[0]
    model(batch["img"])  # materialise the lazy layer with the same seed on every rank
    local = [p.detach().clone() for p in model.parameters()]
    ddp = torch.nn.parallel.DistributedDataParallel(model)
    loss = (ddp(batch["img"]) - batch["nocs"].mean(dim=1)).pow(2).mean()
    loss.backward()
    grads = torch.cat([p.grad.reshape(-1) for p in model.parameters()])
    everyone = [torch.empty_like(grads) for _ in range(world)]
    dist.all_gather(everyone, grads)
    for g in everyone:
        assert torch.equal(g, grads)
    # Each rank's own gradient without DDP, averaged by hand.
    plain = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 5, stride=4), torch.nn.ReLU(), torch.nn.Flatten(),
                                torch.nn.LazyLinear(3))
    plain(batch["img"])
    with torch.no_grad():
        for p, q in zip(plain.parameters(), local):
            p.copy_(q)
    (plain(batch["img"]) - batch["nocs"].mean(dim=1)).pow(2).mean().backward()
    own = torch.cat([p.grad.reshape(-1) for p in plain.parameters()])
    mean = own.clone()
    dist.all_reduce(mean)
    mean /= world
    assert torch.allclose(grads, mean, rtol=1e-5, atol=1e-7), (grads - mean).abs().max()
    assert not torch.allclose(own, mean), "the ranks' batches differ, so must their own gradients"
    report["ddp"] = {"grad_norm": float(grads.norm()), "own_norm": float(own.norm())}

    print(f"rank {rank}: ddp {time.time() - T0:.1f} s", file=sys.stderr)
    with open(os.path.join(out, f"rank{rank}.json"), "w") as f:
        json.dump(report, f)
    dist.barrier()
    dist.destroy_process_group()
    print(f"rank {rank}: end {time.time() - T0:.1f} s", file=sys.stderr)


if __name__ == "__main__":
    main()

"""Epochs reach every DataLoader worker: whatever the settings (no workers, workers,
persistent or not, fork or spawn), the items of epoch e are ds.item(i, e) bit for bit,
through ds.loader (the epoch travels with each index; no call, or loader.set_epoch)
and through a plain DataLoader (ds.set_epoch, held in shared memory). The sampler's
shards and remainders."""

import pickle

import numpy as np
import pytest

from arkit_tool import ARKitFaceDataset, EpochSampler

# (name, DataLoader settings): the table of the docs.
SETTINGS = [
    ("no workers", dict(num_workers=0)),
    ("2 workers, fork", dict(num_workers=2, multiprocessing_context="fork")),
    ("2 workers, fork, persistent", dict(num_workers=2, multiprocessing_context="fork", persistent_workers=True)),
    ("2 workers, spawn", dict(num_workers=2, multiprocessing_context="spawn")),
    ("2 workers, spawn, persistent", dict(num_workers=2, multiprocessing_context="spawn", persistent_workers=True)),
]
IDS = [name for name, _ in SETTINGS]


def make(dataset, **kw):
    # The 4 test samples: 2 batches of 2, one for each worker.
    return ARKitFaceDataset(dataset, split="test", mode="train", n_pts=32, corr="sparse", **kw)


def assert_pass_is_epoch(ds, batches, indices, epoch):
    """The batches of one pass are ds.item(i, epoch) of `indices`, bit for bit."""
    import torch

    assert sum(len(b["img"]) for b in batches) == len(indices)
    got = {k: torch.cat([b[k] for b in batches]) for k in batches[0]}
    for row, i in enumerate(indices):
        want = ds.item(i, epoch)
        for k, v in want.items():
            assert torch.equal(got[k][row], torch.from_numpy(v)), (epoch, i, k)


@pytest.mark.parametrize("settings", [s for _, s in SETTINGS], ids=IDS)
def test_ds_loader_passes_are_successive_epochs_with_no_call(dataset, settings):
    pytest.importorskip("torch", reason="SKIPPED: torch is not installed")
    ds = make(dataset)
    loader = ds.loader(2, shuffle=True, **settings)
    assert len(ds) == 4 and len(loader) == 2
    if settings.get("multiprocessing_context") == "spawn" and not settings.get("persistent_workers"):
        # Workers spawned anew each pass (seconds each): one pass, of a later epoch.
        ds.set_epoch(3)
        assert_pass_is_epoch(ds, list(loader), loader.sampler.indices(3), 3)
        return
    for epoch in (0, 1):
        assert_pass_is_epoch(ds, list(loader), loader.sampler.indices(epoch), epoch)
    # set_epoch jumps (the dataset's reaches the loader's sampler; loader.set_epoch is
    # in test_resume.py), before the pass.
    ds.set_epoch(4)
    assert_pass_is_epoch(ds, list(loader), loader.sampler.indices(4), 4)


@pytest.mark.parametrize("settings", [s for _, s in SETTINGS], ids=IDS)
def test_plain_dataloader_sees_set_epoch_in_every_worker(dataset, settings):
    torch = pytest.importorskip("torch", reason="SKIPPED: torch is not installed")
    ds = make(dataset)
    loader = torch.utils.data.DataLoader(ds, batch_size=2, **settings)
    spawned_each_pass = settings.get("multiprocessing_context") == "spawn" and not settings.get("persistent_workers")
    for epoch in (1,) if spawned_each_pass else (0, 1):
        ds.set_epoch(epoch)
        assert_pass_is_epoch(ds, list(loader), range(len(ds)), epoch)


def test_epochs_differ_so_the_checks_can_fail(dataset):
    ds = make(dataset)
    a, b = ds.item(0, 0), ds.item(0, 1)
    assert not np.array_equal(a["img"], b["img"])
    np.testing.assert_array_equal(ds[1, 0]["img"], b["img"])
    np.testing.assert_array_equal(ds[0]["img"], a["img"])


def test_an_unused_iterator_does_not_use_up_an_epoch():
    s = EpochSampler(10, shuffle=True, seed=3, num_replicas=1, rank=0)
    iter(s)
    iter(s)
    first = list(s)
    assert {e for e, _ in first} == {0}
    assert sorted(i for _, i in first) == list(range(10))
    second = list(s)
    assert {e for e, _ in second} == {1}
    assert [i for _, i in second] == s.indices(1) != s.indices(0)


@pytest.mark.parametrize("size, ranks", [(12, 2), (11, 2), (10, 3), (2, 3), (0, 2)])
@pytest.mark.parametrize("remainder", ["pad", "drop"])
def test_shards_are_equal_and_cover_the_order(size, ranks, remainder):
    shards = [EpochSampler(size, seed=5, num_replicas=ranks, rank=r, remainder=remainder) for r in range(ranks)]
    for epoch in (0, 1):
        got = [s.indices(epoch) for s in shards]
        lengths = {len(g) for g in got}
        assert len(lengths) == 1 and lengths == {len(shards[0])}
        flat = [i for g in got for i in g]
        if remainder == "pad":
            assert len(got[0]) == -(-size // ranks)
            assert set(flat) == set(range(size))
            assert len(flat) - len(set(flat)) == ((-size) % ranks if size else 0)
        else:
            assert len(got[0]) == size // ranks
            assert len(set(flat)) == len(flat) == size - size % ranks
    # Every rank draws the same permutation: a 1-rank sampler's order, dealt out.
    whole = EpochSampler(size, seed=5, num_replicas=1, rank=0).indices(1)
    for r, s in enumerate(shards):
        assert s.indices(1) == [whole[p % size] for p in range(r, len(s) * ranks, ranks)]


def test_bad_sampler_arguments_are_named():
    with pytest.raises(ValueError, match="remainder"):
        EpochSampler(10, remainder="wrap")
    with pytest.raises(ValueError, match="rank 2 of num_replicas 2"):
        EpochSampler(10, num_replicas=2, rank=2)
    with pytest.raises(ValueError, match="^seed: "):
        EpochSampler(10, seed=-1)
    with pytest.raises(ValueError, match="^epoch: "):
        EpochSampler(10).set_epoch(-1)


def test_the_shared_epoch_survives_pickling(dataset):
    ds = make(dataset)
    ds.set_epoch(6)
    back = pickle.loads(pickle.dumps(ds))
    assert back.epoch == 6 and back.current_epoch() == 6
    back.set_epoch(2)  # a copy made outside a process start is not shared
    assert ds.epoch == 6

"""Resuming mid-epoch: the state saved after k batches, loaded into a new loader (with
another num_workers, or through torchdata's StatefulDataLoader), gives the remaining
batches bit-identical to those of the uninterrupted run, then the next epochs."""

import json

import pytest

from arkit_tool import ARKitFaceDataset, EpochSampler, collate

torch = pytest.importorskip("torch", reason="SKIPPED: torch is not installed")

BATCH = 3  # 12 samples: 4 batches an epoch


def make(dataset):
    return ARKitFaceDataset(dataset, split=None, mode="train", n_pts=32, corr="sparse")


def workers(n, persistent=False):
    if not n:
        return dict(num_workers=0)
    return dict(num_workers=n, multiprocessing_context="fork", persistent_workers=persistent)


def assert_same(got, want):
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), k


def uninterrupted(ds, epochs=2):
    loader = ds.loader(BATCH, shuffle=True)
    return [list(loader) for _ in range(epochs)]


@pytest.mark.parametrize(
    "before, after, k",
    [((0,), (2,), 1), ((2,), (0,), 2), ((2, True), (2,), 3), ((2,), (2, True), 1), ((0,), (0,), 0)],
    ids=["0->2 workers", "2->0 workers", "2 persistent->2", "2->2 persistent", "0->0 at start"],
)
def test_resume_after_k_batches_gives_the_remaining_batches(dataset, before, after, k):
    ds = make(dataset)
    want = uninterrupted(ds)
    # Epoch 0 fully, then k batches of epoch 1, then a checkpoint.
    loader = ds.loader(BATCH, shuffle=True, **workers(*before))
    assert_same(list(loader), want[0])
    it = iter(loader)
    head = [next(it) for _ in range(k)]
    state = json.loads(json.dumps(loader.state_dict()))  # what a checkpoint keeps
    assert (state["epoch"], state["position"]) == (1, k * BATCH)
    assert_same(head, want[1][:k])
    del it, loader
    # A new process would build a new dataset and loader.
    fresh = make(dataset)
    again = fresh.loader(BATCH, shuffle=True, **workers(*after))
    again.load_state_dict(state)
    assert_same(list(again), want[1][k:])
    # And then the next epoch, as the uninterrupted run's third.
    third = ds.loader(BATCH, shuffle=True)
    third.set_epoch(2)
    assert_same(list(again), list(third))


def test_state_at_an_epochs_end_is_the_next_epochs_start(dataset):
    ds = make(dataset)
    loader = ds.loader(BATCH, shuffle=True)
    assert loader.state_dict()["epoch"] == 0 and loader.state_dict()["position"] == 0
    list(loader)
    state = loader.state_dict()
    assert (state["epoch"], state["position"]) == (1, 0)
    it = iter(loader)
    for _ in range(len(loader)):
        next(it)
    # Every batch handed out, before StopIteration: still the next epoch's start.
    assert (loader.state_dict()["epoch"], loader.state_dict()["position"]) == (1 + 1, 0)


def test_a_state_of_another_order_or_shard_is_refused(dataset):
    ds = make(dataset)
    state = ds.loader(BATCH, shuffle=True).state_dict()
    with pytest.raises(ValueError, match="seed 0 .*this sampler: 1"):
        ds.loader(BATCH, shuffle=True, seed=1).load_state_dict(state)
    with pytest.raises(ValueError, match="num_replicas 1 .*this sampler: 2"):
        ds.loader(BATCH, shuffle=True, num_replicas=2, rank=0).load_state_dict(state)
    with pytest.raises(ValueError, match="batch_size"):
        ds.loader(BATCH + 1, shuffle=True).load_state_dict(state)
    bad = dict(state, position=len(ds) + 1)
    with pytest.raises(ValueError, match="position"):
        ds.loader(BATCH, shuffle=True).load_state_dict(bad)


@pytest.mark.parametrize("num_workers", [0, 2])
def test_torchdata_stateful_dataloader_resumes_epoch_and_position(dataset, num_workers):
    sdl = pytest.importorskip("torchdata.stateful_dataloader", reason="SKIPPED: torchdata is not installed")
    ds = make(dataset)
    want = uninterrupted(ds, epochs=3)

    def loader():
        kw = dict(multiprocessing_context="fork") if num_workers else {}
        return sdl.StatefulDataLoader(
            ds, batch_size=BATCH, sampler=EpochSampler(ds, seed=ds.seed), collate_fn=collate,
            num_workers=num_workers, **kw,
        )

    a = loader()
    assert_same(list(a), want[0])
    it = iter(a)
    head = [next(it), next(it)]
    assert_same(head, want[1][:2])
    state = a.state_dict()
    del it, a
    b = loader()
    b.load_state_dict(state)
    assert_same(list(b), want[1][2:])
    assert_same(list(b), want[2])

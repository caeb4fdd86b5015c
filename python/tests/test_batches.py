"""Whole batches computed in place (`ARKitFaceDataset.__getitems__`, `collate`,
`ds.loader`): the same samples as one at a time, the same batches as torch's default
collate of those samples, with 0 and 2 workers; a bad sample in a batch raises."""

import pathlib

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="SKIPPED: torch is not installed")

import arkit_tool  # noqa: E402
from arkit_tool import ARKitFaceDataset, CorrespondenceMatrix, DataError, ItemBatch  # noqa: E402


class OneByOne(torch.utils.data.Dataset):
    """The dataset seen without `__getitems__`: torch then asks for samples one by one."""

    def __init__(self, ds):
        self.ds = ds

    def __len__(self):
        return len(self.ds)

    def __getitem__(self, i):
        return self.ds[i]


def assert_same_sample(a, b, where):
    assert a.keys() == b.keys(), where
    for k in a:
        if isinstance(a[k], (np.ndarray, torch.Tensor, CorrespondenceMatrix)):
            x, y = np.asarray(a[k]), np.asarray(b[k])
            assert x.dtype == y.dtype and x.shape == y.shape, (where, k)
            np.testing.assert_array_equal(x, y, err_msg=f"{where} {k}")
        else:
            assert a[k] == b[k], (where, k)


def as_set_input(v):
    """A batch value as the official set_input has it: `.to(device)` of a tensor (the
    dense matrix of a `CorrespondenceMatrix`)."""
    return v.to("cpu") if isinstance(v, CorrespondenceMatrix) else v


def assert_same_batch(a, b, where):
    assert a.keys() == b.keys(), where
    a = {k: as_set_input(v) for k, v in a.items()}
    b = {k: as_set_input(v) for k, v in b.items()}
    for k in a:
        if torch.is_tensor(a[k]):
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, (where, k)
            assert torch.equal(a[k], b[k]), (where, k)
        else:
            assert a[k] == b[k], (where, k)


@pytest.mark.parametrize("compat", ["exact", "official"])
@pytest.mark.parametrize("mode", ["eval", "train"])
@pytest.mark.parametrize("corr", ["dense", "sparse", "both"])
def test_a_batch_holds_the_samples_one_at_a_time_gives(dataset, compat, mode, corr):
    ds = ARKitFaceDataset(dataset, split=None, mode=mode, compat=compat, corr=corr, n_pts=64)
    ds.set_epoch(4)
    indices = [3, 0, len(ds) - 1, 3, -2]
    batch = ds.__getitems__(indices)
    assert isinstance(batch, ItemBatch) and len(batch) == len(indices)
    one_by_one = [ds[i] for i in indices]
    for i, a, b in zip(indices, batch, one_by_one):
        assert_same_sample(a, b, (compat, mode, corr, i))
    # Our collate hands out the batch arrays; the default one stacks the samples.
    where = (compat, mode, corr)
    assert_same_batch(arkit_tool.collate(batch), torch.utils.data.default_collate(one_by_one), where)
    assert_same_batch(arkit_tool.collate(batch), torch.utils.data.default_collate(list(batch)), where)
    assert arkit_tool.collate(batch)["img"].shape == (len(indices), 3, 192, 192)


def test_tensor_datasets_batch_as_tensors(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=32, tensors=True, corr="sparse")
    batch = ds.__getitems__([1, 2])
    assert torch.is_tensor(batch[0]["img"]) and batch[0]["img"].shape == (3, 192, 192)
    assert_same_sample(batch[1], ds[2], "tensors")
    assert_same_batch(arkit_tool.collate(batch), torch.utils.data.default_collate([ds[1], ds[2]]), "tensors")


@pytest.mark.parametrize("compat", ["exact", "official"])
def test_the_loader_gives_the_default_batches_with_and_without_workers(dataset, compat):
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat=compat, n_pts=64, corr="sparse")
    ds.set_epoch(1)

    # ds.loader's order is epoch 1's permutation of its seed (the dataset's current epoch).
    order = ds.sampler(shuffle=True).indices(1)
    assert sorted(order) == list(range(len(ds)))
    reference = list(torch.utils.data.DataLoader(OneByOne(ds), batch_size=3, sampler=order))
    assert len(reference) == (len(ds) + 2) // 3
    for workers in [0, 2]:
        got = list(ds.loader(3, shuffle=True, num_workers=workers))
        assert len(got) == len(reference)
        for a, b in zip(got, reference):
            assert_same_batch(a, b, (compat, workers))


def test_a_bad_sample_in_a_batch_raises_naming_the_file(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=16, crop_store=None)
    path = pathlib.Path(ds[2]["img_path"])
    moved = path.with_suffix(".moved")
    path.rename(moved)
    try:
        with pytest.raises(DataError, match=str(path)):
            ds.__getitems__([0, 1, 2, 3])
        with pytest.raises(DataError, match=str(path)):
            list(ds.loader(4))
        # From a worker process too: the error reaches the training process, naming
        # the file (it used to be unpicklable there, and the batch never came).
        with pytest.raises(DataError, match=str(path)):
            list(ds.loader(4, num_workers=2, timeout=60))
        assert len(ds.__getitems__([0, 1, 3])) == 3  # the others are unaffected
    finally:
        moved.rename(path)
    with pytest.raises(IndexError):
        ds.__getitems__([0, len(ds)])


def test_a_batch_too_large_for_memory_raises_memory_error(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=16, corr="sparse")
    # 10^7 samples of 3 x 192 x 192 float32: 4.4 TB for img alone, refused by numpy
    # before any sample is computed.
    with pytest.raises(MemoryError):
        ds.__getitems__([0] * 10**7)


@pytest.mark.parametrize("compat", ["exact", "official"])
def test_batch_arrays_are_reused_only_once_nobody_holds_them(dataset, compat):
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat=compat, corr="both", n_pts=48)
    ds.set_epoch(2)
    n = len(ds)
    orders = [[0, 1, 2], [n - 1, n - 2, 3], [2, 0, n - 1], [1, 3, 0]]
    held = arkit_tool.collate(ds.__getitems__(orders[0]))  # the user keeps this batch
    kept = {k: v.clone() for k, v in held.items()}
    pointers = set()
    for order in orders[1:] * 2:
        batch = arkit_tool.collate(ds.__getitems__(order))
        pointers.add(batch["corr_ids"].data_ptr())
        # Every value is the sample's own, whatever the reused arrays held before
        # (corr_mat's rows of another sample among them).
        assert_same_batch(batch, torch.utils.data.default_collate([ds[i] for i in order]), order)
        del batch
    assert held["corr_ids"].data_ptr() not in pointers  # never written over while held
    assert_same_batch(held, kept, "held")
    assert len(pointers) == 1  # dropped batches are written over again
    # A batch of another size gets arrays of its own.
    assert len(ds.__getitems__([0, 1])) == 2


@pytest.mark.parametrize("corr", ["dense", "sparse"])
def test_torch_default_collate_takes_an_intact_batch_without_copying(dataset, corr):
    # The official train.py keeps DataLoader's default collate: it gets the batch arrays
    # themselves, the values stacking the samples gives.
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat="official", corr=corr, n_pts=32)
    batch = ds.__getitems__([2, 0, 1])
    stacked = torch.utils.data.default_collate([dict(s) for s in batch])
    got = torch.utils.data.default_collate(batch)
    assert_same_batch(got, stacked, corr)
    for k, v in batch.arrays.items():
        if isinstance(v, np.ndarray):
            assert got[k].data_ptr() == v.__array_interface__["data"][0], k  # no copy
            assert got[k].data_ptr() != stacked[k].data_ptr(), k


def test_a_changed_batch_is_stacked_as_it_now_is(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", corr="sparse", n_pts=16)
    for change in ["rebind", "replace", "drop", "swap"]:
        batch = ds.__getitems__([0, 1, 2])
        if change == "rebind":
            batch[1]["img"] = batch[1]["img"] * 2
        elif change == "replace":
            batch[0] = ds[3]
        elif change == "drop":
            del batch[2]
        else:
            batch[0], batch[1] = batch[1], batch[0]
        assert not batch.intact(), change
        want = torch.utils.data.default_collate([dict(s) for s in batch])
        for collate in [arkit_tool.collate, torch.utils.data.default_collate]:
            got = collate(batch)
            assert_same_batch(got, want, change)
            assert got["img"].data_ptr() != batch.arrays["img"].__array_interface__["data"][0]
        if change == "rebind":
            np.testing.assert_array_equal(got["img"][1].numpy(), 2 * ds[1]["img"])
    # Writing into a sample's array in place writes into the batch: still intact.
    batch = ds.__getitems__([0, 1])
    batch[0]["img"][:] = 0.5
    assert batch.intact()
    assert torch.all(torch.utils.data.default_collate(batch)["img"][0] == 0.5)


def test_a_plain_dataloader_gives_the_one_by_one_batches(dataset):
    # DataLoader(ds, batch_size=B), train.py's way, with 0 and 2 workers.
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat="official", corr="dense", n_pts=24)
    ds.set_epoch(3)
    reference = list(torch.utils.data.DataLoader(OneByOne(ds), batch_size=4))
    for workers in [0, 2]:
        got = list(torch.utils.data.DataLoader(ds, batch_size=4, num_workers=workers))
        assert len(got) == len(reference)
        for a, b in zip(got, reference):
            assert_same_batch(a, b, workers)

"""The crop store (`arkit-tool crops`) through ARKitFaceDataset: evaluation items equal
to those decoded from the release, training items of the same geometry, the same
batches with worker processes, and a store that does not fit refused by name."""

import os

import numpy as np
import pytest

from arkit_tool import ARKitFaceDataset, DataError

from conftest import BIN, make_dataset, run


def stored(dataset, tmp_path, compat):
    out = tmp_path / f"store-{compat}"
    run(BIN, "crops", "--dataset", dataset, "--compat", compat, "--output", out)
    return out


@pytest.mark.parametrize("compat", ["exact", "official"])
def test_items_from_the_store_equal_items_from_the_release(dataset, tmp_path, compat):
    store = stored(dataset, tmp_path, compat)
    for mode in ["eval", "train"]:
        plain = ARKitFaceDataset(dataset, split=None, mode=mode, compat=compat, n_pts=200,
                                 corr="sparse", crop_store=None)
        fast = ARKitFaceDataset(dataset, split=None, mode=mode, compat=compat, n_pts=200,
                                corr="sparse", crop_store=store)
        assert plain.crop_store is None and fast.crop_store == os.fspath(store)
        fast.set_epoch(1)
        plain.set_epoch(1)
        for i in range(len(plain)):
            a, b = plain[i], fast[i]
            assert a.keys() == b.keys()
            for k in a:
                if k == "img" and mode == "train":
                    # Resampled from the stored window: within a grey level on average.
                    diff = np.abs(a[k] - b[k]).mean() * 0.229 * 255
                    assert 0 < diff < 2, (i, diff)
                elif isinstance(a[k], np.ndarray):
                    np.testing.assert_array_equal(a[k], b[k], err_msg=f"{mode} {i} {k}")
                else:
                    assert a[k] == b[k], (mode, i, k)


def test_the_store_is_found_by_itself_and_one_that_does_not_fit_is_refused(tmp_path):
    data = make_dataset(tmp_path, resources=False, subjects=2)
    assert ARKitFaceDataset(data, split=None, mode="eval").crop_store is None
    run(BIN, "crops", "--dataset", data)
    auto = ARKitFaceDataset(data, split=None, mode="eval", n_pts=64)
    assert auto.crop_store == os.path.join(os.fspath(data), "crops", "exact-192")
    # Another crop size or other rules: no store by default, an error when named.
    assert ARKitFaceDataset(data, split=None, mode="eval", img_size=128).crop_store is None
    with pytest.raises(DataError, match="crops.json.*compat is exact"):
        ARKitFaceDataset(data, split=None, mode="eval", compat="official", crop_store=auto.crop_store)
    with pytest.raises(DataError, match="not a crop store"):
        ARKitFaceDataset(data, split=None, mode="eval", crop_store=tmp_path)
    # A damaged record: that sample raises naming the file, the others are served.
    part = os.path.join(auto.crop_store, "part-0.bin")
    with open(part, "r+b") as f:
        f.seek(64 + 2 * (os.path.getsize(part) - 64) // 5 + 777)
        b = f.read(1)
        f.seek(-1, 1)
        f.write(bytes([b[0] ^ 1]))
    auto = ARKitFaceDataset(data, split=None, mode="eval", n_pts=64)
    with pytest.raises(DataError, match="part-0.bin.*CRC"):
        auto[2]
    auto[0], auto[1], auto[3]


def test_two_workers_give_the_batches_of_none_from_the_store(dataset, tmp_path):
    torch = pytest.importorskip("torch", reason="SKIPPED: torch is not installed")
    store = stored(dataset, tmp_path, "exact")
    ds = ARKitFaceDataset(dataset, split=None, mode="train", n_pts=64, corr="sparse", crop_store=store)
    ds.set_epoch(4)

    def batches(workers):
        return list(torch.utils.data.DataLoader(
            ds, batch_size=4, shuffle=True, generator=torch.Generator().manual_seed(1),
            num_workers=workers, multiprocessing_context="fork" if workers else None))

    reference, got = batches(0), batches(2)
    assert len(got) == len(reference) == 3
    for a, b in zip(got, reference):
        for k in a:
            assert torch.equal(a[k], b[k]), k

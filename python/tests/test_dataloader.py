"""ARKitFaceDataset inside torch.utils.data.DataLoader: the same batches with 0 and 2
worker processes (fork and spawn), tensors on request."""

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="SKIPPED: torch is not installed")

from arkit_tool import ARKitFaceDataset  # noqa: E402


def batches(ds, workers, context=None):
    loader = torch.utils.data.DataLoader(
        ds,
        batch_size=4,
        shuffle=True,
        generator=torch.Generator().manual_seed(0),
        num_workers=workers,
        multiprocessing_context=context if workers else None,
    )
    return list(loader)


@pytest.mark.parametrize("compat", ["exact", "official"])
def test_two_workers_give_the_batches_of_none(dataset, compat):
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat=compat, n_pts=128)
    ds.set_epoch(2)
    reference = batches(ds, 0)
    assert reference[0]["img"].shape == (4, 3, 192, 192)
    assert reference[0]["corr_mat"].shape == (4, 128, 1220)
    for context in ["fork", "spawn"]:
        got = batches(ds, 2, context)
        assert len(got) == len(reference)
        for a, b in zip(got, reference):
            assert a.keys() == b.keys()
            for k in a:
                assert torch.equal(a[k], b[k]), (context, k)
    # Another epoch: other draws.
    ds.set_epoch(3)
    assert not torch.equal(batches(ds, 0)[0]["img"], reference[0]["img"])


def test_tensors_are_returned_on_request(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=64, tensors=True, corr="sparse")
    d = ds[0]
    assert isinstance(d["img"], torch.Tensor) and d["img"].dtype == torch.float32
    assert d["choose"].dtype == torch.int64 and d["corr_ids"].dtype == torch.int64
    assert d["mask"].dtype == torch.int64
    assert isinstance(d["img_path"], str)
    np.testing.assert_array_equal(d["model"].numpy(), ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=64)[0]["model"])

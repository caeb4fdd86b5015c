"""Batches from DataLoader workers: computed in shared memory the training process maps
once (no copy on the way), `corr_mat` carried sparse and built dense by `.to(device)`,
bit for bit the official matrix."""

import gc
import os
import sys
import pickle

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="SKIPPED: torch is not installed")

from arkit_tool import ARKitFaceDataset, CorrespondenceMatrix, _shared_batches  # noqa: E402
from arkit_tool.correspondences import dense_matrix, scatter_matrix  # noqa: E402
from test_batches import OneByOne  # noqa: E402  (the dataset asked for samples one by one)

# What the official PerspNetModel.set_input moves to its device.
SET_INPUT = ["img", "choose", "model", "uvmap", "nocs", "mask", "corr_mat"]


def official_dense(ids, weights, v):
    """The official loader's three assignments (data/arkit_dataset.py), in numpy."""
    ids, weights = np.asarray(ids), np.asarray(weights)
    out = np.zeros(ids.shape[:-1] + (v,), dtype=np.float32)
    flat_ids, flat_w, flat_out = ids.reshape(-1, 3), weights.reshape(-1, 3), out.reshape(-1, v)
    r = np.arange(len(flat_ids))
    for k in range(3):
        flat_out[r, flat_ids[:, k]] = flat_w[:, k]
    return out


def test_both_ways_of_building_the_matrix_give_the_official_one():
    rng = np.random.default_rng(0)
    ids = rng.integers(0, 50, size=(2, 40, 3)).astype(np.int64)
    ids[0, 0] = [5, 5, 7]  # a triangle repeating a vertex: the later weight stays
    ids[0, 1] = [9, 9, 9]
    weights = rng.random((2, 40, 3), dtype=np.float32)
    weights[0, 0] = [0.1, 0.2, 0.7]
    weights[0, 1] = [0.25, -0.0, 0.5]
    want = official_dense(ids, weights, 50)
    assert want[0, 0, 5] == np.float32(0.2) and want[0, 0, 7] == np.float32(0.7)
    assert want[0, 1, 9] == np.float32(0.5) and np.count_nonzero(want[0, 1]) == 1
    rust = dense_matrix(ids, weights, 50)
    torch_cpu = scatter_matrix(torch.from_numpy(ids), torch.from_numpy(weights), 50)
    # Bit for bit (a -0.0 that stays would show in the bytes).
    assert rust.tobytes() == want.tobytes()
    assert torch_cpu.numpy().tobytes() == want.tobytes()
    m = CorrespondenceMatrix(torch.from_numpy(ids), torch.from_numpy(weights), 50)
    assert m.to("cpu").numpy().tobytes() == want.tobytes()
    assert m.shape == (2, 40, 50) and m.dtype == torch.float32 and len(m) == 2
    with pytest.raises(ValueError, match="vertex id 50 outside 0..50"):
        dense_matrix(np.full((1, 2, 3), 50, dtype=np.int64), weights[:1, :2], 50)


def test_the_matrix_acts_as_the_dense_tensor_where_torch_reads_it():
    rng = np.random.default_rng(1)
    ids = torch.from_numpy(rng.integers(0, 30, size=(3, 8, 3)).astype(np.int64))
    weights = torch.from_numpy(rng.random((3, 8, 3), dtype=np.float32))
    m = CorrespondenceMatrix(ids, weights, 30)
    dense = torch.from_numpy(official_dense(ids, weights, 30))
    verts = torch.randn(3, 30, 3)
    assert torch.equal(m.to(torch.device("cpu")), dense)
    assert m.to(torch.float64).dtype == torch.float64 and torch.equal(m.to(torch.float64), dense.double())
    assert torch.equal(torch.bmm(m, verts), torch.bmm(dense, verts))
    assert torch.equal(m @ verts, dense @ verts)
    assert torch.equal(m.sum(2), dense.sum(2))
    assert torch.equal(m[1].to("cpu"), dense[1]) and isinstance(m[1], CorrespondenceMatrix)
    assert torch.equal(m[:, 2], dense[:, 2])
    np.testing.assert_array_equal(np.asarray(m), dense.numpy())
    assert not isinstance(m, torch.Tensor)  # the documented limit
    # A probe for what a tensor does not have builds nothing.
    from arkit_tool import correspondences

    built = []
    real = correspondences._dense
    correspondences._dense = lambda *a, **k: built.append(1) or real(*a, **k)
    try:
        assert not hasattr(m, "_fields") and not hasattr(m, "no_such_method")
        with pytest.raises(AttributeError, match="no_such_method"):
            m.no_such_method()
        assert not built
        assert m.abs().shape == (3, 8, 30) and built == [1]  # a tensor method builds it
    finally:
        correspondences._dense = real
    again = pickle.loads(pickle.dumps(m))
    assert torch.equal(again.to("cpu"), dense)


def test_a_held_dense_matrix_is_never_written_over():
    ids = torch.zeros(2, 4, 3, dtype=torch.int64)
    m1 = CorrespondenceMatrix(ids, torch.full((2, 4, 3), 0.5), 10)
    m2 = CorrespondenceMatrix(ids + 1, torch.full((2, 4, 3), 0.25), 10)
    held = m1.to("cpu")
    views = [m2.to("cpu") for _ in range(4)]  # each held: a buffer of its own
    assert len({v.data_ptr() for v in views} | {held.data_ptr()}) == 5
    assert torch.all(held[..., 0] == 0.5) and torch.all(held[..., 1:] == 0)
    del views
    gc.collect()
    again = m2.to("cpu")
    assert again.data_ptr() != held.data_ptr() and torch.all(held[..., 0] == 0.5)


def official_matrix(m):
    return torch.from_numpy(official_dense(m.ids.numpy(), m.weights.numpy(), m.vertex_count))


def sparse_batch(seed, n=64, b=3, v=1220):
    g = torch.Generator().manual_seed(seed)
    ids = torch.randint(0, v, (b, n, 3), generator=g)
    ids[:, ::5, 2] = ids[:, ::5, 0]  # triangles repeating a vertex: the later weight stays
    return CorrespondenceMatrix(ids, torch.rand(b, n, 3, generator=g) - 0.25, v)


class RustCalls:
    """Records whether each dense CPU matrix was written whole or at its old columns."""

    def __init__(self, monkeypatch):
        from arkit_tool import _native, correspondences

        self.kinds = []
        real = _native.write_correspondence_matrix_into

        def spy(out, ids, weights, previous_ids=None):
            self.kinds.append("whole" if previous_ids is None else "columns")
            return real(out, ids, weights, previous_ids)

        monkeypatch.setattr(correspondences._native, "write_correspondence_matrix_into", spy)


def test_a_reused_buffer_is_rewritten_at_its_columns_to_the_same_bits(monkeypatch):
    calls = RustCalls(monkeypatch)
    first = sparse_batch(1).to("cpu")
    ptr = first.data_ptr()
    del first
    for seed in range(2, 6):
        m = sparse_batch(seed)
        t = m.to("cpu")
        assert t.data_ptr() == ptr  # the buffer nobody held, again
        assert t.numpy().tobytes() == official_matrix(m).numpy().tobytes(), seed
        del t
    assert calls.kinds == ["whole"] + ["columns"] * 4


@pytest.mark.parametrize("write", ["in place", "through a view", "index", "numpy of the batch", "data"])
def test_a_buffer_written_by_its_user_is_written_whole_next_time(monkeypatch, write):
    # Whatever the user wrote into the last matrix never shows in the next one.
    calls = RustCalls(monkeypatch)
    m1, m2 = sparse_batch(7), sparse_batch(8)
    t = m1.to("cpu")
    ptr = t.data_ptr()
    if write == "in place":
        t.add_(3.0)
    elif write == "through a view":
        t[0].view(-1)[:100].fill_(9.0)
    elif write == "index":
        t[1, 2, 3] = 5.0
    elif write == "numpy of the batch":
        del t
        m1.numpy()[:, :, 7] = 2.0
    else:
        del t
        m1.data.fill_(4.0)  # `.data` writes past torch's version counter
    t = None
    gc.collect()
    t2 = m2.to("cpu")
    assert t2.data_ptr() == ptr
    assert t2.numpy().tobytes() == official_matrix(m2).numpy().tobytes()
    assert calls.kinds[-1] == "whole"


@pytest.mark.parametrize("hold", ["view", "numpy", "tensor of its numpy"])
def test_a_buffer_held_in_any_form_is_not_reused(hold):
    m1, m2 = sparse_batch(9), sparse_batch(10)
    t = m1.to("cpu")
    want = t.clone()
    held = {"view": lambda: t[1:], "numpy": lambda: t.numpy(), "tensor of its numpy": lambda: torch.from_numpy(t.numpy())}[hold]()
    ptr = t.data_ptr()
    del t
    gc.collect()
    others = [m2.to("cpu") for _ in range(3)]
    assert all(o.data_ptr() != ptr for o in others)
    assert torch.equal(torch.as_tensor(held), want[1:] if hold == "view" else want)


def test_a_numpy_matrix_held_through_a_view_is_not_reused():
    m1, m2 = sparse_batch(11), sparse_batch(12)
    a = dense_matrix(m1.ids.numpy(), m1.weights.numpy(), 1220)
    held, want = a[1:], a[1:].copy()
    del a
    others = [dense_matrix(m2.ids.numpy(), m2.weights.numpy(), 1220) for _ in range(3)]
    assert all(not np.shares_memory(o, held) for o in others)
    np.testing.assert_array_equal(held, want)


def loader(ds, workers, **kw):
    return torch.utils.data.DataLoader(ds, batch_size=4, shuffle=True, drop_last=True,
                                       generator=torch.Generator().manual_seed(0), num_workers=workers, **kw)


@pytest.mark.parametrize("compat", ["exact", "official"])
def test_train_py_batches_through_workers_are_the_official_tensors(dataset, compat):
    # The official train.py's DataLoader (default collate, shuffle, drop_last), its
    # set_input's `.to(device)`: the tensors of the one-by-one samples, bit for bit.
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat=compat, n_pts=96)
    ds.set_epoch(5)
    # The same DataLoader asking for the samples one by one (`ds[i]`: dense, as the
    # official get_item), stacked by the default collate.
    reference = list(loader(OneByOne(ds), 0))
    for workers in [0, 2]:
        got = list(loader(ds, workers))
        assert len(got) == len(reference) == len(ds) // 4
        for b, (batch, want) in enumerate(zip(got, reference)):
            assert isinstance(batch["corr_mat"], CorrespondenceMatrix)
            assert type(want["corr_mat"]) is torch.Tensor
            for k in SET_INPUT:
                t = batch[k].to("cpu")
                assert type(t) is torch.Tensor and t.dtype == want[k].dtype, (workers, k)
                assert t.shape == want[k].shape and torch.equal(t, want[k]), (workers, b, k)
                assert t.numpy().tobytes() == want[k].numpy().tobytes(), (workers, b, k)


def test_a_segment_is_free_only_when_nothing_holds_it():
    shapes = {"img": ("<f4", (2, 3, 4, 4)), "choose": ("<i8", (2, 5))}
    pool = _shared_batches.SegmentPool()
    seg = pool.acquire(shapes)
    assert seg.free()
    row = seg.arrays["img"][1]  # a view, as a sample of an ItemBatch holds
    assert not seg.free()
    del row
    tensor = torch.as_tensor(seg.arrays["choose"])  # as collate hands it to torch
    assert not seg.free() and pool.acquire(shapes) is not seg
    del tensor
    assert seg.free() and pool.acquire(shapes) is seg
    seg.sent()  # the training process holds it
    assert not seg.free()
    seg.map[_shared_batches.STATE_AT] = _shared_batches.FREE  # its lease let it go
    assert seg.free()
    other = pool.acquire({"img": ("<f4", (3, 3, 4, 4)), "choose": ("<i8", (3, 5))})
    assert other is not seg and other.layout != seg.layout


def mapped_ranges():
    return [(m.base, m.base + len(m.map)) for m in _shared_batches._mappings.values()]


def test_a_workers_batch_reaches_the_training_process_without_a_copy(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat="official", n_pts=64)
    before = _shared_batches.stats["mappings_opened"]
    batches = 0
    dl = loader(ds, 2, persistent_workers=True)
    for epoch in range(4):
        ds.set_epoch(epoch)
        for batch in dl:
            batches += 1
            ranges = mapped_ranges()
            arrays = [batch[k] for k in SET_INPUT if k != "corr_mat"]
            arrays += [batch["corr_mat"].ids, batch["corr_mat"].weights]
            for t in arrays:
                # Every array is a view of a worker's segment, mapped here: nothing was
                # copied into torch's shared memory on the way.
                assert not t.untyped_storage().is_shared()
                assert any(lo <= t.data_ptr() and t.data_ptr() + t.nbytes <= hi for lo, hi in ranges)
    opened = _shared_batches.stats["mappings_opened"] - before
    # Segments are reused: each worker maps a few (prefetched batches, the one held),
    # not one a batch.
    assert batches >= 12 and opened <= 2 * 4, (batches, opened)
    del batch, arrays, dl
    gc.collect()


def test_a_received_batch_frees_its_segment_when_dropped(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=32, corr="sparse")
    dl = loader(ds, 1, persistent_workers=True)
    it = iter(dl)
    got = list(it)  # the whole epoch: the (persistent) worker then waits, writing nothing
    assert len(got) == 3

    def owner(t):
        return next(m for m in _shared_batches._mappings.values() if m.base <= t.data_ptr() < m.base + len(m.map))

    owners = [owner(b["img"]) for b in got]
    assert len({id(o) for o in owners}) == 3  # each batch held: a segment of its own
    assert all(o.map[_shared_batches.STATE_AT] == _shared_batches.SENT for o in owners)
    view = got[0]["img"][1:]  # a view keeps its batch's segment
    del got
    gc.collect()
    states = [o.map[_shared_batches.STATE_AT] for o in owners]
    assert states == [_shared_batches.SENT, _shared_batches.FREE, _shared_batches.FREE]
    del view
    gc.collect()
    assert owners[0].map[_shared_batches.STATE_AT] == _shared_batches.FREE
    del it, dl


def test_a_batch_whose_shared_memory_is_not_the_one_sent_is_refused():
    seg = _shared_batches.SegmentPool().acquire({"img": ("<f4", (2, 3, 4, 4))})
    pid, fd, token = seg.key
    good = _shared_batches._Mapping(pid, fd, token, seg.size, seg.layout)
    assert good.map[: len(_shared_batches.MAGIC)] == _shared_batches.MAGIC
    with pytest.raises(RuntimeError, match="token differs"):
        _shared_batches._Mapping(pid, fd, token ^ 1, seg.size)
    with pytest.raises(RuntimeError, match="bytes, the batch needs"):
        _shared_batches._Mapping(pid, fd, token, seg.size + 4096)
    with pytest.raises(RuntimeError, match="cannot open its shared memory"):
        _shared_batches._Mapping(pid, 10**6, token, seg.size)
    # A layout reaching past the segment is refused before any array is made.
    bad = (("img", "<f4", (2, 3, 4, 4), seg.size - 8),)
    with pytest.raises(RuntimeError, match="outside its shared memory"):
        _shared_batches.receive((pid, fd, token, seg.size, bad), [])


def test_without_shared_batches_workers_give_the_same_batches(dataset, monkeypatch):
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat="official", n_pts=48)
    ds.set_epoch(1)
    shared = list(loader(ds, 2))
    monkeypatch.setenv(_shared_batches.ENV, "0")
    plain = list(loader(ds, 2))
    assert len(shared) == len(plain)
    for a, b in zip(shared, plain):
        for k in SET_INPUT:
            assert torch.equal(a[k].to("cpu"), b[k].to("cpu")), k
        # torch's own way: its shared memory, not a segment of ours.
        assert b["img"].untyped_storage().is_shared()


def test_workers_of_later_epochs_reuse_the_segments_of_earlier_ones(dataset):
    # train.py's DataLoader is not persistent: new workers every epoch. They adopt the
    # segments the training process has mapped (fresh pages cost more than the work).
    ds = ARKitFaceDataset(dataset, split=None, mode="train", compat="official", n_pts=64)
    dl = loader(ds, 2)
    reference = loader(OneByOne(ds), 0)  # its generator draws the same orders, epoch by epoch
    opened = []
    for epoch in range(4):
        for b, (batch, want) in enumerate(zip(dl, list(reference))):
            for k in SET_INPUT:
                assert torch.equal(batch[k].to("cpu"), want[k]), (epoch, b, k)
            del batch
        opened.append(_shared_batches.stats["mappings_opened"])
    assert opened[1] == opened[2] == opened[3], opened  # nothing new mapped after the first epoch


def test_two_loaders_at_once_never_write_into_each_others_batches(dataset):
    # Workers of two loaders alive together (a validation loader inside a training
    # epoch, say): a segment is adopted only from a worker that has ended, under a lock.
    train = ARKitFaceDataset(dataset, split=None, mode="train", compat="official", n_pts=64)
    val = ARKitFaceDataset(dataset, split=None, mode="eval", compat="official", n_pts=64)
    want_train = list(loader(OneByOne(train), 0))
    want_val = list(loader(OneByOne(val), 0))
    held = []
    for epoch in range(3):
        for b, (x, y) in enumerate(zip(loader(train, 2), loader(val, 2))):
            held.append((epoch, b, x, y))  # every batch kept: nothing may write over them
    for epoch, b, x, y in held:
        for k in SET_INPUT:
            assert torch.equal(x[k].to("cpu"), want_train[b][k]), ("train", epoch, b, k)
            assert torch.equal(y[k].to("cpu"), want_val[b][k]), ("val", epoch, b, k)


def test_a_segment_is_adopted_only_from_an_owner_that_has_ended():
    import os

    shapes = {"img": ("<f4", (2, 3, 4, 4))}
    seg = _shared_batches.SegmentPool().acquire(shapes)
    # The training process's mapping of it, as a forked worker inherits it.
    mapping = _shared_batches._Mapping(*seg.key, seg.size, seg.layout)
    _shared_batches._mappings[mapping.key] = mapping
    try:
        def adopted_in_child():
            pid = os.fork()
            if pid == 0:
                got = _shared_batches.Segment.adopt(seg.layout, seg.size)
                os._exit(0 if got is None else 1)
            return os.waitpid(pid, 0)[1] >> 8 == 1

        assert not adopted_in_child()  # its owner (this process) is alive
        ended = os.fork()
        if ended == 0:
            os._exit(0)
        os.waitpid(ended, 0)
        import struct

        struct.pack_into("<I", mapping.map, _shared_batches.OWNER_AT, ended)  # an owner that has ended
        assert adopted_in_child()
        seg.sent()  # held by the training process: not free
        struct.pack_into("<I", mapping.map, _shared_batches.OWNER_AT, ended)
        assert not adopted_in_child()
    finally:
        del _shared_batches._mappings[mapping.key]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork and madvise: Linux")
def test_dense_buffers_are_the_training_process_s_alone_after_a_fork():
    # DataLoader workers are forked at every epoch: the training process's dense buffers
    # are not shared with them (no copy-on-write fault a page afterwards; the child sees
    # zeros there and forgets them), and a matrix the child builds is its own and right.
    from arkit_tool import correspondences

    m1, m2 = sparse_batch(13), sparse_batch(14)
    t = m1.to("cpu")
    want1, want2 = official_matrix(m1), official_matrix(m2)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            ok = (
                not correspondences._buffers  # forgotten
                # (numpy here: torch's OpenMP pool does not survive a fork)
                and not np.any(t.numpy())  # the parent's buffer reads as zeros here
                and np.array_equal(m2.to("cpu").numpy(), want2.numpy())
            )
            os.write(write, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.close(write)
    answer = os.read(read, 1)
    os.waitpid(pid, 0)
    os.close(read)
    assert answer == b"1"
    assert torch.equal(t, want1)  # untouched by the child
    del t
    again = m2.to("cpu")
    assert torch.equal(again, want2)

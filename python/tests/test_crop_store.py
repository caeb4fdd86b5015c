"""The crop store (`arkit-tool crops`) through ARKitFaceDataset: evaluation items equal
to those decoded from the release, training items of the same geometry, the same
batches with worker processes, and a store that does not fit (other rules, damaged,
parts swapped or of another dataset, an earlier format) refused by name in training as
in evaluation; two `crops` into one store never mix."""

import os

import numpy as np
import pytest

from arkit_tool import ARKitFaceDataset, DataError

from conftest import BIN, make_dataset, run

HEADER = 128  # bytes of a part-K.bin header (crop store format 6)
FOOTER = 16  # bytes of its footer, after the record index


def record_offsets(part, records):
    """The `records + 1` offsets of a part file's record index (just before its footer)."""
    data = open(part, "rb").read()
    assert data[:8] == b"ARKCROP4" and data[-FOOTER:-FOOTER + 8] == b"ARKCIDX4"
    index = data[-FOOTER - 8 * (records + 1):-FOOTER]
    return np.frombuffer(index, dtype="<u8").tolist()


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
    offsets = record_offsets(part, 5)
    with open(part, "r+b") as f:
        f.seek((offsets[2] + offsets[3]) // 2)
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



def two_shard_store(tmp_path, name, seed_subjects=2):
    """A dataset of two shards of four samples (rows_per_shard 4) and its store."""
    base = tmp_path / name
    run(BIN, "synth", "--output", base / "release", "--subjects", seed_subjects,
        "--images-per-subject", 4, "--size", "256x256", "--seed", 5 if name == "a" else 6)
    run(BIN, "convert", "--input", base / "release", "--output", base / "converted",
        "--rows-per-shard", 4)
    data = base / "converted"
    run(BIN, "crops", "--dataset", data, "--size", 64)
    return data, os.path.join(os.fspath(data), "crops", "exact-64")


def items(data, store, mode):
    ds = ARKitFaceDataset(data, split=None, mode=mode, img_size=64, n_pts=32, corr="sparse",
                          crop_store=store)
    out = []
    for i in range(len(ds)):
        try:
            out.append(ds[i])
        except DataError as e:
            out.append(str(e))
    return out


@pytest.mark.parametrize("mode", ["train", "eval"])
def test_part_files_swapped_by_hand_are_refused(tmp_path, mode):
    data, store = two_shard_store(tmp_path, "a")
    p0, p1 = (os.path.join(store, f"part-{k}.bin") for k in (0, 1))
    b0, b1 = (open(p, "rb").read() for p in (p0, p1))
    # Whole files swapped: refused when the store is opened, naming the file.
    open(p0, "wb").write(b1)
    open(p1, "wb").write(b0)
    with pytest.raises(DataError, match="part-0.bin.*holds the records of samples shard 1"):
        ARKitFaceDataset(data, split=None, mode=mode, img_size=64, crop_store=store)
    # Shard 1's records under shard 0's header: each of shard 0's items refused, never
    # another sample's mesh and pixels; shard 1's served as without the store.
    open(p0, "wb").write(b0[:HEADER] + b1[HEADER:])
    open(p1, "wb").write(b1)
    got, plain = items(data, store, mode), items(data, None, mode)
    for i in range(4):
        assert isinstance(got[i], str), i
        assert "part-0.bin" in got[i] and "but it holds sample" in got[i], got[i]
    for i in range(4, 8):
        assert isinstance(got[i], dict), got[i]
        for k in got[i]:
            if k == "img":
                continue
            if isinstance(got[i][k], np.ndarray):
                np.testing.assert_array_equal(got[i][k], plain[i][k], err_msg=f"{mode} {i} {k}")


def test_two_crops_into_one_store_never_mix_and_an_old_store_is_refused(tmp_path):
    fcntl = pytest.importorskip("fcntl")
    import subprocess
    a, store = two_shard_store(tmp_path, "a")
    b, _ = two_shard_store(tmp_path, "b")
    # While one crops holds the store's lock, a second (another dataset's) is refused.
    with open(os.path.join(store, ".crops.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        p = subprocess.run([str(BIN), "crops", "--dataset", str(b), "--size", "64", "--output",
                            store], capture_output=True, text=True)
        assert p.returncode != 0 and "another crops is writing" in p.stderr, p.stderr
    # Two at once, from two datasets: the store is one dataset's whole store, in both
    # modes; the other dataset's loader refuses it.
    procs = [subprocess.Popen([str(BIN), "crops", "--dataset", str(d), "--size", "64", "--output",
                               store], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for d in (a, b)]
    results = [(p.wait(), p.stderr.read()) for p in procs]
    assert any(code == 0 for code, _ in results), results
    for code, err in results:
        assert code == 0 or "another crops is writing" in err, err
    owners = 0
    for data in (a, b):
        for mode in ("train", "eval"):
            try:
                got = items(data, store, mode)
            except DataError as e:
                assert "another dataset" in str(e), e
                continue
            owners += 1
            assert all(isinstance(g, dict) for g in got), got
    assert owners == 2
    # No temporaries left; an old store (format 5, 4, 3 or 1) is refused with what to do.
    assert not [n for n in os.listdir(store) if ".tmp-" in n]
    manifest = os.path.join(store, "crops.json")
    text = open(manifest).read()
    assert '"format": 6' in text and '"codec": "pred-zstd"' in text
    for old in (5, 4, 3):
        open(manifest, "w").write(text.replace('"format": 6', f'"format": {old}', 1))
        with pytest.raises(DataError, match=f"format {old}.*rerun `arkit-tool crops`"):
            ARKitFaceDataset(a, split=None, mode="train", img_size=64)
    open(manifest, "w").write(text.replace('"format": 6', '"format": 1', 1))
    with pytest.raises(DataError, match="format 1.*rerun `arkit-tool crops`"):
        ARKitFaceDataset(a, split=None, mode="train", img_size=64)

"""The Python readers of a torn folder.

`convert` and `crops` are stopped just before they rename a complete temporary into
place (`ARKIT_PAUSE_BEFORE_RENAME`, the kill harness's hook) and killed there. While the
folder is torn, `open_dataset` and `ARKitFaceDataset` must refuse with an error naming
a file of it, or read the last complete state; never a half-written file. The rerun
must give the uninterrupted run's files. (tests/kill.rs and tests/kill_all.rs do the
same for the command-line readers.)
"""

import os
import pathlib
import shutil
import subprocess

import numpy as np
import pytest

from conftest import BIN, make_dataset

arkit_tool = pytest.importorskip("arkit_tool")


def killed_before_rename(args, part):
    """Runs `args` until it has a complete temporary of a file whose path contains
    `part`, then kills it (SIGKILL). Returns the writer's report."""
    env = dict(os.environ, ARKIT_PAUSE_BEFORE_RENAME=part)
    p = subprocess.Popen([str(a) for a in args], env=env, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    try:
        line = ""
        for line in p.stderr:
            if "paused before renaming" in line:
                break
    finally:
        p.kill()
        p.wait()
    assert "paused before renaming" in line, f"{args} never paused at {part}: {line}"
    return line


def files(folder: pathlib.Path):
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not p.name.endswith(".lock")
    }


def temporaries(folder: pathlib.Path):
    return [p.name for p in folder.rglob(".*.tmp-*")]


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    base = tmp_path_factory.mktemp("kill")
    make_dataset(base, resources=False, size="200x200")
    return base


@pytest.mark.parametrize("part", ["conversion.json", "samples/part-", "dataset.json"])
def test_a_conversion_killed_before_a_rename_is_refused_then_rerun_whole(base, tmp_path, part):
    reference = base / "converted"
    out = tmp_path / "pq"
    convert = [BIN, "convert", "--input", base / "release", "--output", out,
               "--rows-per-shard", 5]
    killed_before_rename(convert, part)
    with pytest.raises(Exception) as opened:
        arkit_tool.open_dataset(out)
    assert str(out) in str(opened.value), str(opened.value)
    with pytest.raises(Exception) as loaded:
        arkit_tool.ARKitFaceDataset(out, split=None, mode="eval", n_pts=16)
    assert str(out) in str(loaded.value), str(loaded.value)
    subprocess.run([str(a) for a in convert], check=True, stdout=subprocess.DEVNULL)
    want, got = files(reference), files(out)
    # conversion.json names the output folder; everything else is byte for byte.
    want.pop("conversion.json", None)
    got.pop("conversion.json", None)
    assert got == want
    assert temporaries(out) == []
    assert len(arkit_tool.open_dataset(out)) == len(arkit_tool.open_dataset(reference))


def test_a_crop_store_killed_before_its_record_is_refused_or_not_used(base, tmp_path):
    data = tmp_path / "pq"
    shutil.copytree(base / "converted", data)
    crops = [BIN, "crops", "--dataset", data, "--size", 64]
    killed_before_rename(crops, "crops.json")
    store = data / "crops" / "exact-64"
    assert store.is_dir() and not (store / "crops.json").exists()
    # Named explicitly, the torn store is refused, naming its record.
    with pytest.raises(Exception) as refused:
        arkit_tool.ARKitFaceDataset(data, split=None, mode="eval", n_pts=16, img_size=64,
                                    crop_store=store)
    assert "crops.json" in str(refused.value) and str(store) in str(refused.value), \
        str(refused.value)
    # "auto" reads the last complete state: the release's own files, as without a store.
    try:
        auto = arkit_tool.ARKitFaceDataset(data, split=None, mode="eval", n_pts=16, img_size=64)
    except Exception as e:  # a clear refusal is the other allowed outcome
        assert str(store) in str(e), str(e)
    else:
        plain = arkit_tool.ARKitFaceDataset(data, split=None, mode="eval", n_pts=16, img_size=64,
                                            crop_store=None)
        for i in range(len(plain)):
            np.testing.assert_array_equal(auto[i]["img"], plain[i]["img"])
    subprocess.run([str(a) for a in crops], check=True, stdout=subprocess.DEVNULL)
    assert temporaries(data) == []
    whole = arkit_tool.ARKitFaceDataset(data, split=None, mode="eval", n_pts=16, img_size=64,
                                        crop_store=store)
    plain = arkit_tool.ARKitFaceDataset(data, split=None, mode="eval", n_pts=16, img_size=64,
                                        crop_store=None)
    # Evaluation crops from a store are bit for bit the release's (docs/python.md).
    np.testing.assert_array_equal(whole[0]["img"], plain[0]["img"])


def test_a_loader_beside_crops_rewriting_its_store_keeps_serving_the_store_it_opened(base, tmp_path):
    """`ARKitFaceDataset` reading a crop store while `crops` rewrites it (another codec:
    every part file replaced, every record at another offset): the loader, opened
    before, serves the store it opened, item for item, during the rewrite and after it
    (it holds its part files open; the writer renames new ones into place); a loader
    opened afterwards reads the new store. Never a record read at the other store's
    offsets."""
    data = tmp_path / "pq"
    shutil.copytree(base / "converted", data)
    store = data / "crops" / "exact-64"
    subprocess.run([str(BIN), "crops", "--dataset", str(data), "--size", "64"], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def open_loader():
        return arkit_tool.ARKitFaceDataset(data, split=None, mode="eval", n_pts=16, img_size=64,
                                           crop_store=store)

    def parts():
        return {p.name: p.stat().st_ino for p in store.glob("part-*")}

    ds = open_loader()
    before = [ds[i]["img"].copy() for i in range(len(ds))]
    old_parts = parts()
    writer = subprocess.Popen([str(BIN), "crops", "--dataset", str(data), "--size", "64",
                               "--codec", "raw"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    reads = 0
    while writer.poll() is None or reads < len(before):
        i = reads % len(before)
        np.testing.assert_array_equal(ds[i]["img"], before[i], err_msg=f"item {i} read {reads}")
        reads += 1
    assert writer.returncode == 0, writer.stderr.read()
    new_parts = parts()
    assert set(new_parts) == set(old_parts) and all(
        new_parts[k] != old_parts[k] for k in new_parts), "crops did not replace the parts"
    for i, img in enumerate(before):
        np.testing.assert_array_equal(ds[i]["img"], img)
    assert '"raw"' in (store / "crops.json").read_text()
    fresh = open_loader()
    for i, img in enumerate(before):
        # The codecs are lossless: the new store's crops are the same pixels.
        np.testing.assert_array_equal(fresh[i]["img"], img)


@pytest.mark.parametrize("workers,context", [(0, None), (2, "fork"), (2, "spawn")])
def test_a_dataset_converted_again_under_a_loader_never_mixes_two_generations(
        base, tmp_path, workers, context):
    """`convert --overwrite` of another release and `crops` again, into the folder a
    loader has open: the loader and workers forked from it keep serving what it opened,
    item for item; a worker that must open the folder again (spawned) refuses, naming
    the folder, instead of serving the new generation beside the old one's order."""
    torch = pytest.importorskip("torch")
    data = tmp_path / "pq"
    shutil.copytree(base / "converted", data)
    crops = [str(BIN), "crops", "--dataset", str(data), "--size", "64"]
    subprocess.run(crops, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ds = arkit_tool.ARKitFaceDataset(data, split=None, mode="eval", n_pts=16, img_size=64)
    before = [ds[i]["img"].copy() for i in range(len(ds))]

    other = tmp_path / "other"
    subprocess.run([str(BIN), "synth", "--output", str(other), "--subjects", "3",
                    "--images-per-subject", "4", "--size", "200x200", "--seed", "11",
                    "--test-fraction", "0.34"], check=True, stdout=subprocess.DEVNULL)
    subprocess.run([str(BIN), "convert", "--input", str(other), "--output", str(data),
                    "--rows-per-shard", "5", "--overwrite"], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    subprocess.run(crops, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    fresh = arkit_tool.ARKitFaceDataset(data, split=None, mode="eval", n_pts=16, img_size=64)
    assert any(not np.array_equal(fresh[i]["img"], before[i])
               for i in range(min(len(fresh), len(before)))), "the new release gave the same crops"

    kw = dict(batch_size=4, shuffle=False, num_workers=workers)
    if workers:
        kw["multiprocessing_context"] = context
    loader = torch.utils.data.DataLoader(ds, **kw)
    if context == "spawn":
        with pytest.raises(Exception) as refused:
            next(iter(loader))
        assert str(data) in str(refused.value) and "changed since this job opened it" in str(
            refused.value), str(refused.value)
        return
    got = [img for batch in loader for img in batch["img"].numpy()]
    assert len(got) == len(before)
    for i, img in enumerate(got):
        np.testing.assert_array_equal(img, before[i], err_msg=f"item {i}")

"""Datasets read from a bucket (a real S3 server, `s3.py`): `ARKitFaceDataset("s3://...")`
gives the items, batches and DataLoader batches of the local folder bit for bit (0 and 2
workers), a mid-epoch state saved with one backend resumes with the other, the cache
stays under its cap, faults end in retries or in an error naming the object and no
secret, and a worker killed mid-request ends the loader with torch's error, not a hang."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from arkit_tool import ARKitFaceDataset, DataError, open_dataset
from conftest import BIN
from s3 import S3, SECRET

BATCH = 4


@pytest.fixture(scope="module")
def store_dataset(tmp_path_factory):
    from conftest import make_dataset

    base = tmp_path_factory.mktemp("cloud")
    data = make_dataset(base, resources=False)
    for compat in ("official", "exact"):
        subprocess.run([str(BIN), "crops", "--dataset", str(data), "--compat", compat, "--size", "64"],
                       check=True, stdout=subprocess.DEVNULL)
    return data


@pytest.fixture(scope="module")
def s3(tmp_path_factory, store_dataset):
    server = S3(tmp_path_factory.mktemp("s3root"), tmp_path_factory.mktemp("s3cache"))
    server.push(store_dataset, "ds")
    yield server
    server.stop()


@pytest.fixture
def env(s3, monkeypatch):
    for k, v in s3.env.items():
        monkeypatch.setenv(k, v)
    s3.reset()
    return s3


def make(path, compat="official", **kw):
    return ARKitFaceDataset(path, split=None, mode="train", compat=compat, img_size=64, n_pts=32,
                            corr="sparse", **kw)


def same_item(a, b):
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], np.ndarray):
            assert np.array_equal(a[k], b[k]), k
        else:
            assert a[k] == b[k], k


@pytest.mark.parametrize("compat", ["official", "exact"])
def test_items_and_batches_from_the_bucket_are_those_of_the_folder(store_dataset, env, compat):
    local, remote = make(store_dataset, compat), make(env.url("ds"), compat)
    assert len(local) == len(remote) >= 8
    assert remote.crop_store == env.url(f"ds/crops/{compat}-64")
    for epoch in (0, 3):
        for i in range(len(local)):
            same_item(local.item(i, epoch), remote.item(i, epoch))
    env.reset()
    indices = list(range(len(local)))[::-1]
    a, b = local.__getitems__(indices), remote.__getitems__(indices)
    for k in ("img", "model", "choose", "mask", "uvmap", "nocs"):
        assert np.array_equal(a.arrays[k], b.arrays[k]), k
    gets = env.stats()["requests_by_method"].get("GET", 0)
    assert gets <= len(indices), f"{gets} GETs for a batch of {len(indices)}"


def test_a_converted_dataset_opens_from_its_url(store_dataset, env):
    local, remote = open_dataset(store_dataset), open_dataset(env.url("ds"))
    assert len(local) == len(remote) and local.splits == remote.splits
    assert np.array_equal(local.sample(3)["verts"], remote.sample(3)["verts"])


torch = pytest.importorskip("torch", reason="SKIPPED: torch is not installed")


def batches(ds, workers, **kw):
    extra = dict(num_workers=workers, multiprocessing_context="fork") if workers else {}
    return list(ds.loader(BATCH, shuffle=True, **extra, **kw))


def assert_same(got, want):
    assert len(got) == len(want)
    for x, y in zip(got, want):
        assert x.keys() == y.keys()
        for k in x:
            assert torch.equal(x[k], y[k]), k


@pytest.mark.parametrize("workers", [0, 2])
def test_dataloader_batches_from_the_bucket_equal_the_folders(store_dataset, env, workers):
    assert_same(batches(make(env.url("ds")), workers), batches(make(store_dataset), workers))


def test_train_py_dataloader_from_the_bucket_equals_the_folders(store_dataset, env):
    """train.py's plain DataLoader (torch's sampler; the workers read their queued batch
    ahead): the same batches from the bucket, one GET a sample once the dataset is open
    (opening reads each crop-store part's header, then its index and footer)."""
    def run(ds):
        torch.manual_seed(7)
        loader = torch.utils.data.DataLoader(ds, batch_size=BATCH, shuffle=True, num_workers=2,
                                             multiprocessing_context="fork", drop_last=True)
        return [list(loader) for _ in range(2)]

    want = run(make(store_dataset))
    remote = make(env.url("ds"))
    env.reset()
    got = run(remote)
    for a, b in zip(got, want):
        assert_same(a, b)
    samples = sum(len(batch["img"]) for epoch in got for batch in epoch)
    assert env.stats()["requests_by_method"].get("GET", 0) == samples


@pytest.mark.parametrize("first, then", [("bucket", "folder"), ("folder", "bucket")])
def test_a_mid_epoch_state_resumes_with_the_other_backend(store_dataset, env, first, then):
    where = {"bucket": env.url("ds"), "folder": store_dataset}
    want = batches(make(store_dataset), 0)
    loader = make(where[first]).loader(BATCH, shuffle=True, num_workers=2, multiprocessing_context="fork")
    it = iter(loader)
    head = [next(it) for _ in range(2)]
    state = json.loads(json.dumps(loader.state_dict()))
    del it, loader
    again = make(where[then]).loader(BATCH, shuffle=True)
    again.load_state_dict(state)
    assert_same(head + list(again), want)


def test_torchrun_two_ranks_two_workers_bucket_and_folder_agree(store_dataset, env, tmp_path):
    run_env = dict(os.environ, OMP_NUM_THREADS="1")
    run_env["PYTHONPATH"] = os.pathsep.join(p for p in [*sys.path, run_env.get("PYTHONPATH", "")] if p)
    here = os.path.dirname(os.path.abspath(__file__))
    run = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
         os.path.join(here, "torchrun_cloud_check.py"), str(store_dataset), env.url("ds"), str(tmp_path)],
        env=run_env, capture_output=True, text=True, timeout=600,
    )
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-8000:]
    reports = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert [r["rank"] for r in reports] == [0, 1]
    assert all(r["batches_compared"] >= 2 for r in reports), reports
    assert set(reports[0]["indices"]).isdisjoint(reports[1]["indices"]) or len(reports[0]["indices"]) * 2 > 12


def test_the_cache_serves_again_and_stays_under_its_cap(store_dataset, env, tmp_path):
    big = make(env.url("ds"), cache_dir=tmp_path / "big", cache_bytes=1 << 30)
    first = batches(big, 0)
    env.reset()
    assert_same(batches(big, 0), first)
    assert env.stats()["requests_by_method"].get("GET", 0) == 0, "a cached epoch went to the bucket"
    parts = json.loads((store_dataset / "crops" / "official-64" / "crops.json").read_text())["shards"]
    cap = 5 * sum(p["bytes"] for p in parts) // sum(p["records"] for p in parts)  # about 5 records
    small = make(env.url("ds"), cache_dir=tmp_path / "small", cache_bytes=cap)
    assert_same(batches(small, 2), batches(make(store_dataset), 2))
    held = sum(f.stat().st_size for f in (tmp_path / "small" / "records").rglob("*") if f.is_file())
    assert 0 < held <= cap, f"{held} bytes cached for a cap of {cap}"


def test_faults_are_retried_and_a_lasting_one_names_the_object(store_dataset, env):
    local, remote = make(store_dataset), make(env.url("ds"))
    env.faults([{"method": "GET", "key_contains": "crops/official-64/part-", "times": 1, "fault": {"status": 503}},
                {"method": "GET", "key_contains": "crops/official-64/part-", "times": 1, "fault": {"reset": True}},
                {"method": "GET", "key_contains": "crops/official-64/part-", "times": 1, "fault": {"truncate": 9}}])
    same_item(local.item(5, 1), remote.item(5, 1))
    assert env.stats()["faults_fired"] == 3  # ARKIT_STORAGE_RETRIES=4: three failures, then the answer
    env.faults([{"method": "GET", "key_contains": "crops/official-64/part-", "times": 100, "fault": {"status": 500}}])
    with pytest.raises(DataError, match=r"s3://arkit/ds/crops/official-64/part-\d+\.bin.*after 4 tries"):
        remote.item(6, 1)


def test_wrong_credentials_are_refused_without_the_secret(store_dataset, env, monkeypatch):
    wrong = "not-the-right-secret-4k2"
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", wrong)
    with pytest.raises(DataError) as e:
        make(env.url("ds"))
    text = str(e.value)
    assert "credentials" in text and "s3://arkit/ds/" in text
    assert wrong not in text and SECRET not in text
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", SECRET)
    with pytest.raises(DataError, match="no published dataset at s3://arkit/elsewhere"):
        make(env.url("elsewhere"))


def test_a_worker_killed_mid_request_ends_the_loader_with_an_error_not_a_hang(store_dataset, env):
    remote = make(env.url("ds"))
    env.config(latency_ms=3000)
    loader = remote.loader(BATCH, shuffle=True, num_workers=2, multiprocessing_context="fork", timeout=60)
    it = iter(loader)
    killed = []

    def kill_a_worker():
        time.sleep(1.0)
        pids = [w.pid for w in it.inner._workers]  # torch's iterator: the workers, in their first request now
        os.kill(pids[0], signal.SIGKILL)
        killed.append(pids[0])

    t = threading.Thread(target=kill_a_worker)
    t.start()
    started = time.time()
    with pytest.raises(RuntimeError, match="DataLoader worker"):
        list(it)
    t.join()
    assert killed and time.time() - started < 60
    env.config(latency_ms=0)
    # The dataset still serves, the same samples.
    same_item(remote.item(0, 0), make(store_dataset).item(0, 0))

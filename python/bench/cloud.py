"""train.py's DataLoader path from local disk, from a bucket, and through LitData, side by
side in one run, printed as `ratio:` lines.

    python python/bench/cloud.py [--samples 512] [--rounds 3] [--latency-ms 20]
        [--bandwidth-mbit 1000] [--workers 2] [--batch 16] [--no-litdata]

Makes an 800x800 synthetic dataset with the arkit-tool binary (the real topology when the
resource files are there) and its official-rules crop store (S = 192), starts the S3 test
bed (`arkit-s3-testbed`: s3s-fs with SigV4 on, behind its proxy at `--latency-ms` a request
and `--bandwidth-mbit`, like a cloud bucket seen from a cloud VM), publishes the dataset
with `arkit-tool push`, and times training epochs of three loaders, each a
`torch.utils.data.DataLoader` as train.py's (`--workers` worker processes, batch
`--batch`, shuffle, `drop_last`, the default collate, workers started anew each epoch):

- `disk`: `ARKitFaceDataset(FOLDER, compat="official", corr="dense")` (what
  `python -m arkit_tool.official` gives train.py);
- `bucket`: the same dataset from `s3://arkit/bench` (no local cache: every record a
  ranged GET);
- `litdata`: LitData's `StreamingDataset` (pip `litdata`, read through boto3 from the same
  server and proxy) over the same crop records, `optimize`d from our store (one item a
  sample: its index and record bytes), each batch's items then computed by the same code
  (`Loader.supply` hands the records to the loader, `__getitems__` computes the batch):
  only the transport differs.

Every loader's batches are checked against the disk's items first. Figures: samples a
second (an epoch's wall time, worker start-up included), the time to the first batch,
and, from the proxy's counters, the requests and bytes of an epoch against the records'
bytes. The loaders run in turn, an epoch each, `--rounds` times after a warm epoch each;
the median is printed. torch threads: 1 in every process.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))

ACCESS, SECRET, BUCKET = "bench-access", "bench-secret-0f3k", "arkit"


def own_cpu_seconds():
    """User and system CPU seconds of this process and its reaped children."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def cpu_seconds(pid):
    """User and system CPU seconds of process `pid` so far (Linux /proc)."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def control(proxy, path, body=None):
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(f"{proxy}/__testbed/{path}", data=data, method="GET" if body is None else "POST")
    with urllib.request.urlopen(req, timeout=10) as r:
        text = r.read()
    return json.loads(text) if text else None


class LitDataBatches:
    """A collate for LitData's loader: the batch's records handed to our loader, then the
    batch computed by `__getitems__` and collated by torch's default collate."""

    def __init__(self, ds):
        self.ds = ds

    def __call__(self, samples):
        import torch

        indices = [int(s["index"]) for s in samples]
        self.ds._loader.supply(indices, [bytes(s["record"]) for s in samples])
        return torch.utils.data.default_collate(self.ds.__getitems__(indices))


def record_item(item):
    """LitData's `optimize` function: `(index, record bytes)` as one item."""
    return {"index": item[0], "record": item[1]}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--samples", type=int, default=512)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--latency-ms", type=int, default=20)
    p.add_argument("--bandwidth-mbit", type=int, default=1000)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--no-litdata", action="store_true")
    p.add_argument("--resources", default=str(ROOT.parent / "shared" / "arkitface-resources"))
    p.add_argument("--bin", default=str(ROOT / "target" / "release" / "arkit-tool"))
    p.add_argument("--testbed", default=str(ROOT / "target" / "release" / "arkit-s3-testbed"))
    a = p.parse_args()

    import torch

    torch.set_num_threads(1)
    from dataloader import synthetic_dataset

    import arkit_tool

    tmp = pathlib.Path(tempfile.mkdtemp())
    try:
        # A synthetic set none of whose samples the official rules refuse (their box leaving
        # the image's top or left edge: the official loader swaps in another sample there,
        # which a timing of two loaders over the same order cannot follow).
        for attempt in range(8):
            shutil.rmtree(tmp / "release", ignore_errors=True)
            shutil.rmtree(tmp / "data", ignore_errors=True)
            data, res, n = synthetic_dataset(a.bin, tmp, a.samples, a.resources, seed=1 + attempt)
            report = json.loads(subprocess.run([a.bin, "inspect", "--json", "--dataset", str(data)], check=True,
                                               capture_output=True, text=True).stdout)
            if report.get("official_loader_failures", 0) == 0:
                break
        subprocess.run([a.bin, "crops", "--dataset", data, "--compat", "official", *res], check=True,
                       stdout=subprocess.DEVNULL)
        server = subprocess.Popen(
            [a.testbed, "--root", str(tmp / "s3"), "--access-key", ACCESS, "--secret-key", SECRET,
             "--bucket", BUCKET], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        info = json.loads(server.stdout.readline())
        proxy = info["proxy"]
        env = {"AWS_ENDPOINT_URL": proxy, "AWS_ACCESS_KEY_ID": ACCESS, "AWS_SECRET_ACCESS_KEY": SECRET,
               "AWS_REGION": "us-east-1", "AWS_DEFAULT_REGION": "us-east-1",
               "ARKIT_CACHE_DIR": str(tmp / "cache")}
        os.environ.update(env)
        url = f"s3://{BUCKET}/bench"
        subprocess.run([a.bin, "push", str(data), url], check=True, stdout=subprocess.DEVNULL)
        store = json.loads((data / "crops" / "official-192" / "crops.json").read_text())
        record_bytes = sum(s["bytes"] for s in store["shards"]) / sum(s["records"] for s in store["shards"])
        print(f"dataset: {n} samples, 800x800, topology: {'real' if res else 'built-in'}, official crop store "
              f"({record_bytes / 1024:.1f} KiB a record); {os.cpu_count()} cores; torch {torch.__version__}; "
              f"proxy: {a.latency_ms} ms a request, {a.bandwidth_mbit} Mbit/s")

        def dataset(path):
            return arkit_tool.ARKitFaceDataset(path, split="train", mode="train", compat="official",
                                               corr="dense")

        def loader(ds, collate=None, data=None):
            kw = dict(batch_size=a.batch, num_workers=a.workers, drop_last=True)
            if a.workers:
                kw["multiprocessing_context"] = "fork"
            if collate is None:
                return torch.utils.data.DataLoader(ds, shuffle=True, **kw)
            from litdata import StreamingDataLoader

            return StreamingDataLoader(data, collate_fn=collate, **kw)

        disk, bucket = dataset(data), dataset(url)
        loaders = {"disk": loader(disk), "bucket": loader(bucket)}
        # ds.loader's path (our sampler: each worker fetches its next batches ahead).
        ahead_kw = dict(num_workers=a.workers, drop_last=True)
        if a.workers:
            ahead_kw["multiprocessing_context"] = "fork"
        loaders["disk ds.loader"] = disk.loader(a.batch, shuffle=True, **ahead_kw)
        loaders["bucket ds.loader"] = bucket.loader(a.batch, shuffle=True, **ahead_kw)
        if not a.no_litdata:
            import litdata

            lit_url = f"s3://{BUCKET}/litdata"
            started = time.perf_counter()
            litdata.optimize(fn=record_item, inputs=[(i, disk._loader.record(i)) for i in range(len(disk))],
                             output_dir=lit_url,
                             chunk_bytes="64MB", num_workers=1, mode="overwrite")
            print(f"litdata: optimize of {len(disk)} records into {lit_url}: {time.perf_counter() - started:.1f} s")
            stream = litdata.StreamingDataset(lit_url, shuffle=True, drop_last=True,
                                              cache_dir=str(tmp / "litdata-cache"), max_cache_size="100GB")
            loaders["litdata"] = loader(disk, LitDataBatches(dataset(data)), stream)

        # Each loader's first batch: every row's mesh is a sample's, and its image that
        # sample's item's from the disk (the training draws depend on the epoch only).
        table = arkit_tool.open_dataset(data)
        by_mesh = {}
        for i in range(len(disk)):
            k = disk.key(i)
            by_mesh[np.asarray(table.sample(k[:3])["verts"], dtype=np.float32).tobytes()] = i
        for name, ld in loaders.items():
            batch = next(iter(ld))
            rows = [by_mesh.get(batch["model"][r].numpy().tobytes()) for r in range(len(batch["model"]))]
            assert None not in rows, f"{name}: a batch row whose mesh is no sample's"
            print(f"{name}: first batch's {len(rows)} rows are samples of the dataset (meshes matched)")

        control(proxy, "config", {"latency_ms": a.latency_ms, "bandwidth_bytes_per_sec": a.bandwidth_mbit * 125_000})
        times = {k: [] for k in loaders}
        first = {k: [] for k in loaders}
        server_share = {k: [] for k in loaders}
        client_us = {k: [] for k in loaders}
        traffic = {}
        for rnd in range(a.rounds + 1):
            for name, ld in loaders.items():
                if rnd == 1:
                    control(proxy, "reset", {})
                    control(proxy, "config",
                            {"latency_ms": a.latency_ms, "bandwidth_bytes_per_sec": a.bandwidth_mbit * 125_000})
                if name == "litdata":
                    # LitData keeps the chunks it downloaded in its cache folder: emptied
                    # before each epoch, as for a dataset larger than the node's disk (the
                    # release's 40 GB of records), so that each epoch streams.
                    shutil.rmtree(tmp / "litdata-cache", ignore_errors=True)
                server_cpu = cpu_seconds(server.pid)
                client_cpu = own_cpu_seconds()
                started = time.perf_counter()
                count, t_first = 0, None
                for batch in ld:
                    if t_first is None:
                        t_first = time.perf_counter() - started
                    count += len(batch["img"])
                elapsed = time.perf_counter() - started
                server_share[name].append((cpu_seconds(server.pid) - server_cpu) / elapsed)
                # The workers are reaped at the end of each epoch (not persistent), so
                # their CPU is in this process's children's by now.
                client_us[name].append((own_cpu_seconds() - client_cpu) * 1e6 / count)
                if rnd == 1:
                    s = control(proxy, "stats")
                    traffic[name] = (s["requests_by_method"].get("GET", 0), s["response_body_bytes"], count)
                if rnd > 0:
                    times[name].append(count / elapsed)
                    first[name].append(t_first)
        for name in loaders:
            print(f"{name}: {statistics.median(times[name]):.1f} samples/s (rounds: "
                  f"{', '.join(f'{x:.1f}' for x in times[name])}), first batch after "
                  f"{statistics.median(first[name]):.2f} s")
        for name in loaders:
            if not name.startswith("disk"):
                print(f"{name}: the S3 server and proxy, on this machine's cores too, used "
                      f"{statistics.median(server_share[name]):.2f} cores during the epoch")
        for name in loaders:
            print(f"{name}: the loader's CPU (main process and workers): "
                  f"{statistics.median(client_us[name]):.0f} us a sample")
        for name, (gets, body, count) in traffic.items():
            if name.startswith("disk"):
                continue
            print(f"{name}: one epoch: {gets} GETs, {body / 1e6:.2f} MB for {count} samples "
                  f"({count * record_bytes / 1e6:.2f} MB of records)")
        med = {k: statistics.median(v) for k, v in times.items()}
        print(f"ratio: bucket / disk samples a second, train.py's DataLoader = {med['bucket'] / med['disk']:.2f} "
              "(goal >= 0.9)")
        print(f"ratio: bucket / disk samples a second, ds.loader = "
              f"{med['bucket ds.loader'] / med['disk ds.loader']:.2f} (goal >= 0.9)")
        cpu = {k: statistics.median(v) for k, v in client_us.items()}
        print(f"ratio: disk / bucket loader CPU a sample, train.py's DataLoader = {cpu['disk'] / cpu['bucket']:.2f} "
              "(the bucket's ceiling against the disk with the server on other machines)")
        if "litdata" in med:
            print(f"ratio: bucket / litdata samples a second = {med['bucket'] / med['litdata']:.2f} (goal >= 2)")
        gets, body, count = traffic["bucket"]
        print(f"ratio: bucket bytes read / records read = {body / (count * record_bytes):.3f} (goal <= 1.1)")
        print(f"ratio: bucket requests / samples = {gets / count:.3f} (goal <= 1)")
        print(f"time to the first batch from the bucket: {statistics.median(first['bucket']):.2f} s (goal <= 2)")
        server.stdin.close()
        server.wait(timeout=30)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()

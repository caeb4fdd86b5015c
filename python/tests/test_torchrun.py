"""`torchrun --standalone --nproc_per_node=2` (gloo, CPU) runs torchrun_check.py: shards
by rank without a sampler argument (disjoint, equal counts, union the split), epochs
with persistent workers, resume after k batches on each rank, DDP gradients equal on
both ranks."""

import json
import os
import pathlib
import subprocess
import sys

import pytest

pytest.importorskip("torch", reason="SKIPPED: torch is not installed")

HERE = pathlib.Path(__file__).resolve().parent


def test_two_ranks_under_torchrun(dataset, tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in [*sys.path, env.get("PYTHONPATH", "")] if p)
    run = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
         str(HERE / "torchrun_check.py"), str(dataset), str(tmp_path)],
        env=env, capture_output=True, text=True, timeout=300,
    )
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-8000:]
    reports = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert [r["rank"] for r in reports] == [0, 1] and {r["world"] for r in reports} == {2}
    for split in ("train", "test", "None"):
        a, b = reports[0][split], reports[1][split]
        for ea, eb in zip(a["epochs"], b["epochs"]):
            assert len(ea["indices"]) == len(eb["indices"]) and ea["batches"] == eb["batches"]
            assert not set(ea["indices"]) & set(eb["indices"]) or a["remainder"] == "pad"
        # Two epochs, two orders.
        assert a["epochs"][0]["indices"] != a["epochs"][1]["indices"]
    assert {r["resume"]["remaining"] for r in reports} == {reports[0]["resume"]["remaining"]}
    assert reports[0]["ddp"]["grad_norm"] == reports[1]["ddp"]["grad_norm"]
    assert reports[0]["ddp"]["own_norm"] != reports[1]["ddp"]["own_norm"]

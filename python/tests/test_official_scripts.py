"""The official train.py and test.py on a converted dataset (`python -m arkit_tool.official`):
the generated dataset class, its epochs without set_epoch, its compute_metrics against the
official one, and (with ARKIT_OFFICIAL_DIR, a checkout of cbsropenproject/6dof_face) the
official scripts themselves, unchanged but for CPU, for two epochs and a test."""

import ast
import json
import os
import pathlib
import pickle
import re
import shutil
import subprocess
import sys
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="SKIPPED: torch is not installed")

import arkit_tool  # noqa: E402
from arkit_tool import official  # noqa: E402

OFFICIAL = os.environ.get("ARKIT_OFFICIAL_DIR")


def official_dir():
    if not OFFICIAL or not (pathlib.Path(OFFICIAL) / "data" / "arkit_dataset.py").exists():
        pytest.skip("SKIPPED: set ARKIT_OFFICIAL_DIR to a checkout of cbsropenproject/6dof_face")
    return pathlib.Path(OFFICIAL)


def official_compute_metrics(code):
    """`ARKitDataset.compute_metrics` of the official data/arkit_dataset.py, compiled on
    its own from the checkout's source: the module around it imports the Cython build."""
    path = code / "data" / "arkit_dataset.py"
    tree = ast.parse(path.read_text(encoding="utf-8"))
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "ARKitDataset")
    fn = next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "compute_metrics")
    ns = {"np": np}
    exec(compile(ast.Module(body=[fn], type_ignores=[]), str(path), "exec"), ns)

    def call(inference_data, evaluation):
        opt = types.SimpleNamespace(eval=True) if evaluation else types.SimpleNamespace()
        return ns["compute_metrics"](types.SimpleNamespace(opt=opt), inference_data)

    return call


def inference_data(rng, batches=(8, 8, 3)):
    """What the official model's inference_curr_batch collects, with its dtypes
    (3DRecon float32: the model's vertices are float32)."""
    n = sum(batches)
    d = {k: [float(x) for x in rng.uniform(0, 2, len(batches))] for k in official.LOSSES}
    d["batch_size"] = list(batches)
    for k in ["pitch_mae", "yaw_mae", "roll_mae"]:
        d[k] = [np.float64(x) for x in rng.uniform(0, 20, n)]
    for k in ["tx_mae", "ty_mae", "tz_mae", "ADD", "IoU"]:
        d[k] = [np.float64(x) for x in rng.uniform(0, 0.05, n)]
    d["3DRecon"] = [np.float32(x) for x in rng.uniform(0, 0.01, n)]
    d.update(strict_success=int(rng.integers(0, n)), easy_success=int(rng.integers(0, n)),
             total_count=n, pnp_fail=1)
    return d


def test_compute_metrics_by_hand():
    d = {k: [1.0, 4.0] for k in official.LOSSES}
    d.update(batch_size=[3, 1], pnp_fail=2, strict_success=1, easy_success=2, total_count=4,
             IoU=[0.1, 0.2, 0.3, 0.4], **{"3DRecon": [np.float32(0.002)] * 4},
             ADD=[0.01, 0.03, 0.01, 0.03], pitch_mae=[1, 2, 3, 4], yaw_mae=[0, 0, 0, 1],
             roll_mae=[2, 2, 2, 2], tx_mae=[0.001] * 4, ty_mae=[0.002] * 4, tz_mae=[0.0] * 4)
    losses_only = official.compute_metrics(d, evaluation=False)
    assert list(losses_only) == official.LOSSES
    assert losses_only["loss_total"] == pytest.approx((3 * 1.0 + 1 * 4.0) / 4)  # 1.75
    m = official.compute_metrics(d, evaluation=True)
    assert m["pnp_fail"] == 2
    assert m["3DRecon"] == "2.00 mm" and m["ADD"] == "20.00 mm"
    assert m["pitch_mae"] == "2.50 \u00b0" and m["yaw_mae"] == "0.25 \u00b0"
    assert m["tx_mae"] == "1.00 mm" and m["tz_mae"] == "0.00 mm"
    assert m["5\u00b05cm"] == "25.00 " and m["5\u00b010cm"] == "50.00" and m["mean_IoU"] == "0.2500"


def test_compute_metrics_of_nothing_is_nan_with_a_warning():
    d = {k: [] for k in official.LOSSES + ["batch_size", "IoU"] + [m[1] for m in official.MEANS]}
    d.update(pnp_fail=0, strict_success=0, easy_success=0, total_count=0)
    with pytest.warns(RuntimeWarning, match="no batch was evaluated"):
        m = official.compute_metrics(d, evaluation=True)
    assert np.isnan(m["loss_total"]) and m["ADD"] == "nan mm" and m["5\u00b05cm"] == "nan "


def test_compute_metrics_equals_the_official_function():
    compute = official_compute_metrics(official_dir())
    rng = np.random.default_rng(7)
    for trial in range(20):
        d = inference_data(rng, batches=tuple(int(b) for b in rng.integers(1, 65, 1 + trial % 5)))
        for evaluation in (False, True):
            ours, theirs = official.compute_metrics(d, evaluation), compute(d, evaluation)
            assert list(ours) == list(theirs)
            for k in theirs:
                assert type(ours[k]) is type(theirs[k]) and ours[k] == theirs[k], (k, ours[k], theirs[k])


def opt(dataset, is_train, **kw):
    """The official options the dataset reads (no dataroot: the official options have none)."""
    o = types.SimpleNamespace(isTrain=is_train, img_size=192, n_pts=64, batch_size=4,
                              max_dataset_size=float("inf"), debug=False,
                              arkittool_dataset=str(dataset), arkittool_compat="official",
                              arkittool_train_split="train", arkittool_test_split="test",
                              arkittool_seed=0, arkittool_resources=None, arkittool_crop_store="auto")
    o.__dict__.update(kw)
    return o


class Generated(official.OfficialScriptsDataset, torch.utils.data.Dataset):
    pass


def official_loader(ds, o, workers):
    """The official CustomDatasetDataLoader's DataLoader (data/__init__.py)."""
    return torch.utils.data.DataLoader(ds, batch_size=o.batch_size, shuffle=not getattr(o, "serial_batches", False),
                                       num_workers=workers, drop_last=True)


def served(log):
    return [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []


def test_splits_and_keys_follow_the_official_options(dataset):
    data = arkit_tool.open_dataset(dataset)
    train = Generated(opt(dataset, True))
    val = Generated(opt(dataset, False))
    assert len(train) == data.splits["train"] and len(val) == data.splits["test"]
    assert {train.ds.key(i)[3] for i in range(len(train))} == {"train"}
    assert train.ds.mode == "train" and val.ds.mode == "eval"
    batch = val.__getitems__([0, 1])
    for k in ["tform_inv", "R_t", "img_path", "subjectid", "imgid", "facial_action", "corr_mat"]:
        assert k in batch[0], k
    assert batch[0]["corr_mat"].shape == (64, 1220)
    assert len(Generated(opt(dataset, False, debug=True))) == min(1394, len(val))
    # Picklable for spawn-started workers, the same samples after the round trip.
    again = pickle.loads(pickle.dumps(val))
    np.testing.assert_array_equal(again.__getitems__([1])[0]["img"], batch[1]["img"])
    with pytest.raises(SystemExit, match="--arkittool_dataset"):
        Generated(opt(dataset, True, arkittool_dataset=None))
    with pytest.raises(SystemExit, match="no samples"):
        Generated(opt(dataset, True, arkittool_train_split="nope"))


def check_epochs(ds, o, workers, log):
    """Two epochs as train.py runs them (no set_epoch; in order, so that batch b holds
    samples 4b..4b+3): every sample is ds.item(i, key) of its epoch's key, one key per
    epoch, a new key each epoch."""
    keys = []
    for _ in range(2):
        start = len(served(log))
        batches = list(official_loader(ds, o, workers))
        records = served(log)[start:]
        assert len(records) == len(batches) == len(ds) // o.batch_size
        epoch_keys = {r["epoch"] for r in records}
        assert len(epoch_keys) == 1, epoch_keys
        keys.append(epoch_keys.pop())
        for r in records:
            b = batches[r["indices"][0] // o.batch_size]
            for j, i in enumerate(r["indices"]):
                np.testing.assert_array_equal(b["img"][j].numpy(), ds.ds.item(i, keys[-1])["img"])
                np.testing.assert_array_equal(b["choose"][j].numpy(), ds.ds.item(i, keys[-1])["choose"])
    assert keys[0] != keys[1]
    return keys


def test_epochs_advance_without_set_epoch(dataset, tmp_path, monkeypatch):
    log = tmp_path / "served.jsonl"
    monkeypatch.setenv(official.LOG_ENV, str(log))
    o = opt(dataset, True, serial_batches=True)
    # No workers: the batches served so far count the epochs.
    assert check_epochs(Generated(o), o, 0, log) == [0, 1]
    # Workers: each epoch's base seed (fresh workers every epoch), shared by both workers.
    keys = check_epochs(Generated(o), o, 2, log)
    assert all(k & official.SEED_KEY_BIT for k in keys)
    # set_epoch, when called (train.py has it commented out), is the key whatever the workers.
    ds = Generated(o)
    ds.current_epoch = 3
    a = list(official_loader(ds, types.SimpleNamespace(batch_size=4, serial_batches=True), 0))
    b = list(official_loader(ds, types.SimpleNamespace(batch_size=4, serial_batches=True), 2))
    for x, y in zip(a, b):
        assert torch.equal(x["img"], y["img"])
    np.testing.assert_array_equal(a[0]["img"][0].numpy(), ds.ds.item(0, 3)["img"])


def test_counted_epochs_follow_max_dataset_size():
    assert official._served_per_epoch(10, 4, float("inf")) == 8
    # the loop breaks after the batch i with i * 4 >= 5: batches 0, 1, 2 are fetched
    assert official._served_per_epoch(40, 4, 5) == 12
    assert official._served_per_epoch(40, 4, 8) == 12
    assert official._served_per_epoch(3, 4, float("inf")) == 0


def test_a_bad_sample_is_reported_and_left_out(dataset, tmp_path, capfd):
    o = opt(dataset, False, arkittool_crop_store="none")
    ds = Generated(o)
    path = ds.ds.item(1)["img_path"]
    broken = tmp_path / "moved.jpg"
    shutil.move(path, broken)
    try:
        batch = ds.__getitems__([0, 1, 2])
    finally:
        shutil.move(broken, path)
    assert [b["imgid"] for b in batch] == [ds.ds.key(0)[2], ds.ds.key(2)[2]]
    assert f"skipped sample 1 ({'/'.join(ds.ds.key(1)[:3])})" in capfd.readouterr().err


def fake_official(tmp_path):
    """The two files of the official data/ folder the command checks and imports."""
    code = tmp_path / "code"
    (code / "data").mkdir(parents=True)
    (code / "data" / "__init__.py").write_text(
        'import importlib\n'
        'def find_dataset_using_name(name):\n'
        '    lib = importlib.import_module("data." + name + "_dataset")\n'
        '    from data.base_dataset import BaseDataset\n'
        '    return [c for n, c in lib.__dict__.items() if n.lower() == name.replace("_", "") + "dataset"\n'
        '            and issubclass(c, BaseDataset)][0]\n')
    (code / "data" / "base_dataset.py").write_text(
        "import torch.utils.data as data\nfrom abc import ABC, abstractmethod\n"
        "class BaseDataset(data.Dataset, ABC):\n"
        "    def __init__(self, opt):\n        self.root = opt.dataroot\n"
        "    @abstractmethod\n    def __len__(self):\n        return 0\n")
    return code


def test_command_writes_one_file_and_prints_the_flags(dataset, tmp_path, capsys):
    code = fake_official(tmp_path)
    assert official.main([str(code), "--dataset", str(dataset)]) == 0
    out = capsys.readouterr().out
    assert f"--dataset_mode arkittool --arkittool_dataset {os.path.abspath(dataset)}" in out
    target = code / "data" / "arkittool_dataset.py"
    assert sorted(p.name for p in (code / "data").iterdir()) == ["__init__.py", "arkittool_dataset.py", "base_dataset.py"]
    # Loaded the way data/__init__.py loads it; BaseDataset.__init__ (opt.dataroot) not called.
    script = ("import sys, types; sys.path.insert(0, sys.argv[1]); import data\n"
              "cls = data.find_dataset_using_name('arkittool')\n"
              "o = types.SimpleNamespace(isTrain=True, img_size=192, n_pts=32, batch_size=2, debug=False,\n"
              "    max_dataset_size=float('inf'), arkittool_dataset=sys.argv[2], arkittool_compat='official',\n"
              "    arkittool_train_split='train', arkittool_test_split='test', arkittool_seed=0)\n"
              "print(cls.__name__, len(cls(o)), 'lib.mesh' in sys.modules)\n")
    r = subprocess.run([sys.executable, "-c", script, str(code), str(dataset)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["ArkittoolDataset", str(arkit_tool.open_dataset(dataset).splits["train"]), "False"]
    # Running it again replaces its own file; a file of that name it did not write is refused.
    assert official.main([str(code), "--dataset", str(dataset)]) == 0
    target.write_text("# someone else's\n")
    with pytest.raises(SystemExit, match="not written by this command"):
        official.main([str(code), "--dataset", str(dataset)])
    assert target.read_text() == "# someone else's\n"
    assert official.main([str(code), "--dataset", str(dataset), "--force"]) == 0
    assert target.read_text().startswith(official.MARKER)
    assert not [p for p in (code / "data").iterdir() if p.name.startswith(".")]  # no temporary left
    with pytest.raises(SystemExit, match="not a checkout of the official code"):
        official.main([str(tmp_path), "--dataset", str(dataset)])
    with pytest.raises(SystemExit, match="no samples in split 'val'"):
        official.main([str(code), "--dataset", str(dataset), "--test-split", "val"])


# --- The official scripts themselves (ARKIT_OFFICIAL_DIR) -------------------------------

# What a CPU run of the official code needs, and nothing else: two tensors made on
# 'cuda', and save_networks, which on CPU saves the DataParallel wrapper's keys
# ('module.' prefix) that its own load_networks cannot read.
CPU_PATCHES = [
    ("models/network.py", "torch.zeros(d_model, height, width).to(device='cuda')",
     "torch.zeros(d_model, height, width).to(device='cpu')"),
    ("models/loss.py", "torch.FloatTensor(mask).to(device='cuda')", "torch.FloatTensor(mask).to(device='cpu')"),
    ("models/base_model.py", "torch.save(net.cpu().state_dict(), save_path)",
     "torch.save(getattr(net, 'module', net).cpu().state_dict(), save_path)"),
]


def cpu_copy(code, dest):
    shutil.copytree(code, dest, ignore=shutil.ignore_patterns(".git", "*.so", "checkpoint*"))
    for rel, old, new in CPU_PATCHES:
        p = dest / rel
        text = p.read_text(encoding="utf-8")
        assert text.count(old) == 1, (rel, old)
        p.write_text(text.replace(old, new), encoding="utf-8")
    # The backbone loads ImageNet weights from download.pytorch.org into ./models; with no
    # network here, a random ResNet-18 stands in at the cached file's path.
    sys.path.insert(0, str(dest))
    try:
        from models.resnet import model_urls, resnet18

        net = resnet18(fully_conv=True, pretrained=False, output_stride=32, remove_avg_pool_layer=True)
        torch.save(net.state_dict(), dest / "models" / model_urls["resnet18"].rsplit("/", 1)[1])
    finally:
        sys.path.remove(str(dest))
        for name in [m for m in sys.modules if m == "models" or m.startswith("models.")]:
            del sys.modules[name]


def official_build(imported):
    """The official loader's Cython rasterizers (lib/mesh, lib/mesh_p, lib/Sim3DR) among
    the modules a run imported."""
    return [m for m in imported if m == "lib" or m.startswith("lib.")]


def run_script(code, args, log, env_extra=None):
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore", **(env_extra or {}))
    env[official.LOG_ENV] = str(log)
    env["PYTHONPATH"] = os.pathsep.join(p for p in [env.get("PYTHONPATH", ""), str(code)] if p)
    r = subprocess.run([sys.executable, "-X", "importtime", *args], cwd=code, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    imported = [line.rsplit("|", 1)[-1].strip() for line in r.stderr.splitlines() if line.startswith("import time:")]
    return r.stdout, imported


@pytest.fixture(scope="module")
def official_dataset(tmp_path_factory):
    """6 training and 2 test samples (800x800, the real topology when the resource files
    are there), with the official rules' crop store: the official network takes about a
    second a sample on a CPU."""
    from conftest import BIN, RESOURCES, run

    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    base = tmp_path_factory.mktemp("official_scripts")
    res = ["--resources", RESOURCES] if (RESOURCES / "triangles.npy").exists() else []
    run(BIN, "synth", "--output", base / "release", "--subjects", 4, "--images-per-subject", 2,
        "--size", "800x800", "--seed", 4, "--test-fraction", 0.25, *res)
    run(BIN, "convert", "--input", base / "release", "--output", base / "converted", *res)
    run(BIN, "crops", "--dataset", base / "converted", "--compat", "official", *res)
    return base / "converted"


def test_official_train_and_test_scripts_run_unchanged(official_dataset, tmp_path):
    code = tmp_path / "code"
    cpu_copy(official_dir(), code)
    assert official.main([str(code), "--dataset", str(official_dataset)]) == 0
    flags = official.flags(str(official_dataset))
    splits = arkit_tool.open_dataset(official_dataset).splits
    common = ["--gpu_ids", "-1", "--n_pts", "256", "--checkpoints_dir", str(tmp_path / "ckpt")]
    for workers in (0, 2):
        log = tmp_path / f"served{workers}.jsonl"
        name = f"w{workers}"
        out, imported = run_script(code, ["train.py", *flags, *common, "--name", name,
                                          "--num_threads", str(workers), "--batch_size", "2",
                                          "--n_epochs", "1", "--n_epochs_decay", "1", "--print_freq", "2"], log)
        # Nothing imported the official loader or its Cython build.
        # (-X importtime lists what `import` statements load: data/__init__.py loads the
        # dataset module by importlib, unlisted, but what that module imports is listed.)
        assert "arkit_tool.official" in imported
        assert not official_build(imported)
        assert "End of epoch 2 / 2" in out and "evaluation epoch 2 end" in out
        losses = [float(x) for x in re.findall(r"\(epoch: \d, iters: \d+, .*?\) total: ([0-9.]+)", out)]
        assert len(losses) == 2 * (splits["train"] // 2) and all(np.isfinite(losses))
        # Two training epochs, each its own key; the validation set is the test split.
        records = served(log)
        train = [r for r in records if "indices" in r and r["train"]]
        assert len(train) == 2 * (splits["train"] // 2)
        keys = [r["epoch"] for r in train]
        half = len(keys) // 2
        assert len(set(keys[:half])) == 1 and len(set(keys[half:])) == 1 and keys[0] != keys[-1]
        if workers == 0:
            assert (keys[0], keys[-1]) == (0, 1)
        assert {r["split"] for r in records if "indices" in r and not r["train"]} <= {"test"}
        for f in ["latest_net_R.pth", "1_net_R.pth", "2_net_R.pth"]:
            assert (tmp_path / "ckpt" / name / f).exists(), f
    # test.py on the saved checkpoint, batch 2 (its 64 with drop_last gives no batch here).
    log = tmp_path / "test.jsonl"
    out, imported = run_script(code, ["test.py", *flags, *common, "--name", "w2", "--batch_size", "2",
                                      "--num_threads", "0"], log)
    assert "arkit_tool.official" in imported and not official_build(imported)
    assert "[metric]" in out and "mean_IoU" in out
    record = next(r["compute_metrics"] for r in served(log) if "compute_metrics" in r)
    assert record["evaluation"] is True
    data = record["inference_data"]
    assert data["total_count"] == splits["test"] // 2 * 2 > 0
    # Our compute_metrics and the official one, on the same inference data.
    theirs = official_compute_metrics(official_dir())(data, True)
    ours = official.compute_metrics(data, True)
    assert list(ours) == list(theirs)
    assert all(ours[k] == theirs[k] for k in theirs), (ours, theirs)
    for k in ["5\u00b05cm", "ADD", "mean_IoU"]:
        assert repr(record["metrics"][k]) in out  # what test.py printed

"""`arkit-tool export-onnx` run with onnxruntime equals candle (`predict --dump`).

For the shipped tiny model and for a paper-config model (192 px, ResNet-18 widths; one
training step from the official initialisation, the cheapest honest weights of that
shape), on the test split of a small synthetic dataset:

- fed the dumped crop and chosen pixels, onnxruntime's seg_logits, uv_map, assignment,
  points and vertices equal candle's within `REL_TOL` of each output's largest
  magnitude (measured: at most ~1e-6 relative, see docs/onnx.md);
- the ONNX side's own point choice (its mask, `_native.choose_points`, the sample's
  seed `seed ^ ((shard << 32) | row)`) gives the dump's `choose`;
- a batch of 3 crops equals the 3 crops run one by one (the batch dimension is dynamic);
- `onnx.checker` accepts both graphs (when the `onnx` package is installed);
- planted faults are caught: the exported up-sampling switched to half-pixel
  coordinates, and the position encoding's x and y swapped, each break the equality.
"""

import json
import pathlib
import shutil
import subprocess

import numpy as np
import pytest

from conftest import BIN, run

ort = pytest.importorskip("onnxruntime", reason="SKIPPED: onnxruntime is not installed")

from arkit_tool import _native  # noqa: E402
from arkit_tool.onnx import OnnxPerspNet  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]
TINY = ROOT / "models" / "tiny-synthetic"
SEED = 5

# Relative tolerance: max |onnxruntime - candle| <= REL_TOL * max |candle| per output
# (and per sample). The measured ratio is below 2e-6 for both configs (docs/onnx.md).
REL_TOL = 1e-4
OUTPUTS = [("seg_logits", "seg_logits"), ("uv_map", "uv_map"), ("assignment", "assignment"),
           ("points", "points_raw"), ("vertices", "vertices_raw")]


def sample_seeds(dataset, seed):
    """`predict`'s seed for each sample key: `seed ^ ((shard << 32) | row)`."""
    ds = _native.Dataset(str(dataset))
    manifest = json.loads(ds.manifest_json())
    keys = ds.keys()
    out, i = {}, 0
    for shard in manifest["shards"]:
        for row in range(shard["rows"]):
            out["/".join(keys[i][:3])] = seed ^ ((shard["index"] << 32) | row)
            i += 1
    assert i == len(keys)
    return out


def export_and_dump(tmp, model, dataset):
    out = tmp / "onnx"
    run(BIN, "export-onnx", "--model", model, "--output", out)
    dump = tmp / "dump.npz"
    run(BIN, "predict", "--model", model, "--dataset", dataset, "--seed", SEED,
        "--output", tmp / "pred.parquet", "--dump", dump)
    z = np.load(dump)
    keys = sorted({n.rsplit("/", 1)[0] for n in z.files if n != "vertex_uv"})
    assert len(keys) >= 3, keys
    return out, {k: {n: z[f"{k}/{n}"] for n in
                     ("image", "choose", "seg_logits", "uv_map", "assignment", "points", "vertices")}
                 for k in keys}


@pytest.fixture(scope="module")
def tiny(dataset, tmp_path_factory):
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    return export_and_dump(tmp_path_factory.mktemp("onnx-tiny"), TINY, dataset)


@pytest.fixture(scope="module")
def paper(dataset, tmp_path_factory):
    """A paper-config model: the official shapes after one training step (batch 1)."""
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    tmp = tmp_path_factory.mktemp("onnx-paper")
    run(BIN, "render", "--dataset", dataset, "--size", 192, "--points", 1024, "--output", tmp / "t192")
    run(BIN, "train", "--dataset", dataset, "--targets", tmp / "t192", "--config", "paper",
        "--steps", 1, "--batch", 1, "--output", tmp / "model")
    return export_and_dump(tmp, tmp / "model", dataset)


def worst_ratio(got, want):
    return float(np.abs(got - want).max() / np.abs(want).max())


def check_equal(folder, dumped, dataset):
    """Asserts onnxruntime equals the dump; returns the worst ratio per output."""
    net = OnnxPerspNet(folder)
    seeds = sample_seeds(dataset, SEED)
    worst = {n: 0.0 for n, _ in OUTPUTS}
    for key, d in dumped.items():
        p = net.predict(d["image"][None], choose=d["choose"][None])
        for name, attr in OUTPUTS:
            r = worst_ratio(getattr(p, attr)[0], d[name])
            worst[name] = max(worst[name], r)
            assert r <= REL_TOL, f"{key} {name}: max |ort - candle| / max |candle| = {r:.3g}"
        np.testing.assert_allclose(p.points[0], d["points"] / 9, rtol=0, atol=REL_TOL * np.abs(d["points"]).max() / 9)
        # The ONNX side's own point choice: its mask, the sample's seed.
        own = net.predict(d["image"][None], seeds=seeds[key])
        candle_mask = d["seg_logits"][1] >= d["seg_logits"][0]
        differ = own.mask[0] != candle_mask
        # A pixel may only flip where candle's two logits are within the tolerance.
        margin = np.abs(d["seg_logits"][1] - d["seg_logits"][0])
        bound = REL_TOL * np.abs(d["seg_logits"]).max()
        assert np.all(margin[differ] <= bound), f"{key}: the mask differs beyond the tolerance"
        if not differ.any():
            np.testing.assert_array_equal(own.choose[0], d["choose"], err_msg=key)
    return worst


def test_tiny_onnxruntime_equals_candle(tiny, dataset):
    folder, dumped = tiny
    worst = check_equal(folder, dumped, dataset)
    print("tiny: worst relative differences", worst)


def test_paper_onnxruntime_equals_candle(paper, dataset):
    folder, dumped = paper
    m = json.loads((folder / "onnx.json").read_text())
    assert (m["input_size"], m["points"], m["vertices"]) == (192, 1024, 1220)
    assert m["config"]["encoder_widths"] == [64, 128, 256, 512]
    worst = check_equal(folder, dumped, dataset)
    print("paper: worst relative differences", worst)


def test_the_choice_matches_predict_exactly(tiny, dataset):
    """On the tiny model every sample's mask is well separated: the choice is the dump's."""
    folder, dumped = tiny
    net = OnnxPerspNet(folder)
    seeds = sample_seeds(dataset, SEED)
    for key, d in dumped.items():
        p = net.predict(d["image"][None], seeds=seeds[key])
        np.testing.assert_array_equal(p.choose[0], d["choose"], err_msg=key)
        # Another seed picks other pixels (the seed is used).
        q = net.predict(d["image"][None], seeds=seeds[key] + 1)
        assert not np.array_equal(q.choose[0], d["choose"])


def test_a_batch_equals_singles(tiny):
    folder, dumped = tiny
    net = OnnxPerspNet(folder)
    keys = sorted(dumped)[:3]
    images = np.stack([dumped[k]["image"] for k in keys])
    seeds = [11, 12, 13]
    batch = net.predict(images, seeds=seeds)
    assert batch.assignment.shape == (3, net.points, net.vertices)
    for i in range(3):
        one = net.predict(images[i:i + 1], seeds=seeds[i])
        np.testing.assert_array_equal(batch.choose[i], one.choose[0])
        for _, attr in OUTPUTS:
            a, b = getattr(batch, attr)[i], getattr(one, attr)[0]
            assert worst_ratio(a, b) <= 1e-5, attr


def test_manifest_and_checker(tiny):
    folder, _ = tiny
    m = json.loads((folder / "onnx.json").read_text())
    assert m["opset"] == 17 and m["uv_scale"] == 9
    assert [v["name"] for v in m["points_graph"]["inputs"]] == ["image_features", "uv_features", "uv_map", "choose"]
    assert m["dense"]["inputs"][0]["shape"] == ["batch", 3, 64, 64]
    onnx = pytest.importorskip("onnx", reason="SKIPPED: the onnx package is not installed")
    for f in ("dense.onnx", "points.onnx"):
        model = onnx.load(str(folder / f))
        onnx.checker.check_model(model, full_check=True)
        assert model.opset_import[0].version == 17
        assert model.graph.input[0].type.tensor_type.shape.dim[0].dim_param == "batch"


def planted(folder, tmp, graph_file, edit):
    onnx = pytest.importorskip("onnx", reason="SKIPPED: the onnx package is not installed")
    out = tmp / "planted"
    shutil.copytree(folder, out)
    model = onnx.load(str(out / graph_file))
    edit(onnx, model)
    onnx.save(model, str(out / graph_file))
    return out


def test_planted_faults_are_caught(tiny, dataset, tmp_path):
    folder, dumped = tiny

    def half_pixel(onnx, model):
        for n in model.graph.node:
            if n.op_type == "Resize":
                for a in n.attribute:
                    if a.name == "coordinate_transformation_mode":
                        a.s = b"half_pixel"

    def swap_xy(onnx, model):
        for n in model.graph.node:
            if n.op_type in ("Mod", "Div"):
                n.op_type = "Div" if n.op_type == "Mod" else "Mod"

    for graph_file, edit in (("dense.onnx", half_pixel), ("points.onnx", swap_xy)):
        bad = planted(folder, tmp_path / graph_file, graph_file, edit)
        with pytest.raises(AssertionError):
            check_equal(bad, dumped, dataset)


def test_direct_baseline_and_non_model_folders_are_refused(tmp_path):
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN}")
    direct = tmp_path / "direct"
    shutil.copytree(TINY, direct)
    cfg = json.loads((direct / "perspnet.json").read_text())
    cfg["config"]["architecture"] = "direct"
    (direct / "perspnet.json").write_text(json.dumps(cfg))
    r = subprocess.run([str(BIN), "export-onnx", "--model", str(direct), "--output", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "direct baseline" in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()
    r = subprocess.run([str(BIN), "export-onnx", "--model", str(tmp_path), "--output", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "no perspnet.json" in r.stderr, r.stderr

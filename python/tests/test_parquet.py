"""The samples tables as other readers see them: fixed-size lists with their shapes and the
`huggingface` features record (samples format 2), and datasets written before (format 1,
variable-length lists) still opening."""

import hashlib
import json
import pathlib
import shutil

import numpy as np
import pytest

import arkit_tool
from arkit_tool import ARKitFaceDataset, DataError

pa = pytest.importorskip("pyarrow", reason="SKIPPED: pyarrow is not installed")
pq = pytest.importorskip("pyarrow.parquet", reason="SKIPPED: pyarrow is not installed")

SHAPES = {"verts": ((1220, 3), pa.float32()), "R_t": ((4, 4), pa.float64()),
          "landmarks_2d": ((68, 2), pa.float32())}


def shards(dataset):
    return arkit_tool.open_dataset(dataset).shard_files


def test_fixed_shape_columns_are_fixed_size_lists_with_their_shapes_recorded(dataset):
    data = arkit_tool.open_dataset(dataset)
    table = pq.read_table(shards(dataset)[0])
    for name, ((rows, cols), leaf) in SHAPES.items():
        t = table.schema.field(name).type
        assert pa.types.is_fixed_size_list(t) and t.list_size == rows, (name, t)
        inner = t.value_type
        assert pa.types.is_fixed_size_list(inner) and inner.list_size == cols, (name, t)
        assert inner.value_type == leaf, (name, t)
    # The Hugging Face `datasets` features record, every column in order.
    meta = json.loads(table.schema.metadata[b"huggingface"])
    features = meta["info"]["features"]
    assert list(features) == table.column_names
    dtypes = {pa.float32(): "float32", pa.float64(): "float64"}
    for name, ((rows, cols), leaf) in SHAPES.items():
        assert features[name] == {"shape": [rows, cols], "dtype": dtypes[leaf], "_type": "Array2D"}
    assert features["img_id"] == {"dtype": "string", "_type": "Value"}
    assert features["image_width"] == {"dtype": "uint32", "_type": "Value"}
    assert json.loads(table.schema.metadata[b"arkit_tool"])["samples_format"] == 2
    # The values are the sample's, in their shape, with no reshaping by the reader.
    verts = np.asarray(table["verts"][0].as_py(), dtype=np.float32)
    assert verts.shape == (1220, 3)
    np.testing.assert_array_equal(verts, data.sample(0)["verts"])
    rt = np.asarray(table["R_t"][0].as_py())
    assert rt.shape == (4, 4)
    np.testing.assert_array_equal(rt, data.sample(0)["R_t"])
    np.testing.assert_array_equal(np.asarray(table["landmarks_2d"][0].as_py()), data.sample(0)["landmarks_2d"])


def test_polars_reads_arrays(dataset):
    pl = pytest.importorskip("polars", reason="SKIPPED: polars is not installed")
    df = pl.read_parquet(shards(dataset)[0])
    assert df.schema["verts"] == pl.Array(pl.Float32, (1220, 3))
    assert df["verts"].to_numpy().shape == (df.height, 1220, 3)


def test_hugging_face_datasets_yields_1220_by_3(dataset):
    datasets = pytest.importorskip("datasets", reason="SKIPPED: Hugging Face datasets is not installed")
    ds = datasets.Dataset.from_parquet(shards(dataset)[0]).with_format("numpy")
    assert ds[0]["verts"].shape == (1220, 3) and ds[0]["R_t"].shape == (4, 4)
    assert ds[0]["landmarks_2d"].shape == (68, 2)


def as_format1(table):
    """The table as versions before samples format 2 wrote it (polars: large lists, flat)."""
    columns = []
    for name in table.column_names:
        col = table[name]
        if name in SHAPES:
            leaf = SHAPES[name][1]
            col = pa.chunked_array([
                pa.array([None if v is None else list(np.asarray(v).reshape(-1)) for v in c.to_pylist()],
                         type=pa.large_list(leaf))
                for c in col.chunks
            ], type=pa.large_list(leaf))
        columns.append(col)
    return pa.Table.from_arrays(columns, names=table.column_names)


def rewrite_shards(dataset, out, change=lambda name, table: table):
    """A copy of `dataset` whose samples shards are rewritten (manifest updated to match)."""
    shutil.copytree(dataset, out)
    manifest_path = out / "dataset.json"
    manifest = json.loads(manifest_path.read_text())
    for shard in manifest["shards"]:
        path = out / shard["samples_file"]
        pq.write_table(change(path.name, as_format1(pq.read_table(path))), path, compression="zstd")
        data = path.read_bytes()
        shard["bytes"] = len(data)
        shard["sha256"] = hashlib.sha256(data).hexdigest()
        shard["tail_sha256"] = hashlib.sha256(data[-64 * 1024:]).hexdigest()
    manifest_path.write_text(json.dumps(manifest, indent=2))
    return out


def test_a_dataset_written_before_fixed_shapes_still_opens(dataset, tmp_path):
    old = rewrite_shards(pathlib.Path(dataset), tmp_path / "old")
    t = pq.read_table(old / json.loads((old / "dataset.json").read_text())["shards"][0]["samples_file"])
    assert pa.types.is_large_list(t.schema.field("verts").type)
    assert b"huggingface" not in (t.schema.metadata or {})
    new, before = arkit_tool.open_dataset(dataset), arkit_tool.open_dataset(old)
    assert before.keys == new.keys
    for i in range(len(new)):
        a, b = new.sample(i), before.sample(i)
        for k in ("verts", "R_t", "landmarks_2d"):
            np.testing.assert_array_equal(a[k], b[k])
            assert a[k].shape == b[k].shape
    x = ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=64).item(1)
    y = ARKitFaceDataset(old, split=None, mode="eval", n_pts=64).item(1)
    for k in x:
        if isinstance(x[k], np.ndarray):
            np.testing.assert_array_equal(x[k], y[k])


def test_a_row_of_the_wrong_width_raises_naming_the_file_and_column(dataset, tmp_path):
    def short_verts(name, table):
        if name != "part-00000.parquet":
            return table
        rows = table["verts"].to_pylist()
        rows[1] = rows[1][:-3]
        i = table.column_names.index("verts")
        return table.set_column(i, "verts", pa.array(rows, type=pa.large_list(pa.float32())))

    bad = rewrite_shards(pathlib.Path(dataset), tmp_path / "bad", short_verts)
    with pytest.raises(DataError) as e:
        arkit_tool.open_dataset(bad).sample(0)
    assert "part-00000.parquet" in str(e.value) and "'verts'" in str(e.value)


def test_decode_targets_gives_what_the_loader_computes(dataset, tmp_path):
    """`render`'s compact targets, decoded with plain numpy, equal what ARKitFaceDataset
    computes for the same samples (compat exact, 192 x 192)."""
    from conftest import BIN, run

    out = tmp_path / "rendered"
    run(BIN, "render", "--dataset", dataset, "--output", out)
    rows = []
    for f in sorted((out / "targets").glob("part-*.parquet")):
        rows.extend(pq.read_table(f).to_pylist())
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", corr="sparse", n_pts=64)
    assert len(rows) == len(ds)
    for i in (0, len(ds) - 1):
        t = arkit_tool.decode_targets(rows[i])
        assert (t["subject_id"], t["facial_action"], t["img_id"]) == ds.key(i)[:3]
        d = ds.item(i)
        assert t["mask"].sum() > 1000
        np.testing.assert_array_equal(t["mask"].astype(np.int64), d["mask"])
        face = np.flatnonzero(t["mask"].reshape(-1))
        rank = np.searchsorted(face, d["choose"])
        np.testing.assert_array_equal(face[rank], d["choose"])
        np.testing.assert_array_equal(t["corr_vertices"][rank].astype(np.int64), d["corr_ids"])
        np.testing.assert_allclose(t["corr_weights"][rank], d["corr_weights"], atol=2.0 / 65535)
        assert t["uv_map"].shape == (192, 192, 3) and t["uv_map"].dtype == np.float16
        assert len(t["points"]) == 1024 and t["points"].max() < len(face)
    bad = dict(rows[0], mask_rle=rows[0]["mask_rle"][:-4])
    with pytest.raises(DataError, match="mask_rle"):
        arkit_tool.decode_targets(bad)
    with pytest.raises(DataError, match="uv_size"):
        arkit_tool.decode_targets(dict(rows[0], uv_size=1 << 20))

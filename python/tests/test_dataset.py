"""ARKitFaceDataset, open_dataset, PnP, projection and metrics through the Python package."""

import os
import pathlib
import pickle

import numpy as np
import pytest

import arkit_tool
from arkit_tool import ARKitFaceDataset, DataError

MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)[:, None, None]
STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)[:, None, None]

OFFICIAL_KEYS = {"img", "choose", "model", "uvmap", "nocs", "mask", "corr_mat"}
EVAL_KEYS = {"tform_inv", "R_t", "img_path", "subjectid", "imgid", "facial_action"}


@pytest.mark.parametrize("compat", ["exact", "official"])
@pytest.mark.parametrize("mode", ["train", "eval"])
def test_keys_shapes_and_dtypes_are_the_official_loaders(dataset, compat, mode):
    ds = ARKitFaceDataset(dataset, split=None, mode=mode, compat=compat, n_pts=256)
    d = ds[0]
    assert set(d) == OFFICIAL_KEYS | (EVAL_KEYS if mode == "eval" else set())
    s, n = 192, 256
    expected = {
        "img": ((3, s, s), np.float32),
        "choose": ((n,), np.int64),
        "model": ((1220, 3), np.float32),
        "uvmap": ((3, s, s), np.float32),
        "nocs": ((n, 3), np.float32),
        "mask": ((s, s), np.int64),
        "corr_mat": ((n, 1220), np.float32),
    }
    for k, (shape, dtype) in expected.items():
        assert d[k].shape == shape and d[k].dtype == dtype, k
    if mode == "eval":
        assert d["tform_inv"].shape == (2, 3) and d["R_t"].shape == (4, 4)
        assert os.path.exists(d["img_path"])
    assert d["uvmap"].min() >= -1 and d["uvmap"].max() <= 1
    assert set(np.unique(d["mask"])) <= {0, 1}


@pytest.mark.parametrize("compat", ["exact", "official"])
def test_values_agree_with_the_dataset_and_with_each_other(dataset, compat):
    data = arkit_tool.open_dataset(dataset)
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", compat=compat, n_pts=300, corr="both")
    assert len(ds) == len(data)
    for i in range(len(ds)):
        d, row = ds[i], data.sample(i)
        assert (d["subjectid"], d["facial_action"], d["imgid"]) == data.keys[i]
        np.testing.assert_array_equal(d["model"], row["verts"])
        np.testing.assert_array_equal(d["R_t"], row["R_t"])
        # The dense matrix is the sparse rows scattered; weights sum to 1.
        dense = np.zeros((300, 1220), np.float32)
        np.put_along_axis(dense, d["corr_ids"], d["corr_weights"], axis=1)
        np.testing.assert_array_equal(d["corr_mat"], dense)
        np.testing.assert_allclose(d["corr_mat"].sum(1), 1.0, atol=1e-5)
        # nocs is 4.5 times M X: two paths to the same points.
        np.testing.assert_allclose(d["nocs"], 4.5 * d["corr_mat"] @ d["model"], atol=2e-4)
        # The image is a normalised byte image; the points fall inside the crop.
        bytes_ = (d["img"] * STD + MEAN) * 255
        np.testing.assert_allclose(bytes_, np.round(bytes_), atol=2e-3)
        assert d["choose"].min() >= 0 and d["choose"].max() < 192 * 192
        if compat == "exact":
            # Our points are pixels of the crop mask.
            assert d["mask"].reshape(-1)[d["choose"]].all()


def test_official_points_come_from_the_box_and_land_on_the_crop_mask(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", compat="official", n_pts=256)
    hits = 0
    for i in range(len(ds)):
        d = ds.item(i, extras=True)
        left, top, right, bottom = d["box"]
        crop_w = right - left + 1
        col, row = d["choose_box"] % crop_w + left, d["choose_box"] // crop_w + top
        sx, sy = 191 / (right - left), 191 / (bottom - top)
        # The affine map cv2.getAffineTransform gives: crop = (image - corner) * scale.
        px = np.floor(col * sx + (-left * sx)).astype(np.int64)
        py = np.floor(row * sy + (-top * sy)).astype(np.int64)
        expect = py * 192 + px
        np.testing.assert_array_equal(d["choose"], expect)
        hits += d["mask"].reshape(-1)[d["choose"]].mean()
    # A full-resolution face pixel maps to a crop mask pixel nearly always (the warped
    # mask is rounded, edges can differ).
    assert hits / len(ds) > 0.95


def test_items_are_a_function_of_seed_epoch_and_index(dataset):
    a = ARKitFaceDataset(dataset, split=None, mode="train", n_pts=128, seed=7)
    b = ARKitFaceDataset(dataset, split=None, mode="train", n_pts=128, seed=7)
    x = a[2]
    b[0]
    for k, v in b[2].items():
        np.testing.assert_array_equal(v, x[k])
    a.set_epoch(1)
    assert not np.array_equal(a[2]["img"], x["img"])
    c = ARKitFaceDataset(dataset, split=None, mode="train", n_pts=128, seed=8)
    assert not np.array_equal(c[2]["img"], x["img"])


def test_pickling_reopens_the_loader(dataset):
    ds = ARKitFaceDataset(dataset, split="train", mode="train", n_pts=64)
    ds.set_epoch(3)
    back = pickle.loads(pickle.dumps(ds))
    assert len(back) == len(ds) and back.epoch == 3
    np.testing.assert_array_equal(back[1]["img"], ds[1]["img"])


def test_splits_are_served_separately(dataset):
    data = arkit_tool.open_dataset(dataset)
    train = ARKitFaceDataset(dataset, split="train", mode="eval", n_pts=16)
    test = ARKitFaceDataset(dataset, split="test", mode="eval", n_pts=16)
    assert len(train) == data.splits["train"] and len(test) == data.splits["test"]
    assert len(train) + len(test) == len(data)
    assert {test.key(i)[3] for i in range(len(test))} == {"test"}


def test_a_missing_image_raises_naming_the_file(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=16)
    path = pathlib.Path(ds[0]["img_path"])
    moved = path.with_suffix(".moved")
    path.rename(moved)
    try:
        with pytest.raises(DataError, match=str(path)):
            ds[0]
        ds[1]  # the others are unaffected
    finally:
        moved.rename(path)


def test_bad_arguments_raise_python_errors(dataset, tmp_path):
    with pytest.raises(DataError, match=str(tmp_path)):
        ARKitFaceDataset(tmp_path, split=None)
    with pytest.raises(DataError, match="compat"):
        ARKitFaceDataset(dataset, compat="opencv")
    with pytest.raises(DataError, match="img_size"):
        ARKitFaceDataset(dataset, img_size=8)
    ds = ARKitFaceDataset(dataset, split=None, n_pts=16)
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_open_dataset_serves_samples_by_position_and_key(dataset):
    data = arkit_tool.open_dataset(dataset)
    key = data.keys[3]
    row = data.sample(key)
    assert (row["subject_id"], row["facial_action"], row["img_id"]) == key
    assert row["verts"].shape == (1220, 3) and row["R_t"].shape == (4, 4)
    np.testing.assert_array_equal(row["verts"], data.sample(3)["verts"])
    with pytest.raises(DataError):
        data.index_of(("no", "such", "sample"))
    assert data.manifest["converted"] == len(data)


def test_projection_matches_the_release_formula(dataset):
    data = arkit_tool.open_dataset(dataset)
    row = data.sample(0)
    w, h = row["image_width"], row["image_height"]
    f = 1.57443701  # the release's projection (resources README)
    P = np.array([[f, 0, 0, 0], [0, f, 0, 0], [0, 0, -1.000002, -1], [0, 0, -0.002000002, 0]])
    M1 = np.array([[w / 2, 0, 0, 0], [0, h / 2, 0, 0], [0, 0, 1, 0], [w / 2, h / 2, 0, 1]])
    v = np.hstack([row["verts"].astype(np.float64), np.ones((1220, 1))]) @ row["R_t"] @ P @ M1
    uv = np.stack([v[:, 0] / v[:, 3], h - v[:, 1] / v[:, 3]], axis=1)
    np.testing.assert_allclose(arkit_tool.project(row["verts"], row["R_t"], w, h), uv, atol=1e-3)


def test_pnp_recovers_a_known_pose_with_opencv_conventions():
    rng = np.random.default_rng(0)
    obj = rng.uniform(-0.08, 0.08, (500, 3))
    angle = np.deg2rad(20.0)
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    K_ = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(angle) * K_ + (1 - np.cos(angle)) * K_ @ K_
    t = np.array([0.02, -0.01, 0.5])
    K = np.array([[630.0, 0, 400], [0, 630.0, 400], [0, 0, 1]])
    cam = obj @ R.T + t
    img = cam[:, :2] / cam[:, 2:] * 630.0 + 400
    # 20% outliers, each at least 50 px off (far outside the 8 px threshold).
    img[:100] += rng.uniform(50, 100, (100, 2)) * rng.choice([-1, 1], (100, 2))
    ok, rvec, tvec, inliers = arkit_tool.solve_pnp_ransac(obj, img, K)
    assert ok
    np.testing.assert_allclose(rvec[:, 0], axis * angle, atol=1e-6)
    np.testing.assert_allclose(tvec[:, 0], t, atol=1e-6)
    assert inliers.dtype == np.int32
    np.testing.assert_array_equal(inliers[:, 0], np.arange(100, 500))
    assert arkit_tool.solve_pnp_ransac(obj[:3], img[:3], K) == (False, None, None, None)
    with pytest.raises(DataError):
        arkit_tool.solve_pnp_ransac(obj, img, K, dist_coeffs=[0.1, 0, 0, 0])


def test_evaluate_scores_the_ground_truth_at_zero(dataset):
    data = arkit_tool.open_dataset(dataset)
    truth = {k: data.sample(i)["R_t"] for i, k in enumerate(data.keys)}
    s = arkit_tool.evaluate(dataset, truth)["summary"]
    assert s["samples"] == len(data) and s["pose_failures"] == 0
    for k in ["mae_r_deg", "mae_t_mm", "add_mm", "rotation_mean_deg"]:
        assert abs(s[k]) < 1e-6, k
    assert s["success_5deg5cm_pct"] == 100.0
    # A failed prediction is counted (and replaced by the identity), not dropped.
    truth[data.keys[0]] = None
    s = arkit_tool.evaluate(dataset, truth)["summary"]
    assert s["pose_failures"] == 1 and s["add_mm"] > 1.0
    assert s["success_5deg5cm_pct"] == pytest.approx(100.0 * (len(data) - 1) / len(data))


@pytest.mark.parametrize("compat", ["exact", "official"])
def test_real_topology_items(real_dataset, compat):
    ds = ARKitFaceDataset(real_dataset, split=None, mode="eval", compat=compat)
    d = ds[0]
    assert d["img"].shape == (3, 192, 192) and d["corr_mat"].shape == (1024, 1220)
    np.testing.assert_allclose(d["nocs"], 4.5 * d["corr_mat"] @ d["model"], atol=2e-4)


def test_the_samples_table_is_the_shards_read_by_arrow(dataset):
    pa = pytest.importorskip("pyarrow", reason="SKIPPED: neither polars nor pyarrow is installed")
    data = arkit_tool.open_dataset(dataset)
    table = data.samples
    n = table.num_rows if isinstance(table, pa.Table) else table.height
    assert n == len(data)
    col = table["img_id"].to_pylist() if isinstance(table, pa.Table) else table["img_id"].to_list()
    assert col == [k[2] for k in data.keys]

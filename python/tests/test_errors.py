"""Small errors in the Python API say what is wrong: an index out of range is an
IndexError, a bad argument is named, points given transposed are refused (not
reshaped into other points)."""

import numpy as np
import pytest

import arkit_tool
from arkit_tool import ARKitFaceDataset, DataError


def test_indices_out_of_range_are_index_errors(dataset):
    ds = ARKitFaceDataset(dataset, split=None, mode="eval", n_pts=16, corr="sparse")
    n = len(ds)
    np.testing.assert_array_equal(ds[-n]["img"], ds[0]["img"])
    np.testing.assert_array_equal(ds[-1]["model"], ds[n - 1]["model"])
    for bad in (n, -(n + 1), -(1 << 70), 1 << 70):
        with pytest.raises(IndexError, match=f"out of range for {n} samples"):
            ds[bad]
        with pytest.raises(IndexError):
            ds.__getitems__([0, bad])
        with pytest.raises(IndexError):
            ds.key(bad)
    with pytest.raises(TypeError):
        ds[1.0]
    data = arkit_tool.open_dataset(dataset)
    assert data.sample(-1)["img_id"] == data.keys[-1][2]
    with pytest.raises(IndexError):
        data.sample(-(len(data) + 1))


@pytest.mark.parametrize(
    "argument, value",
    [("seed", -1), ("seed", 1 << 64), ("seed", 0.5), ("n_pts", -3), ("img_size", -192)],
)
def test_a_bad_constructor_argument_is_named(dataset, argument, value):
    with pytest.raises(DataError, match=f"^{argument}: "):
        ARKitFaceDataset(dataset, split=None, **{argument: value})


def test_a_bad_epoch_is_named(dataset):
    ds = ARKitFaceDataset(dataset, split=None, n_pts=16, corr="sparse")
    with pytest.raises(DataError, match="^epoch: "):
        ds.set_epoch(-1)
    with pytest.raises(DataError, match="^epoch: "):
        ds.item(0, epoch=-2)
    assert ds.epoch == 0


def _pose_problem():
    rng = np.random.default_rng(1)
    obj = rng.uniform(-0.08, 0.08, (40, 3))
    t = np.array([0.01, 0.02, 0.5])
    K = np.array([[630.0, 0, 400], [0, 630.0, 400], [0, 0, 1]])
    cam = obj + t
    img = cam[:, :2] / cam[:, 2:] * 630.0 + 400
    return obj, img, K, t


def test_pnp_refuses_transposed_points():
    obj, img, K, t = _pose_problem()
    ok, rvec, tvec, _ = arkit_tool.solve_pnp_ransac(obj, img, K)
    assert ok
    np.testing.assert_allclose(tvec[:, 0], t, atol=1e-6)
    # OpenCV's (N, 1, k) layout is the same points.
    ok2, rvec2, tvec2, _ = arkit_tool.solve_pnp_ransac(obj[:, None], img[:, None], K)
    assert ok2
    np.testing.assert_array_equal(tvec2, tvec)
    for o, i, name in [(obj.T, img, "object_points"), (obj, img.T, "image_points"), (obj.T, img.T, "object_points")]:
        with pytest.raises(DataError, match=rf"^{name}: shape \(\d+, \d+\); expected \(N, \d\) \(transposed"):
            arkit_tool.solve_pnp_ransac(o, i, K)
    with pytest.raises(DataError, match="object_points"):
        arkit_tool.solve_pnp_ransac(obj.reshape(-1), img, K)
    with pytest.raises(DataError, match="as many"):
        arkit_tool.solve_pnp_ransac(obj[:-1], img, K)
    with pytest.raises(DataError, match="camera_matrix"):
        arkit_tool.solve_pnp_ransac(obj, img, K.reshape(-1))


def test_project_refuses_transposed_points_and_reads_a_flat_pose(dataset):
    row = arkit_tool.open_dataset(dataset).sample(0)
    verts, R_t = row["verts"].astype(np.float64), row["R_t"]
    w, h = row["image_width"], row["image_height"]
    uv = arkit_tool.project(verts, R_t, w, h)
    assert uv.shape == (len(verts), 2)
    # The 16 values row by row are the same pose.
    np.testing.assert_array_equal(arkit_tool.project(verts, R_t.reshape(-1), w, h), uv)
    np.testing.assert_array_equal(arkit_tool.project(verts, list(R_t.reshape(-1)), w, h), uv)
    with pytest.raises(DataError, match=r"^verts: shape \(3, 1220\); expected \(N, 3\) \(transposed"):
        arkit_tool.project(verts.T, R_t, w, h)
    for bad in (R_t.reshape(2, 8), R_t[:3], R_t.reshape(-1)[:12]):
        with pytest.raises(DataError, match=r"^R_t: shape .*expected \(4, 4\) or 16 values"):
            arkit_tool.project(verts, bad, w, h)


def test_evaluate_reads_flat_poses_and_names_a_bad_one(dataset):
    data = arkit_tool.open_dataset(dataset)
    truth = {k: data.sample(i)["R_t"] for i, k in enumerate(data.keys)}
    flat = {k: v.reshape(-1) for k, v in truth.items()}
    assert arkit_tool.evaluate(dataset, flat)["summary"] == arkit_tool.evaluate(dataset, truth)["summary"]
    key = data.keys[0]
    flat[key] = truth[key][:3]
    with pytest.raises(DataError, match=r"R_t of .*%s.*shape \(3, 4\)" % key[2]):
        arkit_tool.evaluate(dataset, flat)

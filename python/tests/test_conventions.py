"""`arkit_tool.conventions` against OpenCV's `cv2.Rodrigues` and each peer's published
formula, written out again here in numpy (see docs/conventions.md), and round trips on
random poses. The OpenCV checks say SKIPPED without cv2."""

import numpy as np
import pytest

from arkit_tool import DataError, conventions as cv

F = np.diag([1.0, -1.0, -1.0])


def rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rodrigues(v):
    """Rodrigues' formula (SciPy's from_rotvec, cv2.Rodrigues)."""
    a = np.linalg.norm(v)
    if a == 0:
        return np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / a
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def release_rt(r, t):
    """The release's row-vector R_t of the column-form rotation r and translation t."""
    m = np.eye(4)
    m[:3, :3] = r.T
    m[3, :3] = t
    return m


def random_poses(n, seed):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    r = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    t = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-1.0, -0.2, n)], 1)
    return np.stack([release_rt(r[i], t[i]) for i in range(n)])


def wrap(d, turn=360.0):
    return (np.asarray(d) + turn / 2) % turn - turn / 2


def yxz(m):
    """SciPy's as_euler('yxz') of m = Rz(c) Rx(b) Ry(a), closed form: (a, b, c)."""
    return np.array([np.arctan2(-m[2, 0], m[2, 2]), np.arctan2(m[2, 1], np.hypot(m[2, 0], m[2, 2])),
                     np.arctan2(-m[0, 1], m[1, 1])])


def xyz(m):
    """SciPy's as_euler('xyz') of m = Rz(c) Ry(b) Rx(a), closed form: (a, b, c)."""
    return np.array([np.arctan2(m[2, 1], m[2, 2]), np.arctan2(-m[2, 0], np.hypot(m[2, 1], m[2, 2])),
                     np.arctan2(m[1, 0], m[0, 0])])


POSES = random_poses(1000, 51)


def test_every_conversion_round_trips_on_a_batch():
    rvec, tvec = cv.to_opencv(POSES)
    assert rvec.shape == tvec.shape == (1000, 3)
    np.testing.assert_allclose(cv.from_opencv(rvec, tvec), POSES, rtol=0, atol=1e-9)
    cameras = random_poses(1000, 7).transpose(0, 2, 1)  # rigid, column form
    anchors = cv.to_arkit(POSES, cameras)
    np.testing.assert_allclose(cv.from_arkit(anchors, cameras), POSES, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cv.from_trg(cv.to_trg(POSES)), POSES, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cv.from_img2pose(cv.to_img2pose(POSES)), POSES, rtol=0, atol=1e-9)
    for name in cv.CONVENTIONS:
        a = cv.angles(POSES, name)
        assert a.shape == (1000, 3)
        np.testing.assert_allclose(cv.from_angles(a, POSES[:, 3, :3], name), POSES, rtol=0, atol=1e-9)


def test_one_pose_in_one_pose_out():
    pose = POSES[0]
    rvec, tvec = cv.to_opencv(pose)
    assert rvec.shape == tvec.shape == (3,)
    assert cv.from_opencv(rvec.reshape(3, 1), tvec.reshape(3, 1)).shape == (4, 4)
    assert cv.angles(pose).shape == (3,)
    assert cv.to_img2pose(pose).shape == (6,)
    assert cv.to_trg(pose).shape == (4, 4)
    assert cv.from_arkit(np.eye(4), np.eye(4)).shape == (4, 4)
    # A single camera goes with a batch of anchors; a batch of one stays a batch.
    assert cv.to_arkit(POSES[:5], np.eye(4)).shape == (5, 4, 4)
    assert cv.angles(POSES[:1]).shape == (1, 3)
    assert cv.from_angles([[0, 0, 0], [10, 0, 0]], [0, 0, -0.5]).shape == (2, 4, 4)


def test_official_and_wcpa_angles_are_yxz_of_the_transposed_block():
    o = cv.angles(POSES, "official")
    w = cv.angles(POSES, "wcpa")
    for i, m in enumerate(POSES):
        yaw, pitch, roll = yxz(m[:3, :3].T)
        np.testing.assert_allclose(wrap(o[i] - np.degrees([yaw, pitch, roll])), 0, atol=1e-9)
        np.testing.assert_allclose(wrap(w[i] - [pitch, yaw, roll], 2 * np.pi), 0, atol=1e-11)


def test_trg_matches_its_loader_and_evaluation():
    trg = cv.to_trg(POSES)
    t_angles = cv.angles(POSES, "trg")
    for i, rt in enumerate(POSES):
        # data/arkit_dataset.py: ZYX angles of R_t[:3,:3].T, then
        # euler_to_rotation_matrix(roll, -pitch, -yaw) = Rz(-yaw) Ry(-pitch) Rx(roll),
        # stored transposed; ty and tz negated.
        r = rt[:3, :3].T
        yaw, pitch, roll = np.arctan2(r[1, 0], r[0, 0]), np.arctan2(-r[2, 0], np.hypot(r[2, 1], r[2, 2])), \
            np.arctan2(r[2, 1], r[2, 2])
        expect = rt.copy()
        expect[:3, :3] = (rz(-yaw) @ ry(-pitch) @ rx(roll)).T
        expect[3, 1] *= -1
        expect[3, 2] *= -1
        np.testing.assert_allclose(trg[i], expect, rtol=0, atol=1e-12)
        # test.py: as_euler('yxz') of gt_extrinsic.transpose()[:3, :3], [yaw, pitch, roll].
        np.testing.assert_allclose(wrap(t_angles[i] - np.degrees(yxz(expect[:3, :3].T))), 0, atol=1e-9)


def test_6drepnet_matches_its_formula_and_hand_values():
    a = cv.angles(POSES, "6drepnet")
    for i, rt in enumerate(POSES):
        r = rt[:3, :3]
        sy = np.sqrt(r[0, 0] ** 2 + r[1, 0] ** 2)
        x, y, z = np.arctan2(r[2, 1], r[2, 2]), np.arctan2(-r[2, 0], sy), np.arctan2(r[1, 0], r[0, 0])
        np.testing.assert_allclose(wrap(a[i] - np.array([x, y, z]) * 180 / np.pi), 0, atol=1e-9)
    # yaw 20, pitch 10, roll 5 (official) gives about (-8.16, -20.79, -5.27).
    pose = cv.from_angles([20, 10, 5], [0, 0, -0.5], "official")
    np.testing.assert_allclose(cv.angles(pose, "6drepnet"), [-8.16, -20.79, -5.27], atol=0.005)
    np.testing.assert_allclose(cv.angles(pose, "img2pose"), [-8.16, -20.79, -5.27], atol=0.005)
    np.testing.assert_allclose(cv.angles(pose, "trg"), [-20, 10, -5], atol=1e-12)
    np.testing.assert_allclose(cv.angles(pose, "wcpa"), np.radians([10, 20, 5]), atol=1e-14)
    # Its singular branch (sqrt(R00^2 + R10^2) < 1e-6): roll 0.
    block = rz(np.radians(25)) @ ry(np.pi / 2) @ rx(np.radians(-40))
    singular = release_rt(block.T, [0, 0, -0.5])
    np.testing.assert_allclose(cv.angles(singular, "6drepnet"), [-65, 90, 0], atol=1e-6)


def test_img2pose_matches_its_frame_and_aflw_conversion():
    dof = cv.to_img2pose(POSES)
    a = cv.angles(POSES, "img2pose")
    v = np.array([0.03, -0.02, 0.05])
    for i, rt in enumerate(POSES):
        rot, t = rodrigues(dof[i, :3]), dof[i, 3:]
        # Its frame: OpenCV's camera, model points F v; the release's point is v @ R_t.
        np.testing.assert_allclose(rot @ (F @ v) + t, F @ (np.append(v, 1) @ rt)[:3], atol=1e-12)
        # convert_to_aflw: from_rotvec, transpose, as_euler('xyz'), yaw and roll negated.
        p, y, r = np.degrees(xyz(rot.T))
        np.testing.assert_allclose(wrap(a[i] - [p, -y, -r]), 0, atol=1e-9)


def test_arkit_is_the_inverse_camera_times_the_anchor():
    cameras = random_poses(100, 8).transpose(0, 2, 1)
    anchors = random_poses(100, 9).transpose(0, 2, 1)
    got = cv.from_arkit(anchors, cameras)
    for i in range(100):
        np.testing.assert_allclose(got[i], (np.linalg.inv(cameras[i]) @ anchors[i]).T, atol=1e-12)


def test_bad_inputs_are_refused():
    with pytest.raises(DataError, match="orthonormal"):
        cv.from_arkit(np.diag([1.1, 1.1, 1.1, 1.0]), np.eye(4))
    anchor = np.eye(4)
    anchor[:3, 3] = [0, 0, -0.4]
    with pytest.raises(DataError, match="transposed"):
        cv.from_arkit(anchor.T, np.eye(4))
    with pytest.raises(DataError, match="reflection"):
        cv.to_arkit(POSES[0], np.diag([-1.0, 1, 1, 1]))
    bad = POSES[:3].copy()
    bad[2, 0, 0] = np.nan
    with pytest.raises(DataError, match="pose 2"):
        cv.angles(bad)
    with pytest.raises(DataError, match="expected one of official, wcpa, trg, 6drepnet, img2pose"):
        cv.angles(POSES[0], "opencv")  # type: ignore[arg-type]
    with pytest.raises(DataError, match="shape"):
        cv.to_opencv(np.eye(3))
    with pytest.raises(DataError, match="rvec and tvec"):
        cv.from_opencv(np.zeros((2, 3)), np.zeros((3, 3)))


def test_against_opencv_rodrigues():
    cv2 = pytest.importorskip("cv2", reason="SKIPPED: OpenCV (cv2) is not installed")
    rvec, tvec = cv.to_opencv(POSES)
    for i, rt in enumerate(POSES):
        r, _ = cv2.Rodrigues(rvec[i])
        # R_t = [[R^T, 0], [t^T, 1]] @ diag(1, -1, -1, 1).
        np.testing.assert_allclose(release_rt(r, tvec[i]) @ np.diag([1, -1, -1, 1.0]), rt, atol=1e-9)
        back, _ = cv2.Rodrigues(r)
        np.testing.assert_allclose(back.ravel(), rvec[i], atol=1e-9)
    # Near 0 and near pi: the same rotation as OpenCV's.
    axis = np.array([0.48, -0.6, 0.64])
    for angle in [0.0, 1e-12, 1e-6, np.pi - 1e-6, np.pi - 1e-9, np.pi]:
        r = rodrigues(axis * angle)
        rt = release_rt(F @ r, [0, 0, -0.5])
        ours, _ = cv.to_opencv(rt)
        np.testing.assert_allclose(np.linalg.norm(ours), angle, atol=1e-12)
        np.testing.assert_allclose(cv2.Rodrigues(ours)[0], r, atol=1e-12)
        # OpenCV's own matrix-to-vector branch for angles within about 1e-5 of 0 or pi
        # is approximate (a rotation of 1e-6 rad comes back as zero): ours is not.
        np.testing.assert_allclose(cv.from_opencv(cv2.Rodrigues(r)[0], [0, 0, 0.5]), rt, atol=2e-5)
    # solvePnP's (3, 1) vectors, as they come.
    ok, rv, tv = cv2.solvePnP(np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1], [0.1, 0.1, 0], [0.05, 0, 0.1]]),
                              np.array([[400, 400], [460, 402], [398, 340], [405, 398], [462, 341], [433, 400.0]]),
                              np.array([[600.0, 0, 400], [0, 600, 400], [0, 0, 1]]), None)
    assert ok
    rt = cv.from_opencv(rv, tv)
    back_r, back_t = cv.to_opencv(rt)
    np.testing.assert_allclose(cv2.Rodrigues(back_r)[0], cv2.Rodrigues(rv)[0], atol=1e-12)
    np.testing.assert_allclose(back_t, tv.ravel(), atol=1e-12)

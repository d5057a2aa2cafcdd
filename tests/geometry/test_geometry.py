import numpy as np
import pytest

from surfelslam.geometry import se3
from surfelslam.geometry.camera import backproject, project
from surfelslam.io.trajectory import read_tum, write_tum
from surfelslam.types import Intrinsics, Trajectory


def random_pose(rng, angle=0.5, trans=1.0):
    return se3.exp(np.concatenate([rng.normal(size=3) * angle, rng.normal(size=3) * trans]))


def test_exp_log_roundtrip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        xi = np.concatenate([rng.normal(size=3) * 0.8, rng.normal(size=3)])
        T = se3.exp(xi)
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.allclose(se3.log(T), xi, atol=1e-9)


def test_so3_log_of_a_batch_equals_one_at_a_time():
    """A ``(K, 3, 3)`` stack gives ``(K, 3)``, each row the single matrix's log (the pose graph's residual check
    takes hundreds at once): scipy for stacks, scalar code for one matrix, bit for bit the same; angles near 0,
    at the series' bound and near pi included."""
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(200, 3))
    omegas = list(axes / np.linalg.norm(axes, axis=1, keepdims=True) * rng.uniform(0.0, 3.1, (200, 1)))
    omegas += [np.array([1e-9, 0.0, 0.0]), np.array([0.0, 1e-3, 0.0]), np.array([0.0, np.pi - 1e-6, 0.0]),
               np.array([0.3, -2.0, 2.2]) * (np.pi - 1e-7) / np.linalg.norm([0.3, -2.0, 2.2])]
    R = np.stack([se3.so3_exp(w) for w in omegas])
    batch = se3.so3_log(R)
    assert batch.shape == (len(omegas), 3)
    assert np.array_equal(batch, np.stack([se3.so3_log(r) for r in R]))
    assert np.allclose(batch, np.stack(omegas), atol=1e-8)


def test_exp_small_angle_matches_first_order():
    xi = np.array([1e-10, -2e-10, 3e-10, 0.1, 0.2, 0.3])
    assert np.allclose(se3.exp(xi), se3.small_angle_update(xi), atol=1e-12)


def test_invert_and_compose():
    rng = np.random.default_rng(1)
    A, B = random_pose(rng), random_pose(rng)
    assert np.allclose(se3.compose(A, se3.invert(A)), np.eye(4), atol=1e-12)
    assert np.allclose(se3.invert(se3.compose(A, B)), se3.invert(B) @ se3.invert(A), atol=1e-12)
    batch = np.stack([A, B])
    assert np.allclose(se3.invert(batch)[1], se3.invert(B))


def test_quaternion_roundtrip_and_sign():
    rng = np.random.default_rng(2)
    R = np.stack([random_pose(rng)[:3, :3] for _ in range(20)])
    q = se3.rotation_to_quat_xyzw(R)
    assert np.all(q[:, 3] >= 0)
    assert np.allclose(np.linalg.norm(q, axis=1), 1)
    assert np.allclose(se3.quat_xyzw_to_rotation(q), R, atol=1e-12)
    # identity is (0, 0, 0, 1) in xyzw order
    assert np.allclose(se3.rotation_to_quat_xyzw(np.eye(3)), [0, 0, 0, 1])


def test_motion_norm_uses_short_angle():
    T = se3.exp(np.array([0, 0, 2 * np.pi - 0.1, 0.3, 0, 0]))
    assert se3.motion_norm(T) == pytest.approx(0.1 + np.linalg.norm(T[:3, 3]), abs=1e-9)


def test_backproject_project_roundtrip():
    intr = Intrinsics(500.0, -480.0, 319.5, 239.5, 640, 480)
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.5, 4.0, size=(480, 640)).astype(np.float32)
    V = backproject(depth, intr)
    u, v, z = project(V.reshape(-1, 3).astype(np.float64), intr)
    vv, uu = np.mgrid[0:480, 0:640]
    assert np.allclose(u, uu.ravel(), atol=1e-3)
    assert np.allclose(v, vv.ravel(), atol=1e-3)
    assert np.allclose(z, depth.ravel())


def test_intrinsics_scaled_matches_slicing():
    intr = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    s = intr.scaled(2)
    assert (s.width, s.height) == np.zeros((480, 640))[::2, ::2].shape[::-1]
    assert s.fx == 262.5 and s.cx == 159.75
    # a point projecting to old pixel (2u', 2v') projects to new pixel (u', v')
    X = np.array([0.3, -0.2, 2.0])
    u, v, _ = project(X, intr)
    u2, v2, _ = project(X, s)
    assert u2 == pytest.approx(u / 2) and v2 == pytest.approx(v / 2)
    with pytest.raises(Exception, match="downsample"):
        intr.scaled(0)


def test_trajectory_tum_roundtrip(tmp_path):
    rng = np.random.default_rng(4)
    T = np.stack([random_pose(rng) for _ in range(10)])
    traj = Trajectory(np.arange(10) * 0.033, T)
    path = tmp_path / "traj.txt"
    write_tum(traj, path)
    back = read_tum(path)
    assert np.allclose(back.timestamps, traj.timestamps, atol=1e-6)
    assert np.allclose(back.T_world_cam, T, atol=1e-8)
    assert not list(tmp_path.glob(".*tmp"))


def test_trajectory_bad_file(tmp_path):
    from surfelslam.errors import InputError

    p = tmp_path / "bad.txt"
    p.write_text("0 1 2 3\n")
    with pytest.raises(InputError, match="bad.txt.*line 1"):
        read_tum(p)
    with pytest.raises(InputError, match="not found"):
        read_tum(tmp_path / "none.txt")


def test_appender_refuses_a_non_rigid_pose_and_keeps_earlier_lines(tmp_path):
    """A tracker fault (non-finite or non-orthonormal pose) is a one-line TrackingError naming the frame's time, not
    a traceback from the quaternion conversion; the lines written before it stay in the file."""
    from surfelslam.errors import TrackingError
    from surfelslam.io.trajectory import TumAppender

    path = tmp_path / "trajectory.txt"
    good = se3.exp(np.array([0.1, -0.2, 0.05, 0.3, 0.1, -0.2]))
    bad_scale = good.copy()
    bad_scale[:3, :3] *= 1.01
    overflow = np.full((4, 4), 1e42)
    with TumAppender(path) as out:
        out.append(0.0, good)
        for t, T in ((0.033333, bad_scale), (0.066667, overflow), (0.1, np.full((4, 4), np.nan))):
            with pytest.raises(TrackingError, match=f"t = {t:.6f} s"):
                out.append(t, T)
    back = read_tum(path)
    assert len(back) == 1 and np.allclose(back.T_world_cam[0], good, atol=1e-8)


def test_growing_rows_keep_their_rows_dtype_and_fill():
    from surfelslam.types import GrowingRows

    rows = GrowingRows((2,), np.int64, fill=-1, capacity=2)
    assert rows.rows.shape == (0, 2) and rows.rows.dtype == np.int64
    for k in range(5):
        assert rows.append((k, 10 * k)) == k
    np.testing.assert_array_equal(rows.rows, [[k, 10 * k] for k in range(5)])
    assert rows.capacity == 8 and len(rows) == 5  # 2 -> 4 -> 8
    np.testing.assert_array_equal(rows.buffer[5:], -1)  # rows not appended yet read as the fill, after growing too
    rows.rows[1, 0] = 7  # a view
    assert rows.rows[1, 0] == 7
    scalars = GrowingRows((), np.float64, np.inf, capacity=1)
    scalars.append(2.5)
    scalars.append(3.5)
    assert scalars.rows.tolist() == [2.5, 3.5] and scalars.capacity == 2


def test_pose_array_grows_by_doubling_and_keeps_its_poses():
    from surfelslam.types import PoseArray

    rng = np.random.default_rng(0)
    poses = [se3.exp(rng.normal(size=6)) for _ in range(37)]
    arr = PoseArray(capacity=4)
    assert len(arr) == 0 and arr.poses.shape == (0, 4, 4)
    for i, T in enumerate(poses):
        arr.append(T)
        assert len(arr) == i + 1
    np.testing.assert_array_equal(arr.poses, np.stack(poses))
    assert arr.capacity == 64  # 4 -> 8 -> 16 -> 32 -> 64: doubled, never grown per append
    arr.poses[3] = np.eye(4)  # a view: writes land in the stack
    np.testing.assert_array_equal(arr.poses[3], np.eye(4))

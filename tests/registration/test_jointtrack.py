"""JointTrack's calibration and pose files, read and written in its own camera frame."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from registration.jointtrack import (
    ROTATION_TOLERANCE,
    camera_view,
    read_calibration,
    read_camera_pose,
    read_poses,
    write_calibration,
    write_poses,
)


def test_a_point_projects_where_jointtracks_formula_puts_it(tmp_path):
    path = tmp_path / "calibration.txt"
    path.write_text("JT_INTCALIB\n1198\n2.5\n-1.5\n0.373\n", encoding="utf-8")
    view = read_calibration(path, rows=1000, cols=1024)
    rng = np.random.default_rng(0)
    points = rng.uniform([-80, -80, -1150], [80, 80, -1000], size=(50, 3))
    d, x_off, y_off, p = 1198.0, 2.5, -1.5, 0.373
    col = (1024 - 1) / 2 + x_off / p + (d / p) * points[:, 0] / -points[:, 2]
    row = (1000 - 1) / 2 - y_off / p - (d / p) * points[:, 1] / -points[:, 2]
    np.testing.assert_allclose(view.project(points), np.column_stack((col, row)), atol=1e-9)
    again = read_calibration(write_calibration(tmp_path / "again.txt", view), 1000, 1024)
    np.testing.assert_allclose(again.matrix, view.matrix, rtol=1e-9)


def test_poses_round_trip_with_rotations_about_z_then_x_then_y(tmp_path):
    rng = np.random.default_rng(1)
    poses = []
    for _ in range(5):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.uniform(-50, 50, 3) + np.array([0.0, 0.0, -1080.0])
        poses.append(T)
    back = read_poses(write_poses(tmp_path / "body.jts", poses))
    np.testing.assert_allclose(back, np.stack(poses), atol=1e-6)
    one = tmp_path / "one.jts"
    header = "JT_EULER_312\nx_tran,y_tran,z_tran,z_rot,x_rot,y_rot\n"
    one.write_text(header + "1,2,-1000,90,0,0\n", encoding="utf-8")
    T = read_poses(one)[0]
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # 90 deg about z


def test_bad_files_are_refused_with_the_line_named(tmp_path):
    bad = tmp_path / "bad.jts"
    bad.write_text("JT_EULER_312\nx_tran,y_tran,z_tran,z_rot,x_rot,y_rot\n1,2,3,4,5\n")
    with pytest.raises(ValueError, match="line 3 is not six finite numbers"):
        read_poses(bad)
    calibration = tmp_path / "calibration.txt"
    calibration.write_text("JT_INTCALIB\n1198\n0\n0\n-0.373\n")
    with pytest.raises(ValueError, match=r"pixel size -0\.373 must be > 0 mm"):
        read_calibration(calibration, 1024, 1024)
    with pytest.raises(ValueError, match="only a view in JointTrack's camera frame"):
        write_calibration(
            tmp_path / "x.txt",
            camera_view(1198, 0, 0, 0.373, 8, 8)
            .binned(2)
            .transformed(np.diag([1.0, -1.0, -1.0, 1.0])),
        )


def test_a_camera_pose_reads_as_a_rigid_transform_in_either_form(tmp_path):
    """Four rows or three, spaces or commas, comments; a rotation written to six decimals is
    made the nearest rotation; a matrix further from one than the tolerance is refused."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [90, 10, -5], degrees=True).as_matrix()
    T[:3, 3] = (-850.0, 12.5, 40.0)
    rows = [", ".join(f"{v:.6f}" for v in row) for row in T[:3]]
    three = tmp_path / "three.txt"
    three.write_text("# camera 2 in camera 1's frame\n" + "\n".join(rows) + "\n")
    read = read_camera_pose(three)
    np.testing.assert_allclose(read, T, atol=1e-6)
    np.testing.assert_allclose(read[:3, :3].T @ read[:3, :3], np.eye(3), atol=1e-14)
    four = tmp_path / "four.txt"
    np.savetxt(four, T)
    np.testing.assert_allclose(read_camera_pose(four), T, atol=1e-12)
    off = T.copy()
    off[0, 0] += 10 * ROTATION_TOLERANCE
    for matrix, said in (
        (off, "rotation is not one"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "determinant -1"),
        (np.vstack([T[:3], [0, 0, 1, 1]]), "last row"),
    ):
        np.savetxt(four, matrix)
        with pytest.raises(ValueError, match=said):
            read_camera_pose(four)
    four.write_text("1 0 0\n0 1 0\n0 0 1\n")
    with pytest.raises(ValueError, match="got 3 x 3 numbers"):
        read_camera_pose(four)


def test_a_mayacam_projects_as_opencvs_k_r_t(tmp_path):
    """XMALab's MayaCam 2.0: x_cam = R X + t, (u, v) = (fx x / z + cx, fy y / z + cy)."""
    from registration.mayacam import read_mayacam

    rng = np.random.default_rng(3)
    R = Rotation.random(random_state=rng).as_matrix()
    t = np.array([12.0, -30.0, 900.0])
    K = np.array([[2900.0, 0.0, 500.0], [0.0, 2900.0, 530.0], [0.0, 0.0, 1.0]])
    text = "image size\n1000,1024\n\ncamera matrix\n"
    text += "\n".join(",".join(repr(float(v)) for v in row) for row in K)
    text += "\n\nrotation\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in R)
    text += "\n\ntranslation\n" + "\n".join(repr(float(v)) for v in t) + "\n"
    path = tmp_path / "cam.txt"
    path.write_text(text)
    view = read_mayacam(path, pixel_pitch_mm=0.3)
    assert (view.rows, view.cols) == (1000, 1024)
    points = rng.uniform(-60, 60, size=(20, 3))
    cam = points @ R.T + t
    expected = np.column_stack(
        (K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2])
    )
    np.testing.assert_allclose(view.project(points), expected, atol=1e-7)
    nominal = read_mayacam(path)  # no pitch: the same pixels, the panel 1000 mm away
    np.testing.assert_allclose(nominal.project(points), expected, atol=1e-7)
    assert nominal.sdd_mm == pytest.approx(1000.0) and view.sdd_mm == pytest.approx(2900 * 0.3)
    path.write_text(text.replace("rotation", "turn"))
    with pytest.raises(ValueError, match=r"line 9 of 'camera matrix' is not numbers: 'turn'"):
        read_mayacam(path, 0.3)

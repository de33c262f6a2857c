"""JointTrack's files: its calibration (``JT_INTCALIB``) as the fluoroscopy view, and its poses
(``.jts``, ``JT_EULER_312``), read and written in its own camera frame, so that JointTrack and
JTML read our results and we read theirs.

JointTrack's camera frame (the world frame of a registration whose view comes from its
calibration): origin at the X-ray focal spot, looking down -z, +x to the right of the image
and +y to its top as the image is displayed (row 0 at the top). With principal distance ``d``,
principal point offset ``(x_off, y_off)`` and pixel size ``p`` (mm), a point projects to
``col = (W - 1) / 2 + x_off / p + (d / p) X / (-Z)`` and
``row = (H - 1) / 2 - y_off / p - (d / p) Y / (-Z)``.

A ``.jts`` row maps the body's mesh (mm) into the camera frame, ``p_cam = R p_mesh + t``, with
``R = Rz(z_rot) Rx(x_rot) Ry(y_rot)`` (degrees): the translation columns first, then the
rotations about z, x and y, one row per frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from recon.geometry import View

CALIBRATION_TAG = "JT_INTCALIB"
POSES_TAG = "JT_EULER_312"
POSE_COLUMNS = ("x_tran", "y_tran", "z_tran", "z_rot", "x_rot", "y_rot")


def read_calibration(path: str | Path, rows: int, cols: int) -> View:
    """The view of a ``JT_INTCALIB`` file for frames of ``rows`` x ``cols`` pixels (the file
    gives the principal distance, the principal point's offset and the pixel size, mm)."""
    path = Path(path)
    words = path.read_text(encoding="utf-8").split()
    if not words or words[0] != CALIBRATION_TAG:
        raise ValueError(f"{path}: not a JointTrack calibration (first line {CALIBRATION_TAG})")
    try:
        distance, x_off, y_off, pixel = (float(w) for w in words[1:5])
    except ValueError:
        raise ValueError(
            f"{path}: {CALIBRATION_TAG} needs four numbers (principal distance, principal point "
            f"x and y offsets, pixel size; mm), got {words[1:5]}"
        ) from None
    if len(words) != 5:
        raise ValueError(f"{path}: {CALIBRATION_TAG} holds four numbers, got {len(words) - 1}")
    if not (distance > 0 and pixel > 0 and np.isfinite([x_off, y_off]).all()):
        raise ValueError(
            f"{path}: principal distance {distance} and pixel size {pixel} must be > 0 mm, "
            f"offsets {x_off}, {y_off} finite"
        )
    return camera_view(distance, x_off, y_off, pixel, rows, cols)


def camera_view(
    distance_mm: float, x_off_mm: float, y_off_mm: float, pixel_mm: float, rows: int, cols: int
) -> View:
    """JointTrack's camera as a view in its own frame (see the module docstring).

    Args:
        distance_mm: principal distance, source to image plane, mm.
        x_off_mm: principal point's offset from the image centre to the right, mm.
        y_off_mm: principal point's offset from the image centre upward, mm.
        pixel_mm: square pixel size, mm.
        rows: image rows, pixels.
        cols: image columns, pixels.
    """
    cu = 0.5 * (cols - 1) + x_off_mm / pixel_mm
    cv = 0.5 * (rows - 1) - y_off_mm / pixel_mm
    return View(
        source_mm=np.zeros(3),
        detector_origin_mm=np.array([-cu * pixel_mm, cv * pixel_mm, -distance_mm]),
        e_u=np.array([1.0, 0.0, 0.0]),
        e_v=np.array([0.0, -1.0, 0.0]),
        pitch_u_mm=pixel_mm,
        pitch_v_mm=pixel_mm,
        rows=rows,
        cols=cols,
    )


def write_calibration(path: str | Path, view: View) -> Path:
    """A view in JointTrack's camera frame (source at the origin, panel facing +z, rows along
    -y) as a ``JT_INTCALIB`` file; raises ValueError for any other view."""
    path = Path(path)
    if not (
        np.allclose(view.source_mm, 0.0, atol=1e-9)
        and np.allclose(view.e_u, (1, 0, 0), atol=1e-9)
        and np.allclose(view.e_v, (0, -1, 0), atol=1e-9)
        and np.isclose(view.pitch_u_mm, view.pitch_v_mm)
    ):
        raise ValueError("only a view in JointTrack's camera frame has a JT_INTCALIB form")
    p = view.pitch_u_mm
    distance = -float(view.detector_origin_mm[2])
    x_off = (-view.detector_origin_mm[0] / p - 0.5 * (view.cols - 1)) * p
    y_off = (0.5 * (view.rows - 1) - view.detector_origin_mm[1] / p) * p
    text = "\n".join([CALIBRATION_TAG, *(f"{v:.10g}" for v in (distance, x_off, y_off, p))])
    path.write_text(text + "\n", encoding="utf-8")
    return path


def read_poses(path: str | Path) -> np.ndarray:
    """The poses of a ``.jts`` file, ``T_camera_mesh`` per row (F, 4, 4), mm."""
    path = Path(path)
    lines = [line.strip() for line in path.read_text(encoding="utf-8").splitlines()]
    lines = [line for line in lines if line]
    if not lines or lines[0] != POSES_TAG:
        raise ValueError(f"{path}: not JointTrack poses (first line {POSES_TAG})")
    header = [w.strip() for w in lines[1].split(",")] if len(lines) > 1 else []
    if header != list(POSE_COLUMNS):
        raise ValueError(f"{path}: the columns must be {', '.join(POSE_COLUMNS)}, got {header}")
    poses = []
    for number, line in enumerate(lines[2:], start=3):
        try:
            values = [float(w) for w in line.split(",")]
        except ValueError:
            raise ValueError(f"{path}: line {number} is not six numbers: {line!r}") from None
        if len(values) != 6 or not np.all(np.isfinite(values)):
            raise ValueError(f"{path}: line {number} is not six finite numbers: {line!r}")
        poses.append(pose_of_row(values))
    if not poses:
        raise ValueError(f"{path}: no pose rows")
    return np.stack(poses)


def pose_of_row(values: Sequence[float]) -> np.ndarray:
    """``T_camera_mesh`` (4, 4) of one ``.jts`` row (x, y, z mm; z, x, y rotations deg)."""
    x, y, z, rz, rx, ry = values
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZXY", [rz, rx, ry], degrees=True).as_matrix()
    T[:3, 3] = (x, y, z)
    return T


def row_of_pose(T: np.ndarray) -> list[float]:
    """The ``.jts`` row of ``T_camera_mesh``: x, y, z (mm), then z, x, y rotations (deg)."""
    rz, rx, ry = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_euler("ZXY", degrees=True)
    return [*(float(v) for v in np.asarray(T)[:3, 3]), float(rz), float(rx), float(ry)]


def write_poses(path: str | Path, poses: Sequence[np.ndarray]) -> Path:
    """``T_camera_mesh`` per frame as a ``.jts`` file."""
    path = Path(path)
    width = 16
    lines = [POSES_TAG, ",".join(f"{name:>{width}}" for name in POSE_COLUMNS)]
    for T in poses:
        lines.append(",".join(f"{v:>{width}.9g}" for v in row_of_pose(T)))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def camera_frame(view: View) -> np.ndarray:
    """``T_world_camera`` of JointTrack's camera frame of a view: origin at the focal spot,
    +x along the panel's columns, +y against its rows (up, as the image shows), looking down
    -z (registration.jointtrack)."""
    x, y = view.e_u, -view.e_v
    z = np.cross(x, y)
    T = np.eye(4)
    T[:3, :3] = np.column_stack((x, y, z))
    T[:3, 3] = view.source_mm
    return T


ROTATION_TOLERANCE = 1e-4
"""Largest deviation of a camera pose's rotation from orthonormal (``|R^T R - I|``, any
entry) read as a rotation written to a few decimals."""


def read_camera_pose(path: str | Path) -> np.ndarray:
    """``T_world_camera`` (4, 4; mm) of a JointTrack camera frame in a world shared with other
    cameras, from a text file of the matrix: its four rows of four numbers (or the first three
    rows), separated by spaces or commas, ``#`` starting a comment. The rotation is made exactly
    orthonormal (the nearest rotation); ValueError for one further off than
    :data:`ROTATION_TOLERANCE`, a reflection or a last row other than 0 0 0 1."""
    path = Path(path)
    rows = []
    for line in path.read_text(encoding="utf-8").splitlines():
        words = line.split("#")[0].replace(",", " ").split()
        if words:
            try:
                rows.append([float(w) for w in words])
            except ValueError:
                raise ValueError(f"{path}: camera pose row {words} is not numbers") from None
    if len(rows) not in (3, 4) or any(len(r) != 4 for r in rows):
        shape = " x ".join(str(n) for n in (len(rows), *{len(r) for r in rows}))
        raise ValueError(
            f"{path}: a camera pose is the 4 x 4 matrix T_world_camera (or its first 3 rows), "
            f"got {shape} numbers"
        )
    T = np.eye(4)
    T[: len(rows)] = rows
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{path}: the camera pose holds a value that is not finite")
    if not np.allclose(T[3], (0, 0, 0, 1), rtol=0, atol=1e-9):
        raise ValueError(f"{path}: the camera pose's last row is {T[3].tolist()}, not 0 0 0 1")
    R = T[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if off > ROTATION_TOLERANCE or np.linalg.det(R) <= 0:
        raise ValueError(
            f"{path}: the camera pose's rotation is not one (|R^T R - I| up to {off:.2g}, limit "
            f"{ROTATION_TOLERANCE:g}; determinant {np.linalg.det(R):.4g}, must be +1)"
        )
    u, _, vt = np.linalg.svd(R)
    T[:3, :3] = u @ vt
    return T


def read_jointtrack_poses(path: str | Path, view: View) -> np.ndarray:
    """A JointTrack ``.jts`` file's poses in the world, ``T_world_body`` (F, 4, 4), mm.

    Args:
        path: The ``.jts`` file (:func:`read_poses`).
        view: The view whose camera frame (:func:`camera_frame`) the file's poses are in.
    """
    return camera_frame(view) @ read_poses(path)

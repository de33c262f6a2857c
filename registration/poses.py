"""Tracked bodies' poses per frame and their file, ``poses.csv`` (docs/conventions.md).

A body is a bone or an implant component. Its pose ``T_world_body`` (4x4) moves it from where
the static CBCT scan saw it (its reference frame: world coordinates at the time of the scan;
a component's mesh frame) to where it is in a frame. The 6-DoF row of the file repeats it as
docs/conventions.md parameterises poses: the world position of the body's centroid (tx, ty, tz) mm
and the rotation as extrinsic x-y-z angles (scipy "xyz") in degrees about that centroid. The
16 matrix entries are authoritative when reading. A file may leave out the similarity,
seconds, failed and reason columns (files written before them still read): similarity and
seconds are then unknown and no pose is marked failed. Files written before the ``body``
column name the body in a ``bone`` column, and still read.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

MATRIX_COLUMNS = tuple(f"t{r}{c}" for r in range(4) for c in range(4))
COLUMNS = (
    "frame",
    "body",
    *MATRIX_COLUMNS,
    "tx_mm",
    "ty_mm",
    "tz_mm",
    "rx_deg",
    "ry_deg",
    "rz_deg",
    "similarity",
    "seconds",
    "failed",
    "reason",
)
RIGID_TOLERANCE = 1e-5
"""Largest |R^T R - I| entry and |det R - 1| accepted as a rotation."""


@dataclass(frozen=True)
class BodyPose:
    """One tracked body in one frame.

    Attributes:
        frame: frame number.
        body: the body's name (a bone's: "femur", "tibia_fibula", "patella"; a component's:
            "femoral_component", "tibial_tray"; registration.roles).
        T_world_body: 4x4 rigid motion from the reference (CBCT) pose, mm.
        similarity: the registration's similarity at this pose (NaN when unknown).
        seconds: time the registration spent on it (NaN when unknown).
        failed: the registration marked this pose failed (the assessment measures nothing
            from it).
        reason: why it failed (empty when it did not), e.g. "NCC 0.308 below 0.5".
    """

    frame: int
    body: str
    T_world_body: np.ndarray
    similarity: float = math.nan
    seconds: float = math.nan
    failed: bool = False
    reason: str = ""

    def six_dof(self, centroid_mm: np.ndarray) -> np.ndarray:
        """(tx, ty, tz) mm of the moved centroid and (rx, ry, rz) deg, extrinsic xyz.

        Args:
            centroid_mm: The body's reference centroid in its own frame (mm), shape (3,).

        Returns:
            Six numbers: translation (mm) then rotation (degrees), shape (6,).

        Examples:
            A femur turned 90 degrees about z: its centroid (10, 0, 0) moves to (0, 10, 0).

            >>> T = np.eye(4)
            >>> T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
            >>> pose = BodyPose(frame=0, body="femur", T_world_body=T)
            >>> pose.six_dof(np.array([10.0, 0.0, 0.0])).round(6).tolist()
            [0.0, 10.0, 0.0, 0.0, 0.0, 90.0]
        """
        T = self.T_world_body
        moved = T[:3, :3] @ np.asarray(centroid_mm, dtype=np.float64) + T[:3, 3]
        angles = Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)
        return np.concatenate((moved, angles))


def check_rigid(T: np.ndarray, where: str) -> np.ndarray:
    """``T`` as a float 4x4 rigid transform, or ValueError naming ``where`` and the defect."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{where}: pose must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{where}: pose contains NaN or infinite values")
    R = T[:3, :3]
    orthogonality = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if orthogonality > RIGID_TOLERANCE or abs(det - 1.0) > RIGID_TOLERANCE:
        raise ValueError(
            f"{where}: pose is not rigid (|R^T R - I| = {orthogonality:.2e}, det R = {det:.6f}, "
            f"tolerance {RIGID_TOLERANCE:g})"
        )
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > RIGID_TOLERANCE:
        raise ValueError(f"{where}: last row of the pose is {T[3].tolist()}, not [0, 0, 0, 1]")
    return T


def write_poses(
    path: str | Path, poses: list[BodyPose], centroids_mm: dict[str, np.ndarray]
) -> Path:
    """Write ``poses.csv`` (never over an existing file; rigid poses only).

    Args:
        path: The CSV file written.
        poses: One pose per frame and body.
        centroids_mm: Each body's reference centroid (mm), for the six-number columns.

    Returns:
        ``path``.
    """
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists: poses are never written over")
    rows = []
    for pose in poses:
        where = f"frame {pose.frame}, body {pose.body}"
        T = check_rigid(pose.T_world_body, where)
        if pose.body not in centroids_mm:
            raise ValueError(f"{where}: no reference centroid for body {pose.body!r}")
        six = pose.six_dof(centroids_mm[pose.body])
        numbers = (*T.ravel(), *six, pose.similarity, pose.seconds)
        rows.append(
            [
                pose.frame,
                pose.body,
                *(repr(float(x)) for x in numbers),
                int(pose.failed),
                pose.reason,
            ]
        )
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(COLUMNS)
        writer.writerows(rows)
    tmp.rename(path)
    return path


def read_poses(path: str | Path) -> list[BodyPose]:
    """Read ``poses.csv``; every matrix is checked to be rigid.

    Raises ValueError naming the file (and the line, or the frame and body) for anything
    malformed.

    Args:
        path: A ``poses.csv`` written by :func:`write_poses` (or in its columns).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such poses file")
    try:
        return _read_poses(path)
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    except csv.Error as err:
        raise ValueError(f"{path}: not a CSV file ({err})") from None


def _read_poses(path: Path) -> list[BodyPose]:
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        columns = reader.fieldnames or []
        name = "bone" if "bone" in columns and "body" not in columns else "body"
        missing = [c for c in ("frame", name, *MATRIX_COLUMNS) if c not in columns]
        if missing:
            raise ValueError(f"{path}: missing columns {missing}")
        poses = []
        for line, row in enumerate(reader, start=2):
            try:
                frame = int(row["frame"])
                values = np.array([float(row[c]) for c in MATRIX_COLUMNS])
            except (TypeError, ValueError):
                raise ValueError(
                    f"{path}: line {line}: frame or matrix entry is not a number"
                ) from None
            body = row[name]
            if not body:
                raise ValueError(f"{path}: line {line}: no body named")
            T = check_rigid(values.reshape(4, 4), f"{path}: frame {frame}, body {body}")
            similarity, seconds = (
                _number(row.get(c), f"{path}: line {line}: {c}") for c in ("similarity", "seconds")
            )
            failed = _flag(row.get("failed"), f"{path}: line {line}: failed")
            reason = row.get("reason") or ""
            poses.append(BodyPose(frame, body, T, similarity, seconds, failed, reason))
    if not poses:
        raise ValueError(f"{path}: no poses")
    return poses


def _number(text: str | None, where: str) -> float:
    """An optional column's value: NaN (unknown) when empty or ``nan``; ValueError naming
    ``where`` for text that is not a number or is infinite."""
    if text in (None, ""):
        return math.nan
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{where}: {text!r} is not a number") from None
    if math.isinf(value):
        raise ValueError(f"{where}: {text!r} is infinite")
    return value


def _flag(text: str | None, where: str) -> bool:
    """The ``failed`` column's value: False when empty (or absent), else 0 or 1; ValueError
    naming ``where`` for anything else."""
    if text in (None, "", "0"):
        return False
    if text == "1":
        return True
    raise ValueError(f"{where}: {text!r} is not 0 or 1")


def poses_by_frame(
    poses: list[BodyPose], bodies: tuple[str, ...]
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Frames (sorted) and, per body, the (F, 4, 4) stack of poses; every frame must hold every
    body exactly once (ValueError naming the frame and body otherwise)."""
    frames = np.array(sorted({p.frame for p in poses}))
    stacks = {body: np.full((len(frames), 4, 4), np.nan) for body in bodies}
    index = {f: i for i, f in enumerate(frames)}
    for pose in poses:
        if pose.body not in stacks:
            continue
        slot = stacks[pose.body][index[pose.frame]]
        if np.isfinite(slot).all():
            raise ValueError(f"frame {pose.frame}, body {pose.body}: pose given twice")
        slot[:] = pose.T_world_body
    for body, stack in stacks.items():
        missing = frames[~np.isfinite(stack).all(axis=(1, 2))]
        if missing.size:
            raise ValueError(
                f"frame {int(missing[0])}, body {body}: no pose ({missing.size} "
                f"frame(s) miss this body)"
            )
    return frames, stacks

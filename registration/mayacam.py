"""XMALab's camera calibration (MayaCam 2.0, as Autoscoper reads it) as the fluoroscopy view.

A MayaCam 2.0 file holds the image size (height, width), the intrinsic matrix ``K`` (pixels),
and the rotation ``R`` and translation ``t`` of the calibration's world into the camera,
OpenCV's convention as XMALab computes them: ``x_cam = R X + t``, ``u = fx x/z + cx``,
``v = fy y/z + cy`` with ``(u, v)`` = (column, row) from the top-left pixel's centre. The
world is the calibration object's frame (mm): every camera calibrated on the same object shares
it. The file does not give the panel's pixel pitch, which the registration's settings (mm at the
panel) need, and the projection in pixels does not depend on it: the panel lies ``fx`` pitches
from the focal spot. Without a pitch, the panel is put :data:`NOMINAL_DISTANCE_MM` from the
focal spot (the pitch ``NOMINAL_DISTANCE_MM / fx``), a clinical fluoroscope's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.geometry import View

SECTIONS = ("image size", "camera matrix", "rotation", "translation")
NOMINAL_DISTANCE_MM = 1000.0
"""Focal spot to panel, mm, of a MayaCam view read without the panel's pixel pitch."""


def read_mayacam(path: str | Path, pixel_pitch_mm: float | None = None) -> View:
    """The view of a MayaCam 2.0 file for a panel of ``pixel_pitch_mm`` pixels (along the
    columns; None: :func:`nominal_pitch_mm`); ValueError naming the file and the section."""
    if pixel_pitch_mm is not None and not pixel_pitch_mm > 0:
        raise ValueError(
            f"{path}: a MayaCam view needs a pixel pitch above 0 mm, got {pixel_pitch_mm}"
        )
    blocks = _blocks(Path(path))
    size = np.array(blocks["image size"], dtype=float).ravel()
    K = np.array(blocks["camera matrix"], dtype=float)
    R = np.array(blocks["rotation"], dtype=float)
    t = np.array(blocks["translation"], dtype=float).ravel()
    if size.shape != (2,) or K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(
            f"{path}: image size (2), camera matrix (3 x 3), rotation (3 x 3) and translation "
            f"(3) expected, got {size.shape}, {K.shape}, {R.shape}, {t.shape}"
        )
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError(f"{path}: the rotation is not a rotation matrix")
    fx, fy, cx, cy = _intrinsics(path, K)
    rows, cols = int(size[0]), int(size[1])
    source = -R.T @ t
    pitch_u = NOMINAL_DISTANCE_MM / fx if pixel_pitch_mm is None else float(pixel_pitch_mm)
    distance = fx * pitch_u
    pitch_v = distance / fy
    origin_camera = np.array([-cx * pitch_u, -cy * pitch_v, distance])
    return View(
        source_mm=source,
        detector_origin_mm=source + R.T @ origin_camera,
        e_u=R.T @ np.array([1.0, 0.0, 0.0]),
        e_v=R.T @ np.array([0.0, 1.0, 0.0]),
        pitch_u_mm=pitch_u,
        pitch_v_mm=pitch_v,
        rows=rows,
        cols=cols,
    )


def nominal_pitch_mm(path: str | Path) -> float:
    """The pixel pitch (mm) that puts a MayaCam file's panel :data:`NOMINAL_DISTANCE_MM` from
    its focal spot: ``NOMINAL_DISTANCE_MM / fx``."""
    K = np.array(_blocks(Path(path))["camera matrix"], dtype=float)
    if K.shape != (3, 3):
        raise ValueError(f"{path}: camera matrix (3 x 3) expected, got {K.shape}")
    return NOMINAL_DISTANCE_MM / _intrinsics(path, K)[0]


def _intrinsics(path: str | Path, K: np.ndarray) -> tuple[float, float, float, float]:
    """``fx, fy, cx, cy`` of a camera matrix; ValueError unless fx, fy > 0 and no skew."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (fx > 0 and fy > 0) or abs(K[0, 1]) > 1e-9 * fx:
        raise ValueError(f"{path}: camera matrix needs fx, fy > 0 and no skew, got {K.tolist()}")
    return float(fx), float(fy), float(cx), float(cy)


def _blocks(path: Path) -> dict[str, list[list[float]]]:
    """A MayaCam 2.0 file's sections as rows of numbers; ValueError naming the line."""
    blocks: dict[str, list[list[float]]] = {}
    name = None
    for number, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.lower() in SECTIONS:
            name = line.lower()
            blocks[name] = []
            continue
        if name is None:
            raise ValueError(f"{path}: line {number} {line!r} is in no section ({SECTIONS})")
        try:
            blocks[name].append([float(w) for w in line.replace(",", " ").split()])
        except ValueError:
            raise ValueError(
                f"{path}: line {number} of {name!r} is not numbers: {line!r}"
            ) from None
    missing = [s for s in SECTIONS if s not in blocks]
    if missing:
        raise ValueError(f"{path}: not a MayaCam 2.0 file: no {missing[0]!r} section")
    return blocks


def is_mayacam(path: str | Path) -> bool:
    """Whether a file starts as a MayaCam 2.0 calibration does (its first section)."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.strip():
                return line.strip().lower() == "image size"
    return False

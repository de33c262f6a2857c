"""Registration accuracy against ground truth (docs/system.md, "Metrics").

Per body and frame: the six DoF of docs/conventions.md (the centroid's translation, mm, and
extrinsic x-y-z rotation angles, deg) estimated minus true; the translation error split into
out-of-plane (along the ray from the source through the bone's true centroid: single-plane depth)
and in-plane (the rest); and the target registration error (TRE), the mean distance between the
bone's voxels moved by the estimated and by the true pose. Over a run: mean and median TRE, the
success rate RSR (share of registrations with TRE below a threshold, 1.5 mm), mTrans and mRot (means
of the absolute translation and rotation DoF errors), seconds per frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from recon.geometry import View

RSR_THRESHOLD_MM = 1.5


@dataclass(frozen=True)
class PoseError:
    """Errors of one body in one frame."""

    body: str
    frame: int
    dof: tuple[float, float, float, float, float, float]
    """Estimated minus true (tx, ty, tz) mm and (rx, ry, rz) deg."""
    in_plane_mm: float
    out_of_plane_mm: float
    tre_mm: float


def six_dof(T: np.ndarray, centroid_mm: np.ndarray) -> np.ndarray:
    """The 6-DoF vector of a pose (docs/conventions.md): moved centroid (mm), extrinsic xyz
    angles (deg)."""
    moved = T[:3, :3] @ centroid_mm + T[:3, 3]
    return np.concatenate((moved, Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)))


def pose_error(
    body: str,
    frame: int,
    estimated: np.ndarray,
    true: np.ndarray,
    points_mm: np.ndarray,
    view: View,
) -> PoseError:
    """Errors of ``estimated`` against ``true`` for a body of reference ``points_mm``."""
    centroid = points_mm.mean(axis=0)
    dof = six_dof(estimated, centroid) - six_dof(true, centroid)
    dof[3:] = (dof[3:] + 180.0) % 360.0 - 180.0
    moved_true = true[:3, :3] @ centroid + true[:3, 3]
    ray = moved_true - view.source_mm
    ray /= np.linalg.norm(ray)
    out_of_plane = float(abs(dof[:3] @ ray))
    in_plane = float(np.linalg.norm(dof[:3] - (dof[:3] @ ray) * ray))
    sample = points_mm[:: max(1, len(points_mm) // 20000)]
    est = sample @ estimated[:3, :3].T + estimated[:3, 3]
    tru = sample @ true[:3, :3].T + true[:3, 3]
    tre = float(np.linalg.norm(est - tru, axis=1).mean())
    return PoseError(body, frame, tuple(float(x) for x in dof), in_plane, out_of_plane, tre)


def summarize(
    errors: list[PoseError],
    warm_seconds: list[float] | None = None,
    first_seconds: float | None = None,
) -> dict:
    """Run-level metrics (JSON-ready; keys name their units)."""
    dof = np.abs(np.array([e.dof for e in errors]))
    tre = np.array([e.tre_mm for e in errors])
    bodies = sorted({e.body for e in errors})
    out = {
        "tx_mm": float(dof[:, 0].mean()),
        "ty_mm": float(dof[:, 1].mean()),
        "tz_mm": float(dof[:, 2].mean()),
        "ra_deg": float(dof[:, 3].mean()),
        "rb_deg": float(dof[:, 4].mean()),
        "rg_deg": float(dof[:, 5].mean()),
        "in_plane_mm_median": float(np.median([e.in_plane_mm for e in errors])),
        "out_of_plane_mm_median": float(np.median([e.out_of_plane_mm for e in errors])),
        "out_of_plane_mm_rms": float(np.sqrt(np.mean([e.out_of_plane_mm**2 for e in errors]))),
        "tre_mm": float(tre.mean()),
        "tre_mm_median": float(np.median(tre)),
        "rsr_pct": float(100.0 * np.mean(tre < RSR_THRESHOLD_MM)),
        "rsr_pct_by_body": {
            b: float(100.0 * np.mean([e.tre_mm < RSR_THRESHOLD_MM for e in errors if e.body == b]))
            for b in bodies
        },
        "mtrans_mm": float(dof[:, :3].mean()),
        "mrot_deg": float(dof[:, 3:].mean()),
        "registrations": len(errors),
    }
    if warm_seconds:
        out["s_per_frame"] = float(np.mean(warm_seconds))
    if first_seconds is not None:
        out["s_first_frame"] = float(first_seconds)
    return out


def as_rows(errors: list[PoseError]) -> list[dict]:
    """Per-registration rows (for a metrics file)."""
    return [asdict(e) for e in errors]


def camera_differences(
    estimated: np.ndarray, reference: np.ndarray, centroid_mm: np.ndarray, T_world_camera
) -> np.ndarray:
    """``estimated`` minus ``reference`` along the camera's axes (registration.jointtrack's
    camera_frame: x, y in the image plane, z along the view, towards the source): the body's
    centroid (mm) and the rotation taking the reference to the estimate, as a rotation vector
    about those axes (deg), (6,)."""
    T_camera_world = np.linalg.inv(T_world_camera)
    moved = [T_camera_world @ T for T in (estimated, reference)]
    centre = [T[:3, :3] @ centroid_mm + T[:3, 3] for T in moved]
    turn = Rotation.from_matrix(moved[0][:3, :3] @ moved[1][:3, :3].T).as_rotvec(degrees=True)
    return np.concatenate((centre[0] - centre[1], turn))


def edge_distances_px(image: np.ndarray, sigma_px: float = 2.0) -> np.ndarray | None:
    """Each pixel's distance (pixels) to the nearest edge a Canny detector finds in ``image``
    at ``sigma_px``; None when it finds none."""
    from scipy.ndimage import distance_transform_edt
    from skimage.feature import canny

    edges = canny(np.asarray(image, dtype=np.float64), sigma=sigma_px)
    return distance_transform_edt(~edges) if edges.any() else None


def edge_fit_px(distances_px: np.ndarray | None, silhouette: np.ndarray) -> float:
    """How well a silhouette's outline sits on an image's edges: the mean distance (pixels)
    from its outline pixels to the nearest edge (``distances_px``: :func:`edge_distances_px`
    of the image); nan without edges or outline."""
    from registration.overlays import outline

    line = outline(silhouette)
    if distances_px is None or not line.any():
        return float("nan")
    return float(distances_px[line].mean())

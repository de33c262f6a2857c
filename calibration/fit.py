"""Projection matrices from ball correspondences.

- :func:`dlt`: normalised direct linear transform (Hartley), then Levenberg-Marquardt on the
  reprojection error (scipy least_squares, robust loss): 11 free parameters per view.
- :func:`fit_view`: a physical view, 9 parameters (focal spot, panel centre, panel rotation
  about the planned orientation) with the pixel pitch fixed and a Gaussian prior toward the
  planned view (the robot's commanded pose): stable with few balls and far better at placing
  the source, whose distance trades against magnification in the free fit.
- :func:`fit_phantom_pose`: the phantom's placement (6 parameters) from all views at once
  through the planned geometry. This fixes the gauge: a rigid motion common to every view is
  attributed to the phantom, so the calibrated views stay in the scanner's (planned) frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from recon.geometry import Geometry, View

ROBUST_SCALE_PX = 0.5
"""soft-L1 loss scale: residuals beyond ~0.5 px (a misdetection) lose influence."""


@dataclass(frozen=True)
class Prior:
    """Standard deviations of the planned view's pose (the robot's repeatability)."""

    source_mm: float = 1.0
    detector_mm: float = 1.0
    detector_deg: float = 0.5


def _normalise_2d(x: np.ndarray) -> np.ndarray:
    mean = x.mean(axis=0)
    scale = np.sqrt(2) / np.mean(np.linalg.norm(x - mean, axis=1))
    return np.array([[scale, 0, -scale * mean[0]], [0, scale, -scale * mean[1]], [0, 0, 1]])


def _normalise_3d(x: np.ndarray) -> np.ndarray:
    mean = x.mean(axis=0)
    scale = np.sqrt(3) / np.mean(np.linalg.norm(x - mean, axis=1))
    T = np.eye(4) * scale
    T[3, 3] = 1.0
    T[:3, 3] = -scale * mean
    return T


def project(P: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel (u, v) of world ``points`` (N, 3) mm through the 3x4 matrix ``P``, (N, 2)."""
    h = points @ P[:, :3].T + P[:, 3]
    return h[:, :2] / h[:, 2:3]


def dlt(points_mm: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Free 3x4 projection matrix from >= 6 correspondences (normalised DLT + robust LM)."""
    if len(points_mm) < 6:
        raise ValueError(f"a free projection matrix needs >= 6 balls, got {len(points_mm)}")
    T2, T3 = _normalise_2d(uv), _normalise_3d(points_mm)
    x = np.column_stack((uv, np.ones(len(uv)))) @ T2.T
    X = np.column_stack((points_mm, np.ones(len(points_mm)))) @ T3.T
    rows = []
    for (u, v, w), Xi in zip(x, X, strict=True):
        rows.append(np.concatenate((np.zeros(4), -w * Xi, v * Xi)))
        rows.append(np.concatenate((w * Xi, np.zeros(4), -u * Xi)))
    _, _, vt = np.linalg.svd(np.array(rows))
    P = np.linalg.inv(T2) @ vt[-1].reshape(3, 4) @ T3
    P /= np.linalg.norm(P)

    def residual(p):
        return (project(p.reshape(3, 4), points_mm) - uv).ravel()

    P = least_squares(residual, P.ravel(), loss="soft_l1", f_scale=ROBUST_SCALE_PX).x
    P = P.reshape(3, 4)
    return P / np.linalg.norm(P) * np.sign(P[2] @ np.append(points_mm.mean(axis=0), 1.0))


def _view(params: np.ndarray, planned: View) -> View:
    R = Rotation.from_rotvec(params[6:9]).as_matrix()
    e_u, e_v = R @ planned.e_u, R @ planned.e_v
    center = planned.detector_center_mm + params[3:6]
    origin = (
        center
        - 0.5 * (planned.cols - 1) * planned.pitch_u_mm * e_u
        - 0.5 * (planned.rows - 1) * planned.pitch_v_mm * e_v
    )
    return View(
        planned.source_mm + params[:3],
        origin,
        e_u,
        e_v,
        planned.pitch_u_mm,
        planned.pitch_v_mm,
        planned.rows,
        planned.cols,
    )


def _project_params(params: np.ndarray, planned: View, points: np.ndarray) -> np.ndarray:
    """Pixels of ``points`` through the view ``params`` describe, without building a View."""
    R = Rotation.from_rotvec(params[6:9]).as_matrix()
    e_u, e_v = R @ planned.e_u, R @ planned.e_v
    n = np.cross(e_u, e_v)
    source = planned.source_mm + params[:3]
    center = planned.detector_center_mm + params[3:6]
    rays = points - source
    t = ((center - source) @ n) / (rays @ n)
    hit = source + t[:, None] * rays - center
    u = hit @ e_u / planned.pitch_u_mm + 0.5 * (planned.cols - 1)
    v = hit @ e_v / planned.pitch_v_mm + 0.5 * (planned.rows - 1)
    return np.column_stack((u, v))


def fit_view(
    planned: View, points_mm: np.ndarray, uv: np.ndarray, prior: Prior, noise_px: float
) -> tuple[View, np.ndarray]:
    """The physical view that best reprojects the balls, regularised toward the plan.

    Args:
        planned: the view the plan expected.
        points_mm: the identified balls' world centres (K, 3), mm.
        uv: their detected centroids (K, 2), pixels (column u, row v).
        prior: the planned pose's standard deviations (mm, degrees).
        noise_px: the centroids' noise, px: weighs the prior against the reprojection.

    Returns:
        The view and the reprojection residuals (K, 2) px.
    """
    weights = np.concatenate(
        (
            np.full(3, 1 / prior.source_mm),
            np.full(3, 1 / prior.detector_mm),
            np.full(3, 1 / np.radians(prior.detector_deg)),
        )
    )

    def residual(params):
        reprojection = (_project_params(params, planned, points_mm) - uv).ravel() / noise_px
        return np.concatenate((reprojection, params * weights))

    fit = least_squares(residual, np.zeros(9), loss="linear", method="lm")
    return _view(fit.x, planned), _project_params(fit.x, planned, points_mm) - uv


def fit_phantom_pose(
    planned: Geometry,
    local_points_mm: np.ndarray,
    detections: list[tuple[np.ndarray, np.ndarray]],
    initial: np.ndarray,
) -> np.ndarray:
    """T_world_phantom (4x4) reprojecting the identified balls best through the planned views.

    ``detections[k]`` holds (ball ids, uv) of view k; ``initial`` is the nominal placement.
    """
    rotvec0 = Rotation.from_matrix(initial[:3, :3]).as_rotvec()
    x0 = np.concatenate((rotvec0, initial[:3, 3]))

    def world(x):
        return local_points_mm @ Rotation.from_rotvec(x[:3]).as_matrix().T + x[3:]

    def residual(x):
        pts = world(x)
        return np.concatenate(
            [
                (view.project(pts[ids]) - uv).ravel()
                for view, (ids, uv) in zip(planned, detections, strict=True)
                if len(ids)
            ]
        )

    fit = least_squares(residual, x0, loss="soft_l1", f_scale=5.0)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(fit.x[:3]).as_matrix()
    T[:3, 3] = fit.x[3:]
    return T

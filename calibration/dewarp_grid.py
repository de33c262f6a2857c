"""Fluoroscopy image distortion: a dewarp grid's image -> a polynomial warp -> dewarped frames.

An image intensifier, and to a lesser degree a flat panel, images a point a little away from
where the view's projection matrix puts it (pincushion, S-distortion). For single-plane 2D-3D
registration this matters most along the ray: 1 mm of depth rescales a bone's shadow by only
~0.1 %, and a pincushion of 1 px at the corners of a 512-pixel panel rescales the image
locally by ~0.2 % half-way out, so it reads as 1-2 mm of depth.

The dewarp grid (:class:`DewarpGridSpec`) is a plate of steel balls on a square lattice,
mounted on the panel's face at a known gap: each ball's ideal pixel position is its
projection through the fluoroscopy view. One exposure of the grid alone gives the balls'
measured centroids (calibration.detect); a bivariate polynomial of the ideal pixel position
(degree 5 by default, so any smooth warp, not only a radial one) is fitted by least squares to
where each ball was imaged (:func:`fit_distortion`). Dewarping a frame samples it at the
polynomial's image of every ideal pixel (cubic B-spline): the result is what the view's
matrix describes, so DRRs and frames share one geometry. The fit also fixes the grid's
gauge: an error in the plate's mounting goes into the dewarped frames, so the plate must sit
on the panel where the spec says.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from calibration.detect import detect_balls
from recon.distortion import Distortion, panel_mm
from recon.geometry import View

MATCH_FRACTION = 0.3
"""A detection is a ball's if it lies within this fraction of the lattice's pitch (at the
panel) of where the current warp puts the ball."""

MAX_RMS_PX = 0.3
"""A fit whose residual RMS exceeds this (pixels) is refused: wrong grid, wrong view, or a
warp the polynomial cannot follow."""


class DewarpGridSpec(BaseModel):
    """A dewarp grid: steel balls on a square lattice in a thin PMMA plate mounted parallel to
    the panel, centred on it, ``gap_mm`` in front of it (towards the source)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    pitch_mm: float = Field(10.0, gt=1.0, le=100.0, description="lattice pitch at the plate, mm")
    ball_diameter_mm: float = Field(2.0, gt=0.1, le=10.0, description="ball diameter, mm")
    ball_mu_per_mm: float = Field(0.47, gt=0.0, description="ball attenuation (steel), 1/mm")
    plate_thickness_mm: float = Field(3.0, ge=0.0, le=50.0, description="plate, mm")
    plate_mu_per_mm: float = Field(0.0214, ge=0.0, description="plate attenuation (PMMA), 1/mm")
    gap_mm: float = Field(
        20.0, ge=0.0, le=200.0, description="plate's mid-plane to the panel's surface, mm"
    )

    def balls_mm(self, view: View) -> np.ndarray:
        """World centres of the balls whose shadows fall on ``view``'s panel, mm (N, 3)."""
        centre = view.detector_center_mm - self.gap_mm * view.normal
        half = 0.5 * max(view.cols * view.pitch_u_mm, view.rows * view.pitch_v_mm)
        n = math.ceil(half / self.pitch_mm)
        i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
        balls = (
            centre
            + (i.reshape(-1, 1) * self.pitch_mm) * view.e_u
            + (j.reshape(-1, 1) * self.pitch_mm) * view.e_v
        )
        uv = view.project(balls)
        on = (uv[:, 0] > -0.5) & (uv[:, 0] < view.cols - 0.5)
        on &= (uv[:, 1] > -0.5) & (uv[:, 1] < view.rows - 0.5)
        return balls[on]

    def ball_radius_px(self, view: View) -> float:
        """The balls' shadow radius at the panel, pixels."""
        magnification = view.sdd_mm / (view.sdd_mm - self.gap_mm)
        return 0.5 * self.ball_diameter_mm * magnification / view.pitch_u_mm


def fit_distortion(
    image: np.ndarray, view: View, grid: DewarpGridSpec, degree: int = 5
) -> Distortion:
    """The panel's warp from one image (line integrals [v, u]) of ``grid`` through ``view``
    (best at the panel's native pitch: the warp then serves every binned read-out).

    Balls are detected (calibration.detect.detect_balls) and matched to the lattice from
    the identity outwards: each round fits a polynomial (degree 1, 3, then ``degree``) to
    the matches so far and matches again within :data:`MATCH_FRACTION` of the pitch of its
    prediction. ValueError if the image does not match the view, its pixels are not square,
    too few balls are found for the degree, or the residual RMS exceeds :data:`MAX_RMS_PX`.
    """
    image = np.asarray(image, dtype=np.float64)
    if image.shape != (view.rows, view.cols):
        raise ValueError(
            f"grid image of shape {image.shape} does not match the view's panel "
            f"({view.rows} rows x {view.cols} cols)"
        )
    if not math.isclose(view.pitch_u_mm, view.pitch_v_mm, rel_tol=1e-6):
        raise ValueError(f"pixels must be square, got {view.pitch_u_mm} x {view.pitch_v_mm} mm")
    if not 1 <= degree <= 9:
        raise ValueError(f"degree must be 1..9, got {degree}")
    pitch = view.pitch_u_mm
    ideal = np.column_stack(
        panel_mm(*view.project(grid.balls_mm(view)).T, view.rows, view.cols, pitch)
    )
    radius = grid.ball_radius_px(view)
    found = detect_balls(image, 1.5 * radius + 1.0, threshold=0.02).uv
    found = np.column_stack(panel_mm(*found.T, view.rows, view.cols, pitch)).reshape(-1, 2)
    magnification = view.sdd_mm / (view.sdd_mm - grid.gap_mm)
    reach = MATCH_FRACTION * grid.pitch_mm * magnification
    terms = (degree + 1) * (degree + 2) // 2
    extent = (view.cols * pitch, view.rows * pitch)
    warp = _fit(ideal, ideal, extent, 1)  # the identity
    for d in (1, 3, degree):
        d = min(d, degree)
        predicted = np.column_stack(warp.warp(ideal[:, 0], ideal[:, 1]))
        pairs = _match(predicted, found, reach)
        if len(pairs) < 3 * terms:
            raise ValueError(
                f"dewarp grid: {len(pairs)} of {len(ideal)} balls found, need at least "
                f"{3 * terms} for degree {degree} (is it the grid's image through this view?)"
            )
        warp = _fit(ideal[pairs[:, 0]], found[pairs[:, 1]], extent, d)
    if warp.rms_mm > MAX_RMS_PX * pitch:
        raise ValueError(
            f"dewarp grid: residual RMS {warp.rms_mm / pitch:.2f} px above the limit "
            f"{MAX_RMS_PX} px"
        )
    return warp


def _match(predicted: np.ndarray, found: np.ndarray, reach_mm: float) -> np.ndarray:
    """(ball, detection) index pairs: each ball's nearest detection within ``reach_mm``, each
    detection used once (the nearer ball keeps it)."""
    if len(found) == 0:
        return np.zeros((0, 2), dtype=int)
    distance = np.linalg.norm(predicted[:, None, :] - found[None, :, :], axis=2)
    nearest = distance.argmin(axis=1)
    close = distance[np.arange(len(predicted)), nearest] < reach_mm
    pairs = {}
    for ball in np.nonzero(close)[0]:
        det = int(nearest[ball])
        if det not in pairs or distance[ball, det] < distance[pairs[det], det]:
            pairs[det] = int(ball)
    return np.array(sorted((b, d) for d, b in pairs.items()), dtype=int).reshape(-1, 2)


def _fit(
    ideal: np.ndarray, measured: np.ndarray, extent_mm: tuple[float, float], degree: int
) -> Distortion:
    """The least-squares polynomial of ``degree`` from ideal to measured panel positions
    (N, 2), mm, on a panel of ``extent_mm`` (width, height)."""
    blank = Distortion(*extent_mm, degree, np.zeros((2, 1)))
    basis = blank.basis(ideal[:, 0], ideal[:, 1])
    coefficients, *_ = np.linalg.lstsq(basis, measured, rcond=None)
    residual = np.linalg.norm(basis @ coefficients - measured, axis=1)
    fitted = Distortion(*extent_mm, degree, coefficients.T)
    y, x = np.mgrid[-0.5:0.5:65j, -0.5:0.5:65j]
    x, y = x * extent_mm[0], y * extent_mm[1]
    wx, wy = fitted.warp(x, y)
    return Distortion(
        *extent_mm,
        degree,
        coefficients.T,
        float(np.sqrt(np.mean(residual**2))),
        float(residual.max()),
        len(ideal),
        float(np.hypot(wx - x, wy - y).max()),
    )

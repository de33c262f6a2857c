"""Renders the steel-ball calibration phantom (calibration.phantom): its PMMA body and balls
as ellipsoids with exact line integrals."""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from calibration.phantom import BBPhantomSpec
from recon.geometry import Geometry
from sim.phantoms.ellipsoids import Ellipsoid, ellipsoid_line_integrals


def bb_ellipsoids(spec: BBPhantomSpec) -> tuple[Ellipsoid, list[Ellipsoid]]:
    """The body (an ellipsoid) and the balls (spheres), in the world."""
    T = spec.T_world_phantom
    body = Ellipsoid(
        T[:3, 3],
        (spec.body_radius_mm, spec.body_radius_mm, spec.body_half_height_mm),
        T[:3, :3],
        spec.body_mu_per_mm,
    )
    balls = [
        Ellipsoid(p, (0.5 * d,) * 3, np.eye(3), spec.ball_mu_per_mm - spec.body_mu_per_mm)
        for p, d in zip(spec.ball_positions_mm(), spec.ball_diameters_mm(), strict=True)
    ]
    return body, balls


def project_bb(
    spec: BBPhantomSpec, geometry: Geometry, body_step_px: int = 8, hidden: set[int] = frozenset()
) -> np.ndarray:
    """Exact line integrals of the phantom, float32 (views, rows, cols).

    The smooth body is evaluated every ``body_step_px`` pixels and interpolated bilinearly;
    each ball exactly, on the pixels around its shadow. Balls in ``hidden`` are left out
    (lost balls, for robustness tests).
    """
    body, balls = bb_ellipsoids(spec)
    balls = [ball for i, ball in enumerate(balls) if i not in hidden]
    out = np.empty((len(geometry), geometry.rows, geometry.cols), dtype=np.float32)
    rows = np.arange(0, geometry.rows + body_step_px, body_step_px).clip(max=geometry.rows - 1)
    cols = np.arange(0, geometry.cols + body_step_px, body_step_px).clip(max=geometry.cols - 1)
    rows, cols = np.unique(rows), np.unique(cols)
    for k, view in enumerate(geometry):
        cc, rr = np.meshgrid(cols, rows)
        ends = view.pixel_to_world(cc, rr).reshape(-1, 3)
        coarse = ellipsoid_line_integrals([body], view.source_mm, ends).reshape(rr.shape)
        out[k] = _upsample(coarse, rows, cols, geometry.rows, geometry.cols)
        for ball in balls:
            u, v = view.project(ball.center_mm)[0]
            depth = float(view.depth(ball.center_mm)[0])
            half = math.ceil(ball.semi_axes_mm[0] / depth / view.pitch_u_mm) + 2
            r0, r1 = max(0, int(v) - half), min(geometry.rows, int(v) + half + 2)
            c0, c1 = max(0, int(u) - half), min(geometry.cols, int(u) + half + 2)
            if r0 >= r1 or c0 >= c1:
                continue
            uu, vv = np.meshgrid(np.arange(c0, c1), np.arange(r0, r1))
            ends = view.pixel_to_world(uu, vv).reshape(-1, 3)
            chords = ellipsoid_line_integrals([ball], view.source_mm, ends)
            out[k, r0:r1, c0:c1] += chords.reshape(uu.shape).astype(np.float32)
    return out


def _upsample(coarse: np.ndarray, rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int):
    interp = RegularGridInterpolator((rows, cols), coarse, method="linear")
    rr, cc = np.meshgrid(np.arange(n_rows), np.arange(n_cols), indexing="ij")
    return interp(np.stack((rr, cc), axis=-1)).astype(np.float32)

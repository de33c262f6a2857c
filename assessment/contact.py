"""How far a femoral condyle stands above the tibial plateau's surface (or the insert's).

The plateau's upward-facing surface points (TibiaAnatomy.surface_mm) make a height field over
the TP plane: their heights along the plane's normal, interpolated linearly between them
(a Delaunay triangulation of their footprints). A condyle's gap is the least height of its
points above the surface beneath them; points beyond the surface's footprint do not count.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import LinearNDInterpolator

from assessment.anatomy import TibiaAnatomy


class PlateauSurface:
    """The plateau's surface as heights above the TP plane, in the tibia's reference frame.

    Args:
        tibia: The tibia's (or the insert's) anatomy, with its surface points.
    """

    def __init__(self, tibia: TibiaAnatomy) -> None:
        if tibia.surface_mm is None or len(tibia.surface_mm) < 3:
            raise ValueError("the plateau has no surface points to measure a gap against")
        self._center = tibia.plateau_center_mm
        self._normal = tibia.plateau_normal
        self._axes = np.stack(tibia.plane_axes)
        surface = np.asarray(tibia.surface_mm, dtype=np.float64)
        self._height = LinearNDInterpolator(
            self._footprint(surface), (surface - self._center) @ self._normal
        )

    def _footprint(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) in the TP plane's (medial, anterior) axes, mm (..., 2)."""
        return (points - self._center) @ self._axes.T

    def gap_mm(self, points: np.ndarray) -> np.ndarray:
        """The least height of each set of points above the surface beneath them.

        Args:
            points: Point sets in the tibia's reference frame (..., N, 3), mm.

        Returns:
            Per set, mm (...); NaN where no point stands over the surface.
        """
        points = np.asarray(points, dtype=np.float64)
        above = (points - self._center) @ self._normal - self._height(self._footprint(points))
        over = np.isfinite(above)
        least = np.where(over, above, np.inf).min(axis=-1)
        return np.where(over.any(axis=-1), least, np.nan)

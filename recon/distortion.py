"""A fluoroscopy panel's geometric distortion as a polynomial warp, and dewarping frames with it.

Where the panel images each ideal point (the view's projection of a world point) is
``(x', y') = poly(x, y)``: panel coordinates in mm from the panel's centre along its u and v
axes, the polynomial of their values normalised by half the panel's larger side (any smooth
warp: pincushion, S-distortion). Millimetres, not pixels: the warp belongs to the panel, so a
grid imaged at the native pitch dewarps frames read out binned. Dewarping samples a frame at
the warp of every pixel centre, so the result is what the view's matrix describes.
calibration.dewarp_grid estimates the warp from an image of a dewarp grid.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

EXTENT_TOLERANCE = 1e-3
"""Frames whose panel extent (pixels x pitch) differs from the warp's by more than this
fraction are refused: another panel."""


def monomials(x: np.ndarray, y: np.ndarray, degree: int) -> np.ndarray:
    """Columns ``x^i y^j`` for ``i + j <= degree``, (N, terms)."""
    return np.column_stack([x**i * y ** (d - i) for d in range(degree + 1) for i in range(d + 1)])


def panel_mm(
    u: np.ndarray, v: np.ndarray, rows: int, cols: int, pitch_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Panel coordinates (mm from the panel's centre) of pixel positions (u, v) of a read-out
    of ``rows`` x ``cols`` square pixels of ``pitch_mm``."""
    return (
        (np.asarray(u, np.float64) - 0.5 * (cols - 1)) * pitch_mm,
        (np.asarray(v, np.float64) - 0.5 * (rows - 1)) * pitch_mm,
    )


@dataclass(frozen=True)
class Distortion:
    """Where the panel images each ideal point: ``(x', y') = poly(x, y)``, panel mm.

    Attributes:
        width_mm, height_mm: the panel's extent (along u, along v).
        degree: total degree of the polynomial.
        coefficients: (2, terms) for x' and y', of :func:`monomials` of (x, y) divided by
            half the panel's larger side.
        rms_mm, max_mm: residuals of the fit at the balls, mm.
        balls: balls matched and fitted.
        max_displacement_mm: the largest |warp - identity| over the panel, mm.
    """

    width_mm: float
    height_mm: float
    degree: int
    coefficients: np.ndarray
    rms_mm: float = 0.0
    max_mm: float = 0.0
    balls: int = 0
    max_displacement_mm: float = 0.0

    def basis(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """The polynomial's terms at panel points (mm), (N, terms)."""
        scale = 0.5 * max(self.width_mm, self.height_mm)
        x, y = np.ravel(x_mm) / scale, np.ravel(y_mm) / scale
        return monomials(x, y, self.degree)

    def warp(self, x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measured panel positions of ideal ones, mm (same shapes)."""
        warped = self.basis(x_mm, y_mm) @ self.coefficients.T
        shape = np.shape(x_mm)
        return warped[:, 0].reshape(shape), warped[:, 1].reshape(shape)

    def undistort(self, frames: np.ndarray, pitch_mm: float) -> np.ndarray:
        """Frames as the view's matrix sees them: each (rows, cols) or (F, rows, cols) image of
        square pixels of ``pitch_mm`` (any read-out of this panel) sampled at the warp of every
        pixel centre (cubic B-spline, edges extended), float32."""
        arr = np.asarray(frames, dtype=np.float32)
        if arr.ndim not in (2, 3):
            raise ValueError(f"frames must be (rows, cols) or (F, rows, cols), got {arr.shape}")
        rows, cols = arr.shape[-2:]
        extent = (cols * pitch_mm, rows * pitch_mm)
        if not all(
            math.isclose(a, b, rel_tol=EXTENT_TOLERANCE)
            for a, b in zip(extent, (self.width_mm, self.height_mm), strict=True)
        ):
            raise ValueError(
                f"frames of {cols} x {rows} pixels of {pitch_mm} mm ({extent[0]:.1f} x "
                f"{extent[1]:.1f} mm) do not match the distortion's panel "
                f"({self.width_mm:.1f} x {self.height_mm:.1f} mm)"
            )
        v, u = np.mgrid[0:rows, 0:cols]
        wx, wy = self.warp(*panel_mm(u, v, rows, cols, pitch_mm))
        coords = np.stack((wy / pitch_mm + 0.5 * (rows - 1), wx / pitch_mm + 0.5 * (cols - 1)))
        flat = arr.reshape(-1, rows, cols)
        out = [ndimage.map_coordinates(f, coords, order=3, mode="nearest") for f in flat]
        return np.stack(out).reshape(arr.shape).astype(np.float32)

    def summary(self) -> dict:
        """The fit's figures (mm), for reports."""
        data = asdict(self)
        del data["coefficients"]
        return data

    def write(self, path: Path) -> Path:
        """Write the warp as JSON (read back by :meth:`read`)."""
        data = self.summary() | {"coefficients": self.coefficients.tolist()}
        Path(path).write_text(json.dumps(data, indent=1), encoding="utf-8")
        return Path(path)

    @classmethod
    def read(cls, path: Path) -> Distortion:
        """A distortion written by :meth:`write`: ValueError naming the file if malformed, a
        number is not finite, the panel's extent is not positive or the degree not a whole
        number >= 0 (OSError if unreadable)."""
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
            data["coefficients"] = np.asarray(data["coefficients"], dtype=np.float64)
            distortion = cls(**data)
            for name, value in asdict(distortion).items():
                if not np.all(np.isfinite(np.asarray(value, dtype=np.float64))):
                    raise ValueError(f"{name} is not finite")
            if not (distortion.width_mm > 0 and distortion.height_mm > 0):
                raise ValueError(f"panel extent {distortion.width_mm} x {distortion.height_mm} mm")
            if not isinstance(distortion.degree, int) or distortion.degree < 0:
                raise ValueError(f"degree {distortion.degree!r} is not a whole number >= 0")
            terms = (distortion.degree + 1) * (distortion.degree + 2) // 2
            if distortion.coefficients.shape != (2, terms):
                raise ValueError(f"coefficients {distortion.coefficients.shape}, need (2, {terms})")
            return distortion
        except (KeyError, TypeError, ValueError) as err:  # JSON and UTF-8 errors are ValueErrors
            raise ValueError(f"{path}: not a distortion file ({err})") from err

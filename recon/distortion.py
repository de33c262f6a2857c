"""A fluoroscopy panel's geometric distortion as a polynomial warp, and dewarping frames with it.

Where the panel images each ideal pixel position (the view's projection of a point) is
``(u', v') = poly(u, v)``, a bivariate polynomial of the position normalised to [-1, 1] across
the panel (any smooth warp: pincushion, S-distortion). Dewarping samples a frame at the warp
of every pixel, so the result is what the view's matrix describes. calibration.distortion
estimates the warp from an image of a dewarp grid.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage


def monomials(x: np.ndarray, y: np.ndarray, degree: int) -> np.ndarray:
    """Columns ``x^i y^j`` for ``i + j <= degree``, (N, terms)."""
    return np.column_stack([x**i * y ** (d - i) for d in range(degree + 1) for i in range(d + 1)])


@dataclass(frozen=True)
class Distortion:
    """Where the panel images each ideal pixel position: ``(u', v') = poly(u, v)``.

    Attributes:
        rows, cols: the panel the warp belongs to, pixels.
        degree: total degree of the polynomial.
        coefficients: (2, terms) for u' and v', of :func:`monomials` of the ideal pixel
            position normalised to [-1, 1] across the panel.
        rms_px, max_px: residuals of the fit at the balls, pixels.
        balls: balls matched and fitted.
        max_displacement_px: the largest |warp - identity| over the panel, pixels.
    """

    rows: int
    cols: int
    degree: int
    coefficients: np.ndarray
    rms_px: float
    max_px: float
    balls: int
    max_displacement_px: float

    def normalised(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel positions normalised to [-1, 1] across the panel (the polynomial's argument)."""
        cu, cv = 0.5 * (self.cols - 1), 0.5 * (self.rows - 1)
        scale = 0.5 * max(self.cols, self.rows)
        return (np.asarray(u, np.float64) - cu) / scale, (np.asarray(v, np.float64) - cv) / scale

    def warp(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measured pixel positions (u', v') of ideal ones (u, v), pixels."""
        x, y = self.normalised(u, v)
        basis = monomials(x.ravel(), y.ravel(), self.degree)
        warped = basis @ self.coefficients.T
        return warped[:, 0].reshape(np.shape(u)), warped[:, 1].reshape(np.shape(u))

    def undistort(self, frames: np.ndarray) -> np.ndarray:
        """Frames as the view's matrix sees them: each (rows, cols) or (F, rows, cols) image
        sampled at the warp of every pixel (cubic B-spline, edges extended), float32."""
        arr = np.asarray(frames, dtype=np.float32)
        if arr.ndim not in (2, 3) or arr.shape[-2:] != (self.rows, self.cols):
            raise ValueError(
                f"frames of shape {arr.shape} do not match the distortion's panel "
                f"({self.rows} rows x {self.cols} cols)"
            )
        v, u = np.mgrid[0 : self.rows, 0 : self.cols]
        wu, wv = self.warp(u, v)
        coords = np.stack((wv, wu))
        flat = arr.reshape(-1, self.rows, self.cols)
        out = [ndimage.map_coordinates(f, coords, order=3, mode="nearest") for f in flat]
        return np.stack(out).reshape(arr.shape).astype(np.float32)

    def summary(self) -> dict:
        """The fit's figures (pixels), for reports."""
        return {
            "degree": self.degree,
            "balls": self.balls,
            "rms_px": self.rms_px,
            "max_px": self.max_px,
            "max_displacement_px": self.max_displacement_px,
        }

    def write(self, path: Path) -> Path:
        """Write the warp as JSON (read back by :meth:`read`)."""
        data = {"rows": self.rows, "cols": self.cols, **self.summary()}
        data["coefficients"] = self.coefficients.tolist()
        Path(path).write_text(json.dumps(data, indent=1), encoding="utf-8")
        return Path(path)

    @classmethod
    def read(cls, path: Path) -> Distortion:
        """A distortion written by :meth:`write` (ValueError naming the file if malformed)."""
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
            coefficients = np.asarray(data["coefficients"], dtype=np.float64)
            degree = int(data["degree"])
            terms = (degree + 1) * (degree + 2) // 2
            if coefficients.shape != (2, terms):
                raise ValueError(f"coefficients {coefficients.shape}, need (2, {terms})")
            return cls(
                int(data["rows"]),
                int(data["cols"]),
                degree,
                coefficients,
                float(data["rms_px"]),
                float(data["max_px"]),
                int(data["balls"]),
                float(data["max_displacement_px"]),
            )
        except (KeyError, TypeError, ValueError, json.JSONDecodeError) as err:
            raise ValueError(f"{path}: not a distortion file ({err})") from err

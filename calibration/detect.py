"""Steel balls in a projection: candidates, sub-pixel centroids, size, rejection.

Candidates are local maxima of a band-pass (difference of Gaussians) image, the weaker of two
maxima closer than a ball's radius dropped (a flat-topped shadow has several). Around each, a
quadratic surface fitted to a ring of pixels outside the ball (and outside its neighbours)
removes the smooth body's line integral; the centroid is the background-free,
intensity-weighted mean within a disc re-centred on it until it settles (a disc centred on the
peak pixel would clip the shadow), and the mass (the sum of those line integrals, pixel
units) measures its volume. Blobs touching the panel's edge, merged (overlapping) or not round
are rejected.

Centroid bias: the intensity-weighted centroid of a sphere's shadow differs from the
projection of its centre by perspective, ~ r^2 tan(gamma) / L (r ball radius, L source
distance, gamma ray angle): below 0.01 px here, against 0.1 px of noise; the quadratic
background removes the bias of the curved body underneath.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy.ndimage import maximum_filter
from scipy.spatial import cKDTree

RING_PX = 1.5
"""Gap between a ball's disc and the background ring around it, px."""

RING_WIDTH_PX = 3.0
"""Width of the background ring, px."""


@dataclass(frozen=True)
class Detections:
    """Balls found in one projection.

    Attributes:
        uv: sub-pixel centroids (column u, row v), (K, 2).
        mass: background-free integrated line integral per blob (pixel units), (K,).
        elongation: ratio of the blob's principal second moments (1 for a round blob), (K,).
    """

    uv: np.ndarray
    mass: np.ndarray
    elongation: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, keep: np.ndarray) -> Detections:
        return Detections(self.uv[keep], self.mass[keep], self.elongation[keep])


def detect_balls(image: np.ndarray, ball_radius_px: float, threshold: float = 0.15) -> Detections:
    """Balls in one line-integral image [v, u] (see the module docstring).

    ``ball_radius_px`` bounds the largest ball's shadow radius (with blur margin), px.
    """
    band = band_pass(image, 0.4 * ball_radius_px, 2.5 * ball_radius_px)
    peaks = (band == maximum_filter(band, size=int(2 * ball_radius_px) | 1)) & (band > threshold)
    rows, cols = np.nonzero(peaks)
    rows, cols = _suppress_neighbours(rows, cols, band[rows, cols], ball_radius_px)
    r = math.ceil(ball_radius_px + RING_PX + RING_WIDTH_PX)
    n_rows, n_cols = image.shape
    inside = (rows >= r) & (rows < n_rows - r) & (cols >= r) & (cols < n_cols - r)
    rows, cols = rows[inside], cols[inside]
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    dist = np.hypot(xx, yy)
    ring = dist > ball_radius_px + RING_PX
    terms = (xx, yy, np.ones_like(xx), xx * xx, yy * yy, xx * yy)  # quadratic background
    uv, mass, elongation = [], [], []
    for row, col in zip(rows, cols, strict=True):
        patch = image[row - r : row + r + 1, col - r : col + r + 1].astype(np.float64)
        # the background ring, minus the discs of neighbouring balls that reach into it
        background = ring.copy()
        near = (np.abs(rows - row) <= 2 * r) & (np.abs(cols - col) <= 2 * r)
        near &= (rows != row) | (cols != col)
        for n_row, n_col in zip(rows[near], cols[near], strict=True):
            disc = np.hypot(xx - (n_col - col), yy - (n_row - row))
            background &= disc > ball_radius_px + RING_PX
        if background.sum() < 12:
            continue
        design = np.column_stack([t[background] for t in terms])
        coef, *_ = np.linalg.lstsq(design, patch[background], rcond=None)
        signal = patch - sum(c * t for c, t in zip(coef, terms, strict=True))
        mx = my = 0.0
        for _ in range(3):  # re-centre the ball's disc on the centroid
            core = np.hypot(xx - mx, yy - my) <= ball_radius_px
            weights = np.where(core, np.clip(signal, 0.0, None), 0.0)
            total = weights.sum()
            if total <= 0:
                break
            mx = (weights * xx).sum() / total
            my = (weights * yy).sum() / total
        if total <= 0:
            continue
        cov = np.cov(np.vstack((xx[core] - mx, yy[core] - my)), aweights=weights[core])
        eig = np.linalg.eigvalsh(cov)
        uv.append((col + mx, row + my))
        mass.append(total)
        elongation.append(float(np.sqrt(eig[1] / max(eig[0], 1e-9))))
    if not uv:
        return Detections(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    return Detections(np.array(uv), np.array(mass), np.array(elongation))


def band_pass(image: np.ndarray, sigma_fine_px: float, sigma_coarse_px: float) -> np.ndarray:
    """The image blurred by a Gaussian of ``sigma_fine_px`` minus blurred by one of
    ``sigma_coarse_px`` (a difference of Gaussians), float64: one FFT of the image mirrored
    past its edges by 4 coarse sigmas (the edges as ``scipy.ndimage.gaussian_filter`` treats
    them) instead of two wide convolutions."""
    pad = math.ceil(4.0 * sigma_coarse_px)
    padded = np.pad(np.asarray(image, dtype=np.float64), pad, mode="symmetric")
    shape = [scipy.fft.next_fast_len(n, real=True) for n in padded.shape]
    fy = scipy.fft.fftfreq(shape[0])[:, None]
    fx = scipy.fft.rfftfreq(shape[1])[None, :]
    f2 = fy * fy + fx * fx
    response = np.exp(-2.0 * np.pi**2 * sigma_fine_px**2 * f2)
    response -= np.exp(-2.0 * np.pi**2 * sigma_coarse_px**2 * f2)
    spectrum = scipy.fft.rfft2(padded, s=shape) * response
    out = scipy.fft.irfft2(spectrum, s=shape)
    return out[pad : pad + image.shape[0], pad : pad + image.shape[1]]


def _suppress_neighbours(rows, cols, strength, radius):
    """Keep the strongest of peaks closer than ``radius`` (one ball, several maxima)."""
    points = np.column_stack((rows, cols)).astype(np.float64)
    neighbours = cKDTree(points).query_ball_point(points, radius * (1.0 + 1e-9))
    dropped = np.zeros(len(points), dtype=bool)
    kept: list[int] = []
    for i in np.argsort(-strength):
        if dropped[i]:
            continue
        kept.append(i)
        for j in neighbours[i]:  # the tree's candidates: exactly those within the radius go
            if (rows[i] - rows[j]) ** 2 + (cols[i] - cols[j]) ** 2 <= radius**2:
                dropped[j] = True
    kept_arr = np.array(kept, dtype=int)
    return rows[kept_arr], cols[kept_arr]

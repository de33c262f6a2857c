"""Image similarity for 2D-3D registration: normalised cross-correlation (NCC) of high-pass
filtered images over a mask, and gradient NCC.

High-pass filtering (the image minus its Gaussian blur of a few mm) removes what the rigid
bone model cannot explain: soft-tissue and scatter backgrounds, beam hardening's slow trends.
NCC is 1 for identical images and unchanged by any affine change of intensity (a x + b, a > 0).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter, sobel


def highpass(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """``image`` minus its Gaussian blur (sigma in pixels)."""
    image = np.asarray(image, dtype=np.float32)
    return image - gaussian_filter(image, sigma_px, mode="nearest")


def turned_gaussian(
    image: np.ndarray, sigma_px: tuple[float, float], angle_rad: float
) -> np.ndarray:
    """``image`` (rows, cols) blurred by a Gaussian whose sigmas ``(s_u, s_v)`` (pixels) lie
    along the image's u and v axes turned by ``angle_rad`` (towards +v); edges extended.
    By FFT over the image padded by 4 sigma, float32."""
    s_u, s_v = sigma_px
    pad = int(4.0 * max(s_u, s_v)) + 1
    padded = np.pad(np.asarray(image, dtype=np.float64), pad, mode="edge")
    f_v = np.fft.fftfreq(padded.shape[0])[:, None]
    f_u = np.fft.rfftfreq(padded.shape[1])[None, :]
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    along, across = c * f_u + s * f_v, -s * f_u + c * f_v
    gain = np.exp(-2.0 * np.pi**2 * ((s_u * along) ** 2 + (s_v * across) ** 2))
    blurred = np.fft.irfft2(np.fft.rfft2(padded) * gain, s=padded.shape)
    return blurred[pad:-pad, pad:-pad].astype(np.float32)


def ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Normalised cross-correlation of ``a`` and ``b`` over ``mask`` (all pixels if None);
    0 when either is constant there."""
    if mask is not None:
        a, b = a[mask], b[mask]
    a = a.astype(np.float64).ravel() - a.mean()
    b = b.astype(np.float64).ravel() - b.mean()
    denominator = np.sqrt(np.dot(a, a) * np.dot(b, b))
    return float(np.dot(a, b) / denominator) if denominator > 0 else 0.0


def gradient_ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean NCC of the two images' row and column gradients (Sobel) over ``mask``."""
    return 0.5 * sum(
        ncc(sobel(np.asarray(a, np.float32), axis), sobel(np.asarray(b, np.float32), axis), mask)
        for axis in (0, 1)
    )

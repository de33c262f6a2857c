"""Image similarity for 2D-3D registration: normalised cross-correlation (NCC) of high-pass
filtered images over a mask, and gradient NCC.

High-pass filtering (the image minus its Gaussian blur of a few mm) removes what the rigid
bone model cannot explain: soft-tissue and scatter backgrounds, beam hardening's slow trends.
NCC is 1 for identical images and unchanged by any affine change of intensity (a x + b, a > 0).
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.fft
from scipy.ndimage import correlate1d, sobel


def highpass(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """``image`` minus its Gaussian blur (sigma in pixels): scipy.ndimage's
    ``gaussian_filter(image, sigma_px, mode="nearest")`` to the bit, its two passes made with
    the kernel computed once per sigma (the registration filters thousands of small renders)."""
    image = np.asarray(image, dtype=np.float32)
    kernel = gaussian_kernel(float(sigma_px))
    blurred = correlate1d(image, kernel, 0, mode="nearest")
    correlate1d(blurred, kernel, 1, blurred, mode="nearest")
    return image - blurred


@functools.lru_cache(maxsize=64)
def gaussian_kernel(sigma_px: float) -> np.ndarray:
    """The sampled, normalised Gaussian of scipy.ndimage's filters, computed as they compute
    it: radius ``int(4 sigma + 0.5)`` pixels, ``sigma_px`` > 0; symmetric, read-only."""
    radius = int(4.0 * sigma_px + 0.5)
    x = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 / (sigma_px * sigma_px) * x**2)
    kernel = kernel / kernel.sum()
    kernel.flags.writeable = False
    return kernel


class BlurredHighpass:
    """``highpass(gaussian_filter(image, blur_px), sigma_px)`` of images of one shape, in one
    pass by FFT: the same sampled kernels as scipy's, the image taken as zero beyond its edges
    (as a render is that vanishes before the edges of its crop).

    Args:
        shape: (rows, cols) of the images filtered.
        blur_px: Gaussian sigma of the blur, pixels (0: none).
        sigma_px: Gaussian sigma of the high-pass, pixels (> 0).
    """

    def __init__(self, shape: tuple[int, int], blur_px: float, sigma_px: float) -> None:
        blur = gaussian_kernel(blur_px) if blur_px > 0 else np.ones(1)
        wide = gaussian_kernel(sigma_px)
        reach = len(blur) // 2 + len(wide) // 2  # the combined kernel's radius
        self.shape = shape
        self.size = tuple(scipy.fft.next_fast_len(n + reach, real=True) for n in shape)
        b_v, b_u = self._spectrum(blur, self.size[0], True), self._spectrum(blur, self.size[1])
        h_v, h_u = self._spectrum(wide, self.size[0], True), self._spectrum(wide, self.size[1])
        self.gain = (np.outer(b_v, b_u) * (1.0 - np.outer(h_v, h_u))).astype(np.complex64)

    @staticmethod
    def _spectrum(kernel: np.ndarray, n: int, full: bool = False) -> np.ndarray:
        """The DFT (length ``n``; half of it unless ``full``) of ``kernel`` centred on 0."""
        wrapped = np.zeros(n)
        radius = len(kernel) // 2
        wrapped[np.arange(-radius, radius + 1) % n] = kernel
        return np.fft.fft(wrapped) if full else np.fft.rfft(wrapped)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The filtered ``image`` (rows, cols as :attr:`shape`), float32."""
        spectrum = scipy.fft.rfft2(np.asarray(image, dtype=np.float32), s=self.size)
        out = scipy.fft.irfft2(spectrum * self.gain, s=self.size)
        return out[: self.shape[0], : self.shape[1]]


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

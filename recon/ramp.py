"""FDK's filtering of a batch of projections: weights, the ramp along rows, pixel quads out.

One pass of a numba kernel weights every pixel (the cosine of its ray's angle to the detector
normal, a per-view scale, optional per-column weights such as Parker's) and packs two rows
into one zero-padded complex row; complex FFTs filter both at once, since the ramp kernel is
real and even, so its response is real and ``filter(a + i b) = filter(a) + i filter(b)``
exactly; a second pass unpacks the rows, multiplies them by a per-pixel weight (the detector
edge taper) and lays them out as :func:`recon.project.pixel_quads` for the backprojector. All
of it runs on the calling thread's numba threads (``numba.get_num_threads()``, every core
unless the caller set fewer): the whole filtering costs about a fifth of the backprojection.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import scipy.fft

from recon.project import quads_kernel


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy", nogil=True)
def _pack_kernel(images, panels, scale, columns, out):  # pragma: no cover
    """out[k, j] (complex rows as interleaved float32) = weighted rows 2j (real parts) and
    2j + 1 (imaginary parts), zero past the panel's columns and its last row; ``panels[k]`` =
    (sdd, u0, v0, pitch_u, pitch_v)."""
    n, rows, cols = images.shape
    half, width = out.shape[1], out.shape[2]
    for job in numba.prange(n * half):
        k = job // half
        j = job - k * half
        d, u0, v0, pu, pv = panels[k, 0], panels[k, 1], panels[k, 2], panels[k, 3], panels[k, 4]
        col = columns[min(k, columns.shape[0] - 1)]
        row_out = out[k, j]
        for part in range(2):
            r = 2 * j + part
            if r >= rows:
                for c in range(cols):
                    row_out[2 * c + part] = 0.0
                continue
            dv = (r - v0) * pv
            base = d * d + dv * dv
            image = images[k, r]
            for c in range(cols):
                du = (c - u0) * pu
                cosine = np.float32(d / np.sqrt(base + du * du))
                row_out[2 * c + part] = image[c] * cosine * scale[k] * col[c]
        for c in range(2 * cols, width):
            row_out[c] = 0.0


class RowFilter:
    """Weighting, ramp filtering along rows and pixel quads for batches of projections whose
    rows hold ``cols`` pixels.

    Args:
        cols: pixels per row.
        response: the ramp's frequency response at the rfft bins of the zero-padded row
            length ``2 * (len(response) - 1)`` (:func:`recon.fdk.ramp_filter_response`).
    """

    def __init__(self, cols: int, response: np.ndarray) -> None:
        n_fft = 2 * (len(response) - 1)
        if n_fft < 2 * cols - 1:
            raise ValueError(f"a ramp of {n_fft} bins wraps around on rows of {cols} pixels")
        self.cols, self.n_fft = cols, n_fft
        response = np.real(np.asarray(response)).astype(np.float32)
        # the real, even response at every bin of the complex FFT
        self._response = np.concatenate((response, response[-2:0:-1]))
        # buffers reused from batch to batch (a fresh 40 MB array costs its page faults)
        self._buffers: dict[str, np.ndarray] = {}

    def _buffer(self, name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
        size = math.prod(shape)
        flat = self._buffers.get(name)
        if flat is None or flat.size < size:
            flat = self._buffers[name] = np.empty(size, dtype=dtype)
        return flat[:size].reshape(shape)

    def __call__(
        self,
        images: np.ndarray,
        panels: np.ndarray,
        scale: np.ndarray,
        support: np.ndarray,
        columns: np.ndarray | None = None,
    ) -> np.ndarray:
        """Filtered ``images`` laid out as pixel quads, float32 (n, rows, cols, 4), in a buffer
        that the next call reuses.

        Args:
            images: float32 (n, rows, cols) projections (any number of rows).
            panels: (n, 5) per view: source-detector distance (mm), principal point u, v
                (pixels) and pixel pitches along u, v (mm), for the cosine weights.
            scale: (n,) per-view factors, applied before the filter.
            support: (n or 1, rows, cols) per-pixel factors, applied after it.
            columns: optional (n or 1, cols) per-column factors, applied before it.
        """
        n, rows, cols = images.shape
        if cols != self.cols:
            raise ValueError(f"images {images.shape} for rows of {self.cols} pixels")
        packed = self._buffer("packed", (n, (rows + 1) // 2, self.n_fft), np.complex64)
        _pack_kernel(
            np.ascontiguousarray(images, dtype=np.float32),
            np.asarray(panels, dtype=np.float64),
            np.asarray(scale, dtype=np.float32),
            np.ones((1, self.cols), np.float32)
            if columns is None
            else np.ascontiguousarray(columns, dtype=np.float32),
            packed.view(np.float32),
        )
        workers = numba.get_num_threads()  # the caller's share of the cores, as the kernels
        spectrum = scipy.fft.fft(packed, axis=2, overwrite_x=True, workers=workers)
        spectrum *= self._response
        filtered = scipy.fft.ifft(spectrum, axis=2, overwrite_x=True, workers=workers)
        out = self._buffer("quads", (n, rows, cols, 4), np.float32)
        support = np.ascontiguousarray(support, dtype=np.float32)
        quads_kernel(filtered.view(np.float32), support, out, True)
        return out

"""The fluoroscopy frames as the similarity sees them: extended beyond the exposed field,
blurred to the renders' resolution, binned to a pyramid level and high-passed, once each."""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import binary_dilation, gaussian_filter

from recon.geometry import View
from registration.frames import blocks
from registration.similarity import highpass, turned_gaussian


class Targets:
    """The frames' high-passed targets by frame, pyramid level and blur, kept for the frame
    being registered.

    Args:
        view: the fluoroscopy view at full resolution.
        frames: line integrals (F, rows, cols), float32.
        field: bool (rows, cols), the pixels the beam reaches, or None for every pixel.
        views: the view binned to each pyramid level, by binning factor.
        highpass_mm: the high-pass Gaussian's sigma at the panel, mm.
    """

    def __init__(
        self,
        view: View,
        frames: np.ndarray,
        field: np.ndarray | None,
        views: dict[int, View],
        highpass_mm: float,
    ) -> None:
        self.view, self.frames, self.field = view, frames, field
        self.views, self.highpass_mm = views, highpass_mm
        self._targets: dict[tuple[int, int, tuple[float, float], int], np.ndarray] = {}
        """High-passed frames by (frame, level, blur_mm, turn_deg) (:meth:`target`)."""
        self._blurred: dict[tuple[int, tuple[float, float], int], np.ndarray] = {}
        """The frames blurred, before binning, by (frame, blur_mm, turn_deg)."""
        self._outside: dict[int, np.ndarray] = {}
        """Per pyramid level: the pixels outside the exposed field (:meth:`outside_field`)."""
        self._extensions: dict[int, np.ndarray] = {}
        """The frame being registered, extended beyond the exposed field (:meth:`_extended`)."""

    def sigma_px(self, level: int) -> float:
        """The high-pass sigma in pixels of ``level``'s view."""
        return self.highpass_mm / self.views[level].pitch_u_mm

    def target(
        self, frame: int, level: int, blur_mm: tuple[float, float], turn_deg: int = 0
    ) -> np.ndarray:
        """The frame blurred by ``blur_mm`` (Gaussian sigmas along u, v at the panel, mm; the
        axes turned by ``turn_deg`` towards +v), binned to ``level``, high-passed."""
        if blur_mm[0] == blur_mm[1]:
            turn_deg = 0  # a round blur does not turn
        key = (frame, level, blur_mm, turn_deg)
        if key not in self._targets:
            blurred = key[:1] + key[2:]
            if blurred not in self._blurred:  # shared by the levels
                image = self._extended(frame)
                sigma_px = (blur_mm[0] / self.view.pitch_u_mm, blur_mm[1] / self.view.pitch_v_mm)
                if turn_deg:
                    image = turned_gaussian(image, sigma_px, math.radians(turn_deg))
                elif any(blur_mm):
                    image = gaussian_filter(image, sigma_px[::-1], mode="nearest")
                self._blurred[blurred] = image
            image = self._blurred[blurred]
            if level > 1:
                image = blocks(image, level).mean(axis=(1, 3))
            self._targets[key] = highpass(image, self.sigma_px(level))
        return self._targets[key]

    def keep_frame(self, frame: int) -> None:
        """Forget the targets of every other frame."""
        self._targets = {k: t for k, t in self._targets.items() if k[0] == frame}
        self._blurred = {k: b for k, b in self._blurred.items() if k[0] == frame}

    def keep_blurs(self, chosen: set[tuple[float, float]]) -> None:
        """Forget the targets of every blur but the ``chosen`` ones."""
        self._targets = {k: t for k, t in self._targets.items() if k[2] in chosen}
        self._blurred = {k: b for k, b in self._blurred.items() if k[1] in chosen}

    def outside_field(self, level: int) -> np.ndarray | None:
        """The pixels of ``level``'s view outside the exposed field, or within two high-pass
        sigmas of it (where the filtered frame still sees the field's edge); None: no field."""
        if self.field is None:
            return None
        if level not in self._outside:
            outside = blocks(~self.field, level).any(axis=(1, 3))
            band = math.ceil(2 * self.sigma_px(level))
            self._outside[level] = binary_dilation(outside, iterations=band)
        return self._outside[level]

    def _extended(self, frame: int) -> np.ndarray:
        """The frame, extended smoothly beyond the exposed field (no step at the field's edge
        for the filters), once per frame."""
        if self.field is None:
            return self.frames[frame]
        if frame not in self._extensions:
            self._extensions.clear()  # one frame at a time
            sigma = self.highpass_mm / self.view.pitch_u_mm
            self._extensions[frame] = _extend_into(self.frames[frame], self.field, sigma)
        return self._extensions[frame]


def _extend_into(image: np.ndarray, field: np.ndarray, sigma_px: float) -> np.ndarray:
    """``image`` with the pixels outside ``field`` replaced by a smooth extension of those
    inside (normalised convolution: Gaussian-weighted means of the field's pixels, sigma
    ``2 sigma_px``; the field's mean where none is near)."""
    weight = field.astype(np.float32)
    sigma = 2.0 * sigma_px
    num = gaussian_filter(np.where(field, image, 0.0).astype(np.float32), sigma, mode="nearest")
    den = gaussian_filter(weight, sigma, mode="nearest")
    fill = np.full_like(num, float(image[field].mean()))
    np.divide(num, den, out=fill, where=den > 1e-3)
    return np.where(field, image, fill).astype(np.float32)

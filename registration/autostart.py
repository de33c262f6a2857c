"""An automatic start for implant components on the first frame, where no start is given.

A metal component is a near-opaque shadow with the component's outline. On the frame binned to
:data:`BIN_MM` pixels, the component's silhouette is rendered at every orientation of a grid
(:data:`DIRECTIONS` directions of its axes brought to world z, each turned about z in steps of
:data:`TURN_DEG`: all of its orientations) at a typical distance (:data:`DEPTH_FRACTION` of the
way to the panel) and matched to the frame by normalised cross-correlation over every position
in the image (FFT, and summed-area tables for the frame's sums under the box): the best
position of each orientation scores it. The best :data:`KEEP` orientations that differ by more
than :data:`DISTINCT_DEG` are the candidates, each placed where its silhouette fits; the
tracker then searches about each (differential evolution in twice its first-frame box) and
keeps the best (registration.tracker.Tracker.best_start).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.fft import irfft2, next_fast_len, rfft2
from scipy.spatial.transform import Rotation

from recon.geometry import View
from registration.frames import blocks
from registration.implants import ImplantModel

BIN_MM = 3.0
"""The search's pixel size: frames are binned to the nearest whole factor of it (8 x 8 for
JointTrack's 0.373 mm calibration, 2 x 2 for the demo's 1.2 mm fluoroscopy)."""
DIRECTIONS = 300
"""Viewing directions of the orientation grid (a Fibonacci sphere)."""
TURN_DEG = 15.0
"""Step of the turn in the image plane, deg."""
DEPTH_FRACTION = 0.9
"""Where along the focal spot-panel distance a component is placed: fluoroscopy images the
knee close to the panel."""
LEAST_CONTRAST = 0.2
"""Least contrast of a match, as a share of the field's range (its 1st to 99th percentile):
metal against soft tissue is about 0.4 of it."""
KEEP = 6
"""Candidates kept per component."""
DISTINCT_DEG = 20.0
"""Least rotation between two candidates, deg."""


def _sphere(n: int) -> np.ndarray:
    """``n`` directions spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / n)
    azimuth = np.pi * (1.0 + 5.0**0.5) * i
    return np.column_stack(
        (np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar))
    )


def binning(view: View) -> int:
    """The binning factor that brings the view's pixels nearest :data:`BIN_MM`."""
    return max(1, round(BIN_MM / view.pitch_u_mm))


def binned_frame(
    frame: np.ndarray, field: np.ndarray | None, factor: int
) -> tuple[np.ndarray, np.ndarray]:
    """A frame (its attenuation stand-in, registration.frames) binned, the pixels outside the
    exposed field set to the field's median; and the binned pixels wholly inside the field."""
    image = blocks(frame, factor).mean(axis=(1, 3)).astype(np.float64)
    inside = np.ones(image.shape, dtype=bool)
    if field is not None:
        inside = blocks(field, factor).all(axis=(1, 3))
        image[~inside] = np.median(image[inside])
    return image, inside


class Matcher:
    """Silhouettes matched to one binned frame at every position: the frame's sums and sums
    of squares under a box from summed-area tables, its correlation with the silhouette and
    with its unexposed part by FFT (spectra computed once; the frame zero-padded by the
    largest box, ``reach`` pixels, so that no match wraps around)."""

    def __init__(self, image: np.ndarray, inside: np.ndarray, reach: int) -> None:
        self.shape = image.shape
        self.reach = reach
        self.padded = tuple(next_fast_len(n + reach, real=True) for n in image.shape)
        low, high = np.percentile(image[inside], [1.0, 99.0])
        self.least_contrast = LEAST_CONTRAST * float(high - low)
        self.tables = [_summed_area(a) for a in (image, image * image)]
        self.spectra = [rfft2(a, self.padded) for a in (image, (~inside).astype(np.float64))]

    def _correlate(self, spectrum: np.ndarray, box_spectrum: np.ndarray, anchor) -> np.ndarray:
        """``sum_q a[p - anchor + q] box[q]`` at every pixel ``p`` of the frame."""
        full = irfft2(spectrum * np.conj(box_spectrum), self.padded)
        rows = (np.arange(self.shape[0]) - anchor[0]) % self.padded[0]
        cols = (np.arange(self.shape[1]) - anchor[1]) % self.padded[1]
        return full[np.ix_(rows, cols)]

    def _box_sums(self, table: np.ndarray, box: tuple[int, int], anchor) -> np.ndarray:
        """``sum_q a[p - anchor + q]`` over a box of shape ``box`` at every pixel ``p`` (zero
        outside the frame), from ``a``'s summed-area table (:func:`_summed_area`)."""
        (n0, n1), (h, w) = self.shape, box
        r0, c0 = n0 - anchor[0], n1 - anchor[1]  # the table's margin is the frame's size
        r1, c1 = r0 + h, c0 + w
        return (
            table[r1 : r1 + n0, c1 : c1 + n1]
            - table[r0 : r0 + n0, c1 : c1 + n1]
            - table[r1 : r1 + n0, c0 : c0 + n1]
            + table[r0 : r0 + n0, c0 : c0 + n1]
        )

    def match(self, box: np.ndarray) -> np.ndarray:
        """How well ``box`` (a silhouette, bool) matches the frame with its pixel
        ``(h // 2, w // 2)`` at each pixel: the normalised cross-correlation (-1..1); -inf
        where the box leaves the exposed field or where the contrast (the mean inside the
        silhouette less the mean around it in the box) is below :data:`LEAST_CONTRAST` of the
        field's range: noise alone correlates with a shape now and then, but has no
        contrast."""
        if max(box.shape) > self.reach:
            raise ValueError(f"a silhouette of {box.shape} pixels beyond the reach {self.reach}")
        anchor = (box.shape[0] // 2, box.shape[1] // 2)
        n, share = box.size, float(box.mean())
        energy = n * share * (1.0 - share)  # sum of (box - share)^2
        if energy == 0.0:  # a silhouette filling its box: no shape to match
            return np.full(self.shape, -np.inf)
        shape = rfft2(box.astype(np.float64), self.padded)
        (image, outside), (sums_table, squares_table) = self.spectra, self.tables
        sums = self._box_sums(sums_table, box.shape, anchor)
        spread = self._box_sums(squares_table, box.shape, anchor) - sums * sums / n
        covariance = self._correlate(image, shape, anchor) - share * sums
        fit = covariance / np.sqrt(np.maximum(spread, 1e-12) * energy)
        fit[covariance / energy < self.least_contrast] = -np.inf
        fit[self._correlate(outside, shape, anchor) > 0.5] = -np.inf
        return fit


def _summed_area(a: np.ndarray) -> np.ndarray:
    """The summed-area table of ``a`` zero-padded by its own size on every side: entry
    ``[i, j]`` is the sum of the padded array's ``[:i, :j]`` (a box no larger than ``a`` then
    reads it without clipping)."""
    padded = np.pad(a, [(n, n) for n in a.shape])
    table = np.zeros((padded.shape[0] + 1, padded.shape[1] + 1))
    table[1:, 1:] = padded.cumsum(axis=0).cumsum(axis=1)
    return table


def candidate_poses(
    model: ImplantModel,
    view: View,
    frame: np.ndarray,
    field: np.ndarray | None,
    near: tuple[np.ndarray, float] | None = None,
    placed: list[tuple[ImplantModel, np.ndarray]] = (),
) -> list[np.ndarray]:
    """Up to :data:`KEEP` starting poses ``T_world_body`` of a component on ``frame``, best
    first (see the module docstring); ``near``: (a world point, a distance in mm): only where
    the component's centre projects within that distance of the point's projection (the
    components of one knee lie close together; dark things elsewhere, a platform's bars, are
    not it); ``placed``: components already placed (model, pose), whose shadows are taken out
    of the frame (the metal they explain is theirs)."""
    factor = binning(view)
    coarse = view.binned(factor)
    image, inside = binned_frame(frame, field, factor)
    background = float(np.median(image))
    for other, T_other in placed:
        image[other.silhouette(coarse, T_other, outline=True)] = background
    centre = coarse.source_mm + DEPTH_FRACTION * (coarse.detector_center_mm - coarse.source_mm)
    depth = float(coarse.depth(centre)[0])  # every grid pose puts the body's centroid there
    body_centre = model.centroid_mm
    radius = float(np.linalg.norm(model.vertices_mm - body_centre, axis=1).max())
    nearest = depth - radius / coarse.sdd_mm  # its nearest point to the source, magnified most
    pitch = min(coarse.pitch_u_mm, coarse.pitch_v_mm)
    matcher = Matcher(image, inside, math.ceil(2.0 * radius / (nearest * pitch)) + 2)
    allowed = np.ones_like(image, dtype=bool)
    if near is not None:
        point, radius_mm = near
        u, v = coarse.project(point)[0]
        radius_px = radius_mm / (coarse.pitch_u_mm * float(coarse.depth(point)[0]))
        rows, cols = np.indices(image.shape)
        allowed = np.hypot(rows - v, cols - u) <= radius_px
    step_u, step_v = depth * coarse.pitch_u_mm * coarse.e_u, depth * coarse.pitch_v_mm * coarse.e_v
    scored = []
    for direction in _sphere(DIRECTIONS):
        facing = Rotation.align_vectors([[0.0, 0.0, 1.0]], [direction])[0]
        for turn in np.arange(0.0, 360.0, TURN_DEG):
            R = (Rotation.from_rotvec([0.0, 0.0, np.radians(turn)]) * facing).as_matrix()
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = centre - R @ body_centre
            silhouette = model.silhouette(coarse, T, outline=True)
            if silhouette.sum() < 4:
                continue
            rows, cols = np.nonzero(silhouette)
            box = silhouette[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1]
            fit = matcher.match(box)
            fit[~allowed] = -np.inf
            best = int(np.argmax(fit))
            if not np.isfinite(fit.flat[best]):
                continue
            where = np.unravel_index(best, fit.shape)
            anchor = (rows.min() + box.shape[0] // 2, cols.min() + box.shape[1] // 2)
            shift = np.array(where, dtype=float) - anchor
            scored.append((fit.flat[best], T, shift))
    scored.sort(key=lambda item: -item[0])
    kept: list[np.ndarray] = []
    rotations: list[Rotation] = []
    for _, T, (dv, du) in scored:
        turn = Rotation.from_matrix(T[:3, :3])
        if any((turn * r.inv()).magnitude() < np.radians(DISTINCT_DEG) for r in rotations):
            continue
        start = T.copy()  # moved sideways so that its silhouette lands where it fits
        start[:3, 3] += du * step_u + dv * step_v
        kept.append(start)
        rotations.append(turn)
        if len(kept) == KEEP:
            break
    return kept

"""Weighted FDK for arbitrary cone-beam trajectories (circular, short scan, helix, reverse spiral).

The classic FDK steps on per-view projection matrices:

1. cosine weighting of each pixel (angle between its ray and the detector normal) and, for a
   short scan, Parker-like smooth redundancy weights along the fan;
2. ramp filtering along the orbit's direction of motion as seen on the panel, with zero
   padding and a window (Ram-Lak, Shepp-Logan, cosine, Hann): along detector rows for panels
   held upright, after resampling onto a virtual panel whose rows run that way for panels
   turned in their plane (recon.turned_panel);
3. voxel-driven backprojection through P with the distance weight ``1 / w^2``.

Uneven sampling (short scans, helices whose ends see fewer views, reverse-spiral passes) is
handled by normalising every voxel with the weighted count of the views that saw it
(docs/system.md's "projection-weight normalisation"): each view contributes its angular step
``dbeta`` times the Jacobian ``SOD * U / L_perp^2`` (``U`` depth, ``L_perp`` the source distance
across the rotation axis), which integrates to ``2*pi`` for a voxel seen over a full turn and
``pi`` over a Parker-weighted short scan. The volume is ``pi * sum(views) / count``; where
all views see a voxel it equals classic FDK. Detector edges fade in over ``edge_taper_px``
pixels so the count is smooth, and voxels whose count falls below ``min_coverage_deg`` are
masked (set to 0 and flagged), not invented.

The rotation axis, isocentre, source-to-axis distances and view angles are read off the
geometry itself: the axis is the direction the detector normals avoid (oriented along the panel
axis nearest it), the isocentre the centre of the circle through the sources.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numba
import numpy as np
import scipy.fft

from recon.geometry import Geometry
from recon.motion import BodyMotion, backproject_field
from recon.project import (
    COUNT_WEIGHT,
    FDK_WEIGHT,
    backproject_weighted,
    check_in_front,
    pixel_quads,
)
from recon.ramp import RowFilter
from recon.turned_panel import AlignedPanels, align_to_motion
from recon.volume import Volume, VolumeGrid

Window = Literal["ram-lak", "shepp-logan", "cosine", "hann"]
Redundancy = Literal["auto", "parker", "none"]
Progress = Callable[[int, int], None]
"""Called as ``progress(views_done, views_total)`` after every batch."""

WINDOWS: tuple[str, ...] = ("ram-lak", "shepp-logan", "cosine", "hann")


@dataclass(frozen=True)
class Orbit:
    """What FDK needs to know about a trajectory, estimated from its views.

    Attributes:
        axis: unit rotation axis (world), oriented along the mean detector e_v (along the
            mean e_u for panels turned a quarter, whose e_v lies across it).
        isocenter_mm: a point on the axis (centre of the circle through the sources).
        sod_mm: per-view source distance from the axis, (N,).
        beta_rad: per-view unwrapped angle about the axis, (N,).
        dbeta_rad: per-view angular weight (trapezoid rule within each pass), (N,).
        passes: (start, stop) view-index ranges of monotonic sweeps.
        closed: True when a single pass covers a whole turn.
    """

    axis: np.ndarray
    isocenter_mm: np.ndarray
    sod_mm: np.ndarray
    beta_rad: np.ndarray
    dbeta_rad: np.ndarray
    passes: tuple[tuple[int, int], ...]
    closed: bool

    @property
    def span_deg(self) -> float:
        """Largest angular range swept by one pass, degrees."""
        return max(
            math.degrees(abs(self.beta_rad[b - 1] - self.beta_rad[a])) for a, b in self.passes
        )


def plane_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit ``axis`` to a right-handed orthonormal frame."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    b1 = np.cross(axis, helper)
    b1 /= np.linalg.norm(b1)
    return b1, np.cross(axis, b1)


def _passes(beta: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index ranges of maximal monotonic sweeps; a still view starts a new one."""
    passes, start, direction = [], 0, 0.0
    for i in range(1, len(beta)):
        step = np.sign(beta[i] - beta[i - 1])
        if i - start == 1 and direction == 0.0 and step != 0.0:
            direction = step
        elif step != direction:
            passes.append((start, i))
            start, direction = i, 0.0
    passes.append((start, len(beta)))
    return passes


def estimate_orbit(geometry: Geometry) -> Orbit:
    """Rotation axis, isocentre, per-view SOD, angles and angular weights of a trajectory."""
    if len(geometry) < 3:
        raise ValueError(f"FDK needs an orbit of at least 3 views, got {len(geometry)}")
    normals = np.stack([v.normal for v in geometry])
    _, vecs = np.linalg.eigh(normals.T @ normals)
    axis = vecs[:, 0]
    mean_axes = [np.mean([getattr(v, e) for v in geometry], axis=0) @ axis for e in ("e_v", "e_u")]
    if mean_axes[int(abs(mean_axes[1]) > abs(mean_axes[0]))] < 0:
        axis = -axis
    b1, b2 = plane_basis(axis)
    src = np.asarray(geometry.sources_mm)
    xy = np.column_stack((src @ b1, src @ b2))
    # algebraic circle fit: x^2 + y^2 = 2 c.x + k
    A = np.column_stack((2 * xy, np.ones(len(xy))))
    sol, *_ = np.linalg.lstsq(A, (xy**2).sum(axis=1), rcond=None)
    center_xy = sol[:2]
    sod = np.linalg.norm(xy - center_xy, axis=1)
    if not np.all(np.isfinite(sod)) or sod.min() <= 0 or np.ptp(sod) > 0.5 * sod.mean():
        raise ValueError(
            "the sources do not lie on a circle about a common axis: FDK needs an orbit "
            f"(source-to-axis distances {sod.min():.1f}..{sod.max():.1f} mm)"
        )
    along = float(np.mean(src @ axis))
    isocenter = center_xy[0] * b1 + center_xy[1] * b2 + along * axis
    beta = np.unwrap(np.arctan2(xy[:, 1] - center_xy[1], xy[:, 0] - center_xy[0]))
    steps = np.diff(beta)
    if np.any(np.abs(steps) > math.radians(45)):
        raise ValueError("consecutive views are more than 45 degrees apart: not an orbit")
    passes = _passes(beta)
    dbeta = np.zeros(len(beta))
    closed = False
    for a, b in passes:
        seg = beta[a:b]
        if len(seg) < 2:
            continue
        span = abs(seg[-1] - seg[0])
        step = span / (len(seg) - 1)
        d = np.abs(np.gradient(seg))
        if len(passes) == 1 and abs(span + step - 2 * math.pi) < 0.02 * step:
            closed = True  # a whole turn without a repeated end view: periodic sampling
        else:
            d[0], d[-1] = 0.5 * abs(seg[1] - seg[0]), 0.5 * abs(seg[-1] - seg[-2])
        dbeta[a:b] = d
    return Orbit(axis, isocenter, sod, beta, dbeta, tuple(passes), closed)


def ramp_filter_response(n_fft: int, pitch_mm: float, window: Window, cutoff: float) -> np.ndarray:
    """Frequency response (rfft bins) of the band-limited ramp times ``window``.

    Built from the spatial Ram-Lak kernel (Kak & Slaney eq. 61) so that the zero-padded
    discrete convolution is exact; ``cutoff`` in (0, 1] is the window's edge as a fraction of
    the Nyquist frequency. Units: the filtered projection is in 1/mm.
    """
    if window not in WINDOWS:
        raise ValueError(f"filter window must be one of {WINDOWS}, got {window!r}")
    if not 0.0 < cutoff <= 1.0:
        raise ValueError(f"cutoff must be in (0, 1] of Nyquist, got {cutoff!r}")
    n = np.arange(n_fft)
    n = np.minimum(n, n_fft - n)  # symmetric kernel wrapped for circular convolution
    h = np.zeros(n_fft)
    h[0] = 1.0 / (4.0 * pitch_mm**2)
    odd = n % 2 == 1
    h[odd] = -1.0 / (np.pi * n[odd] * pitch_mm) ** 2
    response = np.real(np.fft.rfft(h)) * pitch_mm
    f = np.fft.rfftfreq(n_fft)  # cycles per pixel, 0..0.5
    x = f / (0.5 * cutoff)
    if window == "shepp-logan":
        response *= np.sinc(x / 2.0)
    elif window == "cosine":
        response *= np.cos(np.pi * x / 2.0)
    elif window == "hann":
        response *= 0.5 * (1.0 + np.cos(np.pi * x))
    response[x > 1.0] = 0.0
    return response


def _taper(n: int, width: float) -> np.ndarray:
    """1 in the middle, a raised-cosine fade to 0 over ``width`` pixels at both ends."""
    idx = np.arange(n, dtype=np.float64)
    edge = np.minimum(idx, n - 1 - idx) + 0.5
    if width <= 0:
        return np.ones(n)
    t = np.clip(edge / width, 0.0, 1.0)
    return np.sin(0.5 * np.pi * t) ** 2


def parker_weights(geometry: Geometry, orbit: Orbit) -> np.ndarray:
    """Parker short-scan weights per view and detector column, (N, cols).

    Fan angles are measured at the principal row, about the rotation axis, in the sense of the
    sweep; the overscan ``delta = (span - 180 deg) / 2`` must cover the fan.
    """
    if len(orbit.passes) != 1:
        raise ValueError(f"Parker weights need a single pass, the orbit has {len(orbit.passes)}")
    ((a, b),) = orbit.passes
    sweep = np.sign(orbit.beta_rad[b - 1] - orbit.beta_rad[a])
    beta = sweep * (orbit.beta_rad - orbit.beta_rad[a])
    span = beta[b - 1]
    delta = 0.5 * (span - np.pi)
    b1, b2 = plane_basis(orbit.axis)
    out = np.empty((len(geometry), geometry.cols))
    cols = np.arange(geometry.cols, dtype=np.float64)
    gamma_max = 0.0
    for i, view in enumerate(geometry):
        _, vp = view.principal_point_px
        rays = view.pixel_to_world(cols, np.full_like(cols, vp)) - view.source_mm
        central = orbit.isocenter_mm - view.source_mm
        ang_rays = np.arctan2(rays @ b2, rays @ b1)
        ang_c = math.atan2(central @ b2, central @ b1)
        gamma = sweep * np.angle(np.exp(1j * (ang_rays - ang_c)))
        gamma_max = max(gamma_max, float(np.abs(gamma).max()))
        bt = beta[i]
        w = np.ones_like(gamma)
        rise = bt < 2 * delta - 2 * gamma
        fall = bt > np.pi - 2 * gamma
        with np.errstate(divide="ignore", invalid="ignore"):
            w[rise] = np.sin(0.25 * np.pi * bt / (delta - gamma[rise])) ** 2
            w[fall] = np.sin(0.25 * np.pi * (np.pi + 2 * delta - bt) / (delta + gamma[fall])) ** 2
        out[i] = np.nan_to_num(np.clip(w, 0.0, 1.0))
    if delta < gamma_max - 1e-3:
        raise ValueError(
            f"short scan of {math.degrees(span):.1f} deg is shorter than 180 deg plus the fan "
            f"({180 + 2 * math.degrees(gamma_max):.1f} deg): data are incomplete"
        )
    return out


@dataclass(frozen=True)
class FDKResult:
    """Reconstruction, the views' weighted count per voxel and the mask of trusted voxels.

    Attributes:
        volume: linear attenuation (1/mm) on the requested grid; masked voxels are 0.
        mask: bool [z, y, x], True where coverage >= the requested minimum.
        orbit: the trajectory as FDK read it.
        count_deg: float32 [z, y, x], the views' weighted count (degrees) on ``count_grid``,
            a coarser grid over the same extent, which :attr:`coverage_deg` interpolates.
        count_grid: the grid of ``count_deg``.
    """

    volume: Volume
    mask: np.ndarray
    orbit: Orbit
    count_deg: np.ndarray
    count_grid: VolumeGrid

    @cached_property
    def coverage_deg(self) -> np.ndarray:
        """float32 [z, y, x], redundancy-weighted angular coverage in degrees (360 for a voxel
        seen over a full turn, ~180 for a complete short scan), computed when first asked."""
        coverage = np.empty(self.volume.grid.shape, dtype=np.float32)
        taps = _trilinear_taps(self.volume.grid, self.count_grid)
        _coverage_kernel(self.count_deg, *taps, coverage)
        return coverage


CORNER_FRACTION = 0.1
"""An axis projecting within this fraction of the panel's size from two adjacent edges at once
sits in a corner: what a stack origin that does not belong to its geometry produces (RTK's
default Origin (0, 0) under a geometry written for a centred panel puts it on pixel (0, 0)); an
offset (half-fan) panel is off centre along one axis only."""


def check_axis_on_panel(geometry: Geometry, where: str = "the geometry") -> None:
    """ValueError unless the orbit's rotation axis projects onto the panel, away from its
    corners (:data:`CORNER_FRACTION`), in every view (at each view's source height): FDK's data
    are complete nowhere else, and a panel placed so says that the projections' header (its
    origin) or the geometry is wrong. ``where`` names the inputs in the message."""
    orbit = estimate_orbit(geometry)
    for i, view in enumerate(geometry):
        height = (view.source_mm - orbit.isocenter_mm) @ orbit.axis
        u, v = view.project(orbit.isocenter_mm + height * orbit.axis)[0]
        off = not (-0.5 <= u <= view.cols - 0.5 and -0.5 <= v <= view.rows - 0.5)
        near_u = min(u, view.cols - 1 - u) < CORNER_FRACTION * view.cols
        near_v = min(v, view.rows - 1 - v) < CORNER_FRACTION * view.rows
        if off or (near_u and near_v):
            place = "off" if off else "in a corner of"
            raise ValueError(
                f"{where}: the orbit's rotation axis projects at pixel ({u:.1f}, {v:.1f}) in "
                f"view {i}, {place} the {view.cols} x {view.rows} panel; FDK needs it well "
                "inside. Does the projection stack's header (Origin, Spacing, Direction) "
                "belong to this geometry? (A stack written for a centred panel has Origin "
                f"({-0.5 * (view.cols - 1) * view.pitch_u_mm:g}, "
                f"{-0.5 * (view.rows - 1) * view.pitch_v_mm:g}) mm; RTK's default is (0, 0).)"
            )


def corner_pixels(geometry: Geometry, grid: VolumeGrid) -> tuple[np.ndarray, np.ndarray]:
    """Where the grid's eight outer corners project on each view's panel: (u, v), each
    (views, 8), in pixels (centres at whole numbers). The projection of the grid lies within
    that of its corners."""
    corners = np.hstack((grid.corners_mm(), np.ones((8, 1))))
    p = np.einsum("vrk,ck->vrc", geometry.matrices, corners)
    return p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]


def rows_seen(geometry: Geometry, grid: VolumeGrid) -> tuple[int, int]:
    """The panel rows ``r0 <= r < r1`` that hold every bilinear tap of the grid's voxels in
    every view (:func:`corner_pixels`); the whole panel's rows where a corner falls off it."""
    _, v = corner_pixels(geometry, grid)
    r0 = max(0, math.floor(v.min()) - 1)
    r1 = min(geometry.rows, math.floor(v.max()) + 3)
    return (r0, r1) if r1 - r0 >= 2 else (0, geometry.rows)


def _grid_seen(geometry: Geometry, grid: VolumeGrid) -> None:
    """ValueError unless some view's panel overlaps the grid's projection (its corners')."""
    u, v = corner_pixels(geometry, grid)
    seen = (u.max(axis=1) >= 0) & (v.max(axis=1) >= 0)
    seen &= (u.min(axis=1) <= geometry.cols - 1) & (v.min(axis=1) <= geometry.rows - 1)
    if not seen.any():
        raise ValueError("no view sees any part of the volume grid: check its origin and size")


class FDKAccumulator:
    """Weighted FDK built up a batch of views at a time, in any order: what
    :func:`fdk_reconstruct` runs, and what a scan runs while it acquires.

    The orbit (rotation axis, per-view angular weights, redundancy) is read once from
    ``geometry``, the views known before the first projection (a plan or a calibration); each
    batch may bring the matrices its views were actually taken at (``views`` in :meth:`add`),
    which place its rays. :meth:`result` is the volume of every view added so far. Views may
    come in any order and batches; the same batches in the same order give the same float32
    sums bit for bit (a scan that streams its views in :func:`fdk_reconstruct`'s batches gets
    the offline volume), other batches the same volume to float rounding.

    Args: see :func:`fdk_reconstruct`.
    """

    def __init__(
        self,
        geometry: Geometry,
        grid: VolumeGrid,
        *,
        window: Window = "hann",
        cutoff: float = 1.0,
        redundancy: Redundancy = "auto",
        min_coverage_deg: float = 170.0,
        edge_taper_px: float = 8.0,
        coverage_subsample: int = 4,
        motion: BodyMotion | None = None,
    ) -> None:
        if redundancy not in ("auto", "parker", "none"):
            raise ValueError(f"redundancy must be 'auto', 'parker' or 'none', got {redundancy!r}")
        check_in_front(geometry, grid)
        _grid_seen(geometry, grid)
        check_axis_on_panel(geometry)
        self.grid, self.min_coverage_deg = grid, min_coverage_deg
        self.n_views, self.rows, self.cols = len(geometry), geometry.rows, geometry.cols
        # the detector edge fades in over edge_taper_px on the real panel; off it, nothing counts
        rows_taper = _taper(geometry.rows, edge_taper_px).astype(np.float32)
        self._cols_taper = _taper(geometry.cols, edge_taper_px).astype(np.float32)
        self._taper = np.outer(rows_taper, self._cols_taper)
        self._taper_quads = pixel_quads(self._taper[None])
        self.aligned = motion_aligned(geometry)
        self.orbit = estimate_orbit(self.aligned.geometry)
        virtual = self.aligned.geometry
        n_fft = scipy.fft.next_fast_len(2 * virtual.cols)
        # per virtual pixel; an oversampled virtual panel keeps the real panel's band (cycles/mm)
        band = cutoff / self.aligned.oversample
        self._filter = RowFilter(virtual.cols, ramp_filter_response(n_fft, 1.0, window, band))
        use_parker = redundancy == "parker" or (
            redundancy == "auto"
            and len(self.orbit.passes) == 1
            and not self.orbit.closed
            and self.orbit.span_deg < 359.0
        )
        self._parker = parker_weights(virtual, self.orbit) if use_parker else None
        # a short scan's count: the rows' taper shared, the columns' times Parker's per view
        self._rows_taper_quads = (
            pixel_quads(np.repeat(rows_taper[None, :, None], geometry.cols, axis=2))
            if use_parker and not self.aligned.turned
            else None
        )
        self._coarse = _coarse_grid(grid, coverage_subsample)
        self._num = np.zeros(grid.shape, dtype=np.float32)
        self._count = np.zeros(self._coarse.shape, dtype=np.float32)
        self.added = np.zeros(self.n_views, dtype=bool)
        if motion is not None and len(motion) != self.n_views:
            raise ValueError(f"the motion has {len(motion)} views; the orbit has {self.n_views}")
        self.motion = motion
        self._weights = None if motion is None or len(motion.bodies) == 1 else motion.on(grid)

    def add(self, start: int, projections: np.ndarray, views: Geometry | None = None) -> None:
        """Weight, filter and backproject views ``start .. start + n - 1``.

        Args:
            start: index of the first view in the orbit's geometry.
            projections: float32 (n, rows, cols) line integrals.
            views: the n views as acquired (default: the orbit's own).
        """
        if self._num is None:
            raise RuntimeError("this FDK accumulator's result was taken: it takes no more views")
        proj = np.asarray(projections, dtype=np.float32)
        n = len(proj)
        if proj.ndim != 3 or proj.shape[1:] != (self.rows, self.cols):
            raise ValueError(
                f"projections have shape {proj.shape}; the geometry has views of "
                f"{self.rows} x {self.cols} pixels"
            )
        if start < 0 or start + n > self.n_views:
            raise ValueError(
                f"views {start}..{start + n - 1} outside the orbit's 0..{self.n_views - 1}"
            )
        again = np.flatnonzero(self.added[start : start + n]) + start
        if again.size:
            raise ValueError(f"view(s) {again[:10].tolist()} were added already")
        bad = [start + k for k, p in enumerate(proj) if not np.isfinite(p).all()]
        if bad:
            raise ValueError(f"projections contain NaN or infinite values in view(s) {bad[:10]}")
        if views is None:
            virtual, aligned, first = self.aligned.geometry[start : start + n], self.aligned, start
        else:
            if len(views) != n or (views.rows, views.cols) != (self.rows, self.cols):
                raise ValueError(
                    f"{len(views)} views of {views.rows} x {views.cols} pixels given for {n} "
                    f"projections of {self.rows} x {self.cols}"
                )
            check_in_front(views, self.grid)
            aligned, first = align_to_motion(views, self.orbit.axis), 0
            virtual = aligned.geometry
            if (virtual.rows, virtual.cols) != (
                self.aligned.geometry.rows,
                self.aligned.geometry.cols,
            ):
                raise ValueError("the views as acquired turn their panels unlike the orbit's")
        index = np.arange(start, start + n)
        orbit = self.orbit
        # FDK weight SOD / (SDD w^2) per view times dbeta; the ramp runs in pixel units,
        # 1 / pitch turns it into 1/mm. Per-view constants and the Parker weights (along u)
        # go before the filter; the edge taper after it, where it is a plain per-pixel view
        # weight that the views' weighted count carries as well
        # rows are filtered one by one: only those the grid projects onto are needed, on
        # panels cropped to them
        r0, r1 = rows_seen(virtual, self._coarse)  # the coarse grid holds the grid
        seen = Geometry([v.cropped(r0, 0, r1 - r0, v.cols) for v in virtual])
        panels = np.array(
            [(v.sdd_mm, *v.principal_point_px, v.pitch_u_mm, v.pitch_v_mm) for v in seen]
        )
        sdd, pitch = panels[:, 0], panels[:, 3]
        scale = orbit.dbeta_rad[index] * orbit.sod_mm[index] / (sdd * pitch)
        pre = None if self._parker is None else self._parker[index, None, :].astype(np.float32)
        support = (
            aligned.images(np.broadcast_to(self._taper, (n, *self._taper.shape)), first)
            if aligned.turned
            else self._taper[None]
        )
        # only the pixel quads stay alive during the backprojection
        quads = self._filter(
            aligned.images(proj, first)[:, r0:r1],
            panels,
            scale,
            support[:, r0:r1],
            None if pre is None else pre[:, 0],
        )
        if self.motion is None:
            backproject_weighted(quads, seen, self.grid, FDK_WEIGHT, self._num)
        elif self._weights is None:  # one rigid body: its views carried by inv(T), exactly
            carried = Geometry(
                [
                    v.transformed(np.linalg.inv(T[0]))
                    for v, T in zip(seen, self.motion.poses[index], strict=True)
                ]
            )
            backproject_weighted(quads, carried, self.grid, FDK_WEIGHT, self._num)
        else:
            poses = self.motion.poses[index]
            backproject_field(quads, seen, self.grid, poses, self._weights, self._num)
        del quads
        # the views' weighted count: dbeta * SOD * SDD * w / L_perp^2, in degrees
        jac = np.degrees(orbit.dbeta_rad[index]) * orbit.sod_mm[index] * sdd
        if aligned.turned:  # the taper turned with the panel: no longer a row times a column
            weights, columns = pixel_quads(support[:, r0:r1], pre), None
        elif pre is None:
            weights, columns = self._taper_quads[:, r0:r1], None
        else:
            weights, columns = self._rows_taper_quads[:, r0:r1], self._cols_taper * pre[:, 0]
        backproject_weighted(
            weights, seen, self._coarse, COUNT_WEIGHT, self._count, orbit.axis, jac, columns
        )
        self.added[start : start + n] = True

    def result(self) -> FDKResult:
        """The volume of the views added so far (all of them for a complete scan).

        The volume is normalised in the accumulator's own sum, so the accumulator is spent: a
        later :meth:`add` or :meth:`result` raises.
        """
        if self._num is None:
            raise RuntimeError("this FDK accumulator's result was taken already")
        volume, self._num = self._num, None
        mask = np.empty(self.grid.shape, dtype=bool)
        taps = _trilinear_taps(self.grid, self._coarse)
        _normalise_kernel(volume, self._count, *taps, np.float32(self.min_coverage_deg), mask)
        return FDKResult(
            Volume(volume, self.grid, "1/mm"), mask, self.orbit, self._count, self._coarse
        )


def fdk_reconstruct(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    *,
    window: Window = "hann",
    cutoff: float = 1.0,
    redundancy: Redundancy = "auto",
    min_coverage_deg: float = 170.0,
    edge_taper_px: float = 8.0,
    coverage_subsample: int = 4,
    batch_views: int = 16,
    orbit_geometry: Geometry | None = None,
    motion: BodyMotion | None = None,
    progress: Progress | None = None,
) -> FDKResult:
    """Reconstruct line-integral projections with weighted FDK.

    Args:
        projections: float32 (views, rows, cols), line integrals -ln(I/I0).
        geometry: one view per projection.
        grid: the output voxel grid (world mm).
        window: apodisation of the ramp filter.
        cutoff: window edge as a fraction of the Nyquist frequency, (0, 1].
        redundancy: "parker" for short scans, "none" for full turns and spirals, "auto"
            chooses Parker for a single pass shorter than a whole turn.
        min_coverage_deg: voxels with less weighted coverage are masked (set to 0).
        edge_taper_px: detector edge fade (pixels) that keeps the coverage smooth.
        coverage_subsample: the smooth coverage map is computed on a grid this many times
            coarser per axis and interpolated.
        batch_views: views filtered and backprojected together (bounds memory).
        orbit_geometry: the views whose orbit sets the angular weights and the redundancy
            (e.g. the plan of a scan whose ``geometry`` holds the views as recorded, so that
            the arms' tracking noise does not enter the weights); default ``geometry``.
        motion: the patient's motion to compensate (recon.motion): each view's rays meet
            each voxel where the motion field put it then; the views' weighted count stays
            the still one's (a few mm of motion do not change which views see a voxel).
        progress: optional callback ``progress(views_done, views_total)``.

    Returns:
        :class:`FDKResult` with the volume in 1/mm.
    """
    proj = np.asarray(projections)
    n_views = len(geometry)
    if proj.ndim != 3 or proj.shape != (n_views, geometry.rows, geometry.cols):
        raise ValueError(
            f"projections have shape {proj.shape}; the geometry has {n_views} views of "
            f"{geometry.rows} x {geometry.cols} pixels"
        )
    if orbit_geometry is not None and (
        len(orbit_geometry) != n_views
        or (orbit_geometry.rows, orbit_geometry.cols) != (geometry.rows, geometry.cols)
    ):
        raise ValueError(
            f"the orbit's geometry has {len(orbit_geometry)} views of {orbit_geometry.rows} x "
            f"{orbit_geometry.cols} pixels; the projections' {n_views} of {geometry.rows} x "
            f"{geometry.cols}"
        )
    accumulator = FDKAccumulator(
        geometry if orbit_geometry is None else orbit_geometry,
        grid,
        window=window,
        cutoff=cutoff,
        redundancy=redundancy,
        min_coverage_deg=min_coverage_deg,
        edge_taper_px=edge_taper_px,
        coverage_subsample=coverage_subsample,
        motion=motion,
    )
    for start in range(0, n_views, batch_views):
        stop = min(start + batch_views, n_views)
        views = None if orbit_geometry is None else geometry[start:stop]
        accumulator.add(start, proj[start:stop], views)
        if progress is not None:
            progress(stop, n_views)
    return accumulator.result()


def motion_aligned(geometry: Geometry) -> AlignedPanels:
    """The views on virtual panels whose rows run along the orbit's motion (recon.turned_panel;
    upright panels come back as they are)."""
    return align_to_motion(geometry, estimate_orbit(geometry).axis)


def _coarse_grid(grid: VolumeGrid, subsample: int) -> VolumeGrid:
    """A grid ``subsample`` times coarser per axis over the same extent (same origin)."""
    sub = max(1, int(subsample))
    return VolumeGrid(
        shape=tuple(max(2, math.ceil((n - 1) / sub) + 1) for n in grid.shape),
        spacing_mm=tuple(s * sub for s in grid.spacing_mm),
        origin_mm=grid.origin_mm,
    )


def _linear_taps(grid: VolumeGrid, coarse: VolumeGrid, axis: int) -> tuple[np.ndarray, ...]:
    """Along array ``axis`` (0 = z) of ``grid``: the lower coarse index (int64) and the weight
    of the upper one (float32) of each voxel's linear interpolation on ``coarse`` (same
    origin), held within the coarse grid."""
    ratio = grid.spacing_mm[2 - axis] / coarse.spacing_mm[2 - axis]
    position = np.arange(grid.shape[axis]) * ratio
    lower = np.minimum(np.floor(position).astype(np.int64), coarse.shape[axis] - 2)
    return lower, np.clip(position - lower, 0.0, 1.0).astype(np.float32)


def _trilinear_taps(grid: VolumeGrid, coarse: VolumeGrid) -> list[np.ndarray]:
    """:func:`_linear_taps` along z, y and x, in that order."""
    return [t for axis in range(3) for t in _linear_taps(grid, coarse, axis)]


@numba.njit(fastmath=True, error_model="numpy", boundscheck=False, inline="always")
def _coverage_row(count, a, wz, b, wy, x0, fx, row, out):  # pragma: no cover
    """out[x] = the trilinear interpolation of the coarse ``count`` at one voxel row: the
    coarse row at (a + wz, b + wy) into ``row`` first, then along x."""
    for c in range(count.shape[2]):
        lo = count[a, b, c] + wy * (count[a, b + 1, c] - count[a, b, c])
        hi = count[a + 1, b, c] + wy * (count[a + 1, b + 1, c] - count[a + 1, b, c])
        row[c] = lo + wz * (hi - lo)
    for x in range(len(out)):
        c = x0[x]
        out[x] = row[c] + fx[x] * (row[c + 1] - row[c])


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy", nogil=True)
def _coverage_kernel(count, z0, fz, y0, fy, x0, fx, coverage):  # pragma: no cover
    """coverage = the trilinear interpolation of the coarse ``count`` (degrees)."""
    nz, ny, _ = coverage.shape
    for job in numba.prange(nz * ny):
        z = job // ny
        y = job - z * ny
        row = np.empty(count.shape[2], dtype=np.float32)
        _coverage_row(count, z0[z], fz[z], y0[y], fy[y], x0, fx, row, coverage[z, y])


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy", nogil=True)
def _normalise_kernel(
    volume, count, z0, fz, y0, fy, x0, fx, min_coverage, mask
):  # pragma: no cover
    """In place: volume = 180 * volume / coverage (pi * sum / count, the count in degrees)
    where the coverage (the coarse ``count`` interpolated) >= min_coverage (and > 0), else 0;
    ``mask`` where coverage >= min_coverage."""
    nz, ny, nx = volume.shape
    for job in numba.prange(nz * ny):
        z = job // ny
        y = job - z * ny
        row = np.empty(count.shape[2], dtype=np.float32)
        cover = np.empty(nx, dtype=np.float32)
        _coverage_row(count, z0[z], fz[z], y0[y], fy[y], x0, fx, row, cover)
        for x in range(nx):
            inside = cover[x] >= min_coverage
            mask[z, y, x] = inside
            ok = inside and cover[x] > 0
            volume[z, y, x] = np.float32(180.0) * volume[z, y, x] / cover[x] if ok else 0


def default_grid(
    geometry: Geometry,
    spacing_mm: float | None = None,
    size_xyz: tuple[int, int, int] | None = None,
    max_size: int = 512,
) -> VolumeGrid:
    """A grid over the orbit's field of view, centred on it.

    The transaxial field is the cylinder every view's fan covers; its axial extent spans the
    sources' travel plus the panel height at the isocentre. The default spacing is the pixel
    pitch at the isocentre (pitch / magnification). Explicit ``size_xyz`` overrides the
    extent; sizes are capped at ``max_size`` voxels per axis unless given. A panel turned in
    its plane counts its extent along the motion as its width (:func:`motion_aligned`).
    """
    geometry = motion_aligned(geometry).geometry
    orbit = estimate_orbit(geometry)
    sdd = np.array([v.sdd_mm for v in geometry])
    magnification = float(np.median(sdd / orbit.sod_mm))
    view = geometry[0]
    if spacing_mm is None:
        spacing_mm = min(view.pitch_u_mm, view.pitch_v_mm) / magnification
    if not (math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm must be > 0, got {spacing_mm!r}")
    along = np.asarray(geometry.sources_mm) @ orbit.axis
    shift = 0.5 * (along.min() + along.max()) - float(orbit.isocenter_mm @ orbit.axis)
    center = orbit.isocenter_mm + shift * orbit.axis
    if size_xyz is None:
        fan = math.atan(0.5 * view.cols * view.pitch_u_mm / float(np.median(sdd)))
        radius = float(np.median(orbit.sod_mm)) * math.sin(fan)
        height = np.ptp(along) + view.rows * view.pitch_v_mm / magnification
        # bounding box of the field-of-view cylinder along world x, y, z
        extent = height * np.abs(orbit.axis) + 2 * radius * np.sqrt(
            np.clip(1 - orbit.axis**2, 0, 1)
        )
        size_xyz = tuple(min(max_size, max(1, math.ceil(e / spacing_mm))) for e in extent)
    return VolumeGrid.centered(size_xyz, spacing_mm, center)


def seen_along_z(grid: VolumeGrid, geometry: Geometry) -> VolumeGrid:
    """``grid`` extended along z, in whole voxels, over the height the views see."""
    full = default_grid(geometry, spacing_mm=grid.spacing_mm[2])
    dz = grid.spacing_mm[2]
    low = min(grid.origin_mm[2], full.origin_mm[2])
    high = max(
        grid.origin_mm[2] + dz * (grid.shape[0] - 1), full.origin_mm[2] + dz * (full.shape[0] - 1)
    )
    below = math.ceil((grid.origin_mm[2] - low) / dz - 1e-9)
    above = math.ceil((high - grid.origin_mm[2]) / dz - 1e-9) - (grid.shape[0] - 1)
    origin = (grid.origin_mm[0], grid.origin_mm[1], grid.origin_mm[2] - below * dz)
    return VolumeGrid(
        (grid.shape[0] + below + max(above, 0), *grid.shape[1:]), grid.spacing_mm, origin
    )


def offset_voxels(outer: VolumeGrid, inner: VolumeGrid) -> tuple[int, int, int]:
    """Where ``inner``'s first voxel sits in ``outer`` (z, y, x)."""
    return tuple(int(k) for k in np.rint(outer.world_to_index(inner.origin_mm))[::-1])

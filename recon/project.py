"""Projectors: ray-driven forward projection (Joseph) and voxel-driven backprojection.

Both run through arbitrary per-view geometries (recon.geometry) in numba-parallel kernels with
cached compilation. The backprojector is the voxel-driven approximation of the forward
projector's adjoint: every voxel takes the bilinear detector value where its centre projects,
weighted by the ray density there, ``V_voxel / (w^2 cos(theta) * pixel area)`` (``w`` the
view's normalised depth, ``theta`` the ray's angle to the detector normal). The two discretise
the same continuous X-ray transform and its adjoint, so ``<A x, y> = <x, A^T y>`` holds to the
discretisation error of interpolation (second order in voxel and pixel size for smooth x, y).

Boundary convention (docs/conventions.md, "Views, panels and images"): voxels are cubes. Along a
ray's main axis every slice's sample stands for the whole voxel's thickness, so the integral reaches
half a voxel beyond the outer voxel centres; across it, the bilinear taps fall off into zeros
outside the volume, so the content fades out over the voxel beyond the outer centres. This is
exactly RTK's Joseph projector (rtk::JosephForwardProjectionImageFilter) run on the volume
padded with two layers of zero voxels (tests/recon/test_project.py, float precision). RTK on
the unpadded volume stops at the outer voxel centres, with interpolation clamped at the
border: a ray that crosses the volume loses half a step of each end slice's value (a uniform
volume of 1/mm reads one voxel's length less), and the volume's outline moves in by about half
a voxel. The two agree to float precision when the outer layers are zero.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numba
import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d

from recon.geometry import Geometry, View
from recon.volume import VolumeGrid

_PAD = 2  # zero voxels around the volume so Joseph's bilinear taps never leave the array


def _check_volume(volume: np.ndarray, grid: VolumeGrid) -> np.ndarray:
    if volume.shape != grid.shape:
        raise ValueError(f"volume shape {volume.shape} does not match grid shape {grid.shape}")
    vol = np.ascontiguousarray(volume, dtype=np.float32)
    if not np.all(np.isfinite(vol)):
        raise ValueError("volume contains NaN or infinite values")
    return vol


def corner_depths(geometry: Geometry, grid: VolumeGrid) -> np.ndarray:
    """Each view's depth ``w`` (P's third row) at the grid's eight outer corners, (views, 8);
    positive in front of the source."""
    corners = np.hstack((grid.corners_mm(), np.ones((8, 1))))
    return np.einsum("vk,ck->vc", geometry.matrices[:, 2, :], corners)


def check_in_front(geometry: Geometry, grid: VolumeGrid) -> None:
    """Raise ValueError unless the whole grid lies between each source and its detector."""
    bad = np.flatnonzero(corner_depths(geometry, grid).min(axis=1) <= 1e-3)
    if bad.size:
        raise ValueError(
            f"the volume grid reaches behind the source of view {bad[0]} "
            f"({bad.size} views affected): move or shrink the grid"
        )


def full_spans(rows: int, cols: int) -> np.ndarray:
    """Column spans (rows, 2) covering a whole ``rows x cols`` panel."""
    return np.tile(np.array([0, cols], dtype=np.int64), (rows, 1))


def row_spans(mask: np.ndarray, margin_px: int) -> np.ndarray:
    """Per row of a panel, the columns (start, stop) within ``margin_px`` (chessboard) of the
    pixels ``mask`` (bool (rows, cols)) holds, (0, 0) where a row holds none: the spans a
    projection of those pixels alone traces (a render's high-pass reaches ``4 sigma`` beyond
    a registration's mask)."""
    cols = mask.shape[1]
    index = np.arange(cols)
    size = 2 * margin_px + 1
    lo = minimum_filter1d(np.where(mask, index, cols).min(axis=1), size, mode="nearest")
    hi = maximum_filter1d(np.where(mask, index + 1, 0).max(axis=1), size, mode="nearest")
    empty = hi <= lo
    lo, hi = np.maximum(lo - margin_px, 0), np.minimum(hi + margin_px, cols)
    lo[empty] = hi[empty] = 0
    return np.column_stack((lo, hi)).astype(np.int64)


def _view_arrays(geometry: Geometry) -> tuple[np.ndarray, ...]:
    sources = np.array(geometry.sources_mm, dtype=np.float64)  # writable: one kernel signature
    origins = np.stack([v.detector_origin_mm for v in geometry])
    du = np.stack([v.pitch_u_mm * v.e_u for v in geometry])
    dv = np.stack([v.pitch_v_mm * v.e_v for v in geometry])
    return sources, origins, du, dv


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy", nogil=True)
def _joseph_kernel(
    flat, strides, dims, origin, spacing, sources, det_origins, du, dv, spans, out
):  # pragma: no cover
    """Joseph line integrals; ``flat`` is the zero-padded volume raveled, strides per (x, y, z);
    row r of every view is traced over columns ``spans[r, 0] <= c < spans[r, 1]``, zero
    elsewhere. Runs without the GIL: other threads (a scan's storage, recording and
    reconstruction while its simulated panel renders) go on meanwhile."""
    n_views, rows, cols = out.shape
    for job in numba.prange(n_views * rows):
        view = job // rows
        r = job - view * rows
        s = np.empty(3)
        d = np.empty(3)
        for ax in range(3):
            s[ax] = (sources[view, ax] - origin[ax]) / spacing[ax]
        for c in range(cols):
            if c < spans[r, 0] or c >= spans[r, 1]:
                out[view, r, c] = 0.0
                continue
            length2 = 0.0
            for ax in range(3):
                d_mm = (
                    det_origins[view, ax] + c * du[view, ax] + r * dv[view, ax] - sources[view, ax]
                )
                length2 += d_mm * d_mm
                d[ax] = d_mm / spacing[ax]
            k = 0
            if abs(d[1]) > abs(d[k]):
                k = 1
            if abs(d[2]) > abs(d[k]):
                k = 2
            a = (k + 1) % 3
            b = (k + 2) % 3
            # ray parameter t in [0, 1] (source to pixel), restricted to where the bilinear
            # footprint on the two other axes overlaps the volume: index in (-1, n)
            t_lo, t_hi = 0.0, 1.0
            for ax in (a, b):
                if d[ax] != 0.0:
                    t0 = (-1.0 - s[ax]) / d[ax]
                    t1 = (dims[ax] - s[ax]) / d[ax]
                    t_lo = max(t_lo, min(t0, t1))
                    t_hi = min(t_hi, max(t0, t1))
                elif s[ax] <= -1.0 or s[ax] >= dims[ax]:
                    t_hi = -1.0
            total = 0.0
            if t_hi > t_lo:
                k0 = s[k] + t_lo * d[k]
                k1 = s[k] + t_hi * d[k]
                i_lo = max(0, math.ceil(min(k0, k1)))
                i_hi = min(dims[k] - 1, math.floor(max(k0, k1)))
                inv_dk = 1.0 / d[k]
                st_k = np.uint64(strides[k])
                st_a = np.uint64(strides[a])
                st_b = np.uint64(strides[b])
                # padded coordinates, advanced incrementally one slice at a time along the
                # dominant axis: [t_lo, t_hi] keeps them in [_PAD - 1, dims + _PAD] (to the
                # rounding of the increments), so int() floors and all four taps fall inside
                # the padded array; taps in the zero layers add exactly 0
                step_a = d[a] * inv_dk
                step_b = d[b] * inv_dk
                fa = s[a] + (i_lo - s[k]) * step_a + _PAD
                fb = s[b] + (i_lo - s[k]) * step_b + _PAD
                for i in range(i_lo, i_hi + 1):
                    ia = int(fa)
                    ib = int(fb)
                    wa = fa - ia
                    wb = fb - ib
                    base = np.uint64(i + _PAD) * st_k + np.uint64(ia) * st_a + np.uint64(ib) * st_b
                    total += (1.0 - wa) * (
                        (1.0 - wb) * flat[base] + wb * flat[base + st_b]
                    ) + wa * ((1.0 - wb) * flat[base + st_a] + wb * flat[base + st_a + st_b])
                    fa += step_a
                    fb += step_b
                total *= math.sqrt(length2) / abs(d[k])
            out[view, r, c] = total


class JosephProjector:
    """A volume prepared once for many Joseph projections (DRRs in registration loops)."""

    PAD = _PAD
    """Zero voxels on every side of the array a projector holds."""

    def __init__(self, volume: np.ndarray, grid: VolumeGrid) -> None:
        self._hold(np.pad(_check_volume(volume, grid), _PAD), grid)

    @classmethod
    def of_padded(cls, padded: np.ndarray, grid: VolumeGrid) -> JosephProjector:
        """A projector of a volume already laid out with :attr:`PAD` zero voxels on every
        side: float32, C-contiguous, ``grid.shape`` plus ``2 * PAD`` along each axis; held as
        it is (no copy, no check of its values)."""
        expected = tuple(n + 2 * _PAD for n in grid.shape)
        if padded.shape != expected or padded.dtype != np.float32:
            raise ValueError(
                f"a padded volume must be float32 of shape {expected} for grid shape "
                f"{grid.shape}, got {padded.dtype} {padded.shape}"
            )
        projector = cls.__new__(cls)
        projector._hold(np.ascontiguousarray(padded), grid)
        return projector

    def _hold(self, padded: np.ndarray, grid: VolumeGrid) -> None:
        """Keep the padded volume and the grid's figures the kernel takes."""
        self.grid = grid
        self._flat = padded.ravel()
        self._strides = np.array(padded.strides[::-1], dtype=np.int64) // padded.itemsize
        self._dims = np.array(grid.size_xyz, dtype=np.int64)
        self._origin = np.array(grid.origin_mm)
        self._spacing = np.array(grid.spacing_mm)
        self._corners = grid.corners_mm()

    def project(self, geometry: Geometry, out: np.ndarray | None = None) -> np.ndarray:
        """Line integrals through every pixel of every view.

        Args:
            geometry: The views; every one must see the grid in front of its source.
            out: Array to fill, float32 (views, rows, cols); a new one when ``None``.

        Returns:
            Line integrals (the volume's unit times mm), float32 (views, rows, cols).
        """
        check_in_front(geometry, self.grid)
        sources, origins, du, dv = _view_arrays(geometry)
        if out is None:
            out = np.empty((len(geometry), geometry.rows, geometry.cols), dtype=np.float32)
        _joseph_kernel(
            self._flat,
            self._strides,
            self._dims,
            self._origin,
            self._spacing,
            sources,
            origins,
            du,
            dv,
            full_spans(geometry.rows, geometry.cols),
            out,
        )
        return out

    def project_moved(
        self, view: View, T: np.ndarray, spans: np.ndarray | None = None
    ) -> np.ndarray:
        """Line integrals through ``view`` of the volume moved by the rigid motion ``T``.

        The same as ``project(Geometry([view.transformed(inv(T))]))[0]`` without building
        views (the registration's inner loop renders thousands of poses).

        Args:
            view: The view rendered.
            T: Rigid motion of the volume, 4x4, translation in mm.
            spans: Columns traced per row, int (rows, 2): row r over
                ``spans[r, 0] <= c < spans[r, 1]``, zero elsewhere; ``None`` traces all.

        Returns:
            Line integrals (the volume's unit times mm), float32 (rows, cols).
        """
        return self.project_moved_many(view, T[None], spans)[0]

    def project_moved_many(
        self, view: View, Ts: np.ndarray, spans: np.ndarray | None = None
    ) -> np.ndarray:
        """:meth:`project_moved` at each of several rigid motions: the same values as n
        calls, in one parallel loop over every pose's rows (n small renders, such as a
        Jacobian's, would each wake the kernel's threads and wait for them).

        Args:
            view: The view rendered.
            Ts: Rigid motions of the volume, (n, 4, 4), translations in mm.
            spans: Columns traced per row, as :meth:`project_moved` takes them.

        Returns:
            Line integrals (the volume's unit times mm), float32 (n, rows, cols).
        """
        R, t = Ts[:, :3, :3], Ts[:, :3, 3]
        depth = view.matrix[2, :3]
        w = self._corners @ (depth @ R).T + (t @ depth + view.matrix[2, 3])
        if w.min() <= 1e-3:
            raise ValueError(
                "the volume grid reaches behind the source of the view: move or shrink the grid"
            )
        # each view carried by inv(T): x -> R^T (x - t)
        out = np.empty((len(Ts), view.rows, view.cols), dtype=np.float32)
        _joseph_kernel(
            self._flat,
            self._strides,
            self._dims,
            self._origin,
            self._spacing,
            np.array([(view.source_mm - b) @ A for A, b in zip(R, t, strict=True)]),
            np.array([(view.detector_origin_mm - b) @ A for A, b in zip(R, t, strict=True)]),
            np.array([view.pitch_u_mm * view.e_u @ A for A in R]),
            np.array([view.pitch_v_mm * view.e_v @ A for A in R]),
            full_spans(view.rows, view.cols) if spans is None else spans,
            out,
        )
        return out


def forward_project(volume: np.ndarray, grid: VolumeGrid, geometry: Geometry) -> np.ndarray:
    """Line integrals of ``volume`` through every pixel centre of every view (Joseph).

    Args:
        volume: values on ``grid`` (e.g. 1/mm), indexed [z, y, x].
        grid: the voxel grid, world mm.
        geometry: the views.

    Returns:
        float32 (views, rows, cols): line integrals (value x mm, dimensionless for 1/mm).
    """
    return JosephProjector(volume, grid).project(geometry)


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy", nogil=True)
def _chords_kernel(sources, origins, steps_u, steps_v, lo, hi, out):  # pragma: no cover
    """out[view, row, col] = the length (mm) inside the box [lo, hi] of the ray from the view's
    source through its pixel centre ``origins + col steps_u + row steps_v``."""
    n_views, rows, cols = out.shape
    far = 1e30  # no infinities under fastmath
    for job in numba.prange(n_views * rows):
        view = job // rows
        row = job - view * rows
        s = sources[view]
        for col in range(cols):
            enter, leave, length2 = 0.0, far, 0.0
            for a in range(3):
                d = origins[view, a] + col * steps_u[view, a] + row * steps_v[view, a] - s[a]
                length2 += d * d
                if d != 0.0:
                    t0 = (lo[a] - s[a]) / d
                    t1 = (hi[a] - s[a]) / d
                    enter = max(enter, min(t0, t1))
                    leave = min(leave, max(t0, t1))
                elif s[a] < lo[a] or s[a] > hi[a]:
                    leave = -far
            out[view, row, col] = max(leave - enter, 0.0) * math.sqrt(length2)


def centre_chords(geometry: Geometry, grid: VolumeGrid) -> np.ndarray:
    """Length (mm) of every pixel centre's ray inside the box spanned by ``grid``'s outer voxel
    centres, float32 (views, rows, cols); 0 for rays that miss it.

    The forward projector's row sum (:func:`forward_project` of ones) reaches half a voxel
    further at each end (voxels are cubes); this is RTK's ray-box length
    (rtk::RayBoxIntersectionImageFilter with the box from the outer voxel centres).
    """
    lo = np.asarray(grid.origin_mm, dtype=np.float64)
    hi = lo + (np.asarray(grid.shape[::-1]) - 1) * np.asarray(grid.spacing_mm)
    views = list(geometry)
    out = np.empty((len(views), geometry.rows, geometry.cols), dtype=np.float32)
    _chords_kernel(
        np.array([v.source_mm for v in views], dtype=np.float64),
        np.array([v.detector_origin_mm for v in views], dtype=np.float64),
        np.array([v.e_u * v.pitch_u_mm for v in views], dtype=np.float64),
        np.array([v.e_v * v.pitch_v_mm for v in views], dtype=np.float64),
        lo,
        hi,
        out,
    )
    return out


FDK_WEIGHT, ADJOINT_WEIGHT, COUNT_WEIGHT = 0, 1, 2
"""Per voxel-view weights of :func:`backproject_weighted`: ``1/w^2`` (FDK),
``|x - s| / w^3`` (the forward projector's adjoint, up to per-view constants) and
``w / L_perp^2`` (FDK's view-count Jacobian, ``L_perp`` the source distance across ``axis``)."""


@numba.njit(fastmath=True, error_model="numpy", inline="always")
def _clip(lo, hi, a, b):  # pragma: no cover
    """The x range ``lo <= x <= hi`` cut to where ``a x + b >= 0`` (empty: ``hi = -1``)."""
    if a > 0:
        lo = max(lo, -b / a)
    elif a < 0:
        hi = min(hi, -b / a)
    elif b < 0:
        hi = -1.0
    return lo, hi


@numba.njit(fastmath=True, error_model="numpy", boundscheck=False, inline="always")
def _row_samples(
    n, x0, h, s, umax, vmax, cols, mode, scale, d0, dd, axis, idx, fu, fv, wt, iu_out
):  # pragma: no cover
    """Detector sample positions and weights of ``n`` voxels from ``x0`` along one row.

    The tuples ``h`` and ``s`` hold (u*w, v*w, w) at voxel x = 0 and its step per voxel
    (float32 scalars, which stay in registers); ``d0``, ``dd``
    the voxel-minus-source vector at x = 0 and its step (modes 1 and 2); ``scale`` multiplies
    every weight; in mode 2 ``iu_out`` receives each sample's column (:func:`_column_weights`).
    """
    zero = np.float32(0.0)
    xf = np.float32(x0)  # a float counter (exact) vectorises better than converting k
    for k in range(n):
        w = h[2] + xf * s[2]
        inv = np.float32(1.0) / w
        u = min(max((h[0] + xf * s[0]) * inv, zero), umax)
        v = min(max((h[1] + xf * s[1]) * inv, zero), vmax)
        iu = min(np.int32(u), np.int32(cols - 2))
        iv = min(np.int32(v), np.int32(vmax - 1))
        fu[k] = u - np.float32(iu)
        fv[k] = v - np.float32(iv)
        idx[k] = np.uint32(iv * np.int32(cols) + iu)
        if mode == 0:
            wt[k] = inv * inv * scale
        else:
            dx = d0[0] + xf * dd[0]
            dy = d0[1] + xf * dd[1]
            dz = d0[2] + xf * dd[2]
            dist2 = dx * dx + dy * dy + dz * dz
            if mode == 1:
                wt[k] = math.sqrt(dist2) * inv * inv * inv * scale
            else:
                along = dx * axis[0] + dy * axis[1] + dz * axis[2]
                wt[k] = w * scale / (dist2 - along * along)
                iu_out[k] = np.uint32(iu)
        xf += np.float32(1.0)


@numba.njit(fastmath=True, error_model="numpy", boundscheck=False, inline="always")
def _column_weights(n, column, iu, fu, wt):  # pragma: no cover
    """wt[k] *= ``column`` (cols,) interpolated linearly at sample k's column ``iu[k] + fu[k]``
    (a scalar loop apart from :func:`_row_samples`, whose loop a gather would stop vectorising)."""
    for k in range(n):
        c = iu[k]
        wt[k] *= column[c] + fu[k] * (column[c + 1] - column[c])


@numba.njit(fastmath=True, error_model="numpy", boundscheck=False, inline="always")
def row_gather(n, pairs, idx, fu, fv, wt, upper, lower, acc):  # pragma: no cover
    """acc[k] += wt[k] * bilinear(image) for the samples of :func:`_row_samples`.

    ``pairs`` is the view's :func:`pixel_quads` raveled as complex64 (:func:`quad_pairs`): pixel
    i's upper pair (p[r, c], p[r, c + 1]) at 2i, its lower pair at 2i + 1, so that two 8-byte
    loads fetch its whole bilinear footprint; ``upper`` and ``lower`` (complex64, n + 1) are
    scratch. The scalar gather only moves those pairs, two samples a step (``idx`` holds a
    valid index past the n-th), and the interpolation runs vectorised after it, on pairs (a
    stride the vector units deinterleave within their lanes, where a quad's four values
    would cross them: docs/algorithms/fdk.md).
    """
    one = np.uint64(1)
    for k in range(0, n, 2):
        k0 = np.uint64(k)  # unsigned indices: no wrap-around checks in the unrolled step
        i = np.uint64(idx[k0]) << one
        j = np.uint64(idx[k0 + one]) << one
        upper[k0] = pairs[i]
        lower[k0] = pairs[i + one]
        upper[k0 + one] = pairs[j]
        lower[k0 + one] = pairs[j + one]
    for k in range(n):
        r0 = upper[k].real + fu[k] * (upper[k].imag - upper[k].real)
        r1 = lower[k].real + fu[k] * (lower[k].imag - lower[k].real)
        acc[k] += (r0 + fv[k] * (r1 - r0)) * wt[k]


def quad_pairs(quads: np.ndarray) -> np.ndarray:
    """:func:`pixel_quads` (..., rows, cols, 4) float32 viewed as :func:`row_gather` takes them:
    (..., rows, cols, 2) complex64, contiguous."""
    return np.ascontiguousarray(quads, dtype=np.float32).view(np.complex64)


ROWS_PER_JOB = 8
"""Voxel rows (consecutive y at one z) that the backprojector takes view by view together:
each view's band of the detector stays in L1 across them (12-16 % faster than row by row on
this machine's 48 KiB L1)."""


@numba.njit(
    parallel=True, fastmath=True, cache=True, error_model="numpy", boundscheck=False, nogil=True
)
def _backproject_kernel(
    quads, scale, mats, sources, axis, mode, columns, by_column, origin, spacing, out
):  # pragma: no cover
    """out[z, y, x] += sum over views of scale * weight(mode) * bilinear(image) at P x;
    ``quads`` holds the images (one per view, or one for all) as :func:`quad_pairs`, (views or
    1, rows, cols, 2); in mode 2 with ``by_column`` each image is multiplied
    along its columns by ``columns`` (views or 1, cols), float32."""
    n_images, rows, cols = quads.shape[:3]
    n_views = len(mats)
    nz, ny, nx = out.shape
    umax = np.float32(cols - 1.0)
    vmax = np.float32(rows - 1.0)
    flat = quads.reshape(n_images, rows * cols * 2)
    ax32 = axis.astype(np.float32)
    blocks = (ny + ROWS_PER_JOB - 1) // ROWS_PER_JOB
    for job in numba.prange(nz * blocks):
        z = job // blocks
        y0 = (job - z * blocks) * ROWS_PER_JOB
        y1 = min(ny, y0 + ROWS_PER_JOB)
        wz = origin[2] + z * spacing[2]
        acc = np.zeros((ROWS_PER_JOB, nx), dtype=np.float32)
        idx = np.zeros(nx + 1, dtype=np.uint32)  # any entry is a valid pixel index
        fu = np.empty(nx, dtype=np.float32)
        fv = np.empty(nx, dtype=np.float32)
        wt = np.empty(nx, dtype=np.float32)
        cu = np.empty(nx, dtype=np.uint32)
        upper = np.empty(nx + 1, dtype=np.complex64)
        lower = np.empty(nx + 1, dtype=np.complex64)
        d0 = np.empty(3, dtype=np.float32)
        dd = np.zeros(3, dtype=np.float32)
        dd[0] = spacing[0]
        for view in range(n_views):
            m = mats[view]
            s0 = np.float32(m[0, 0] * spacing[0])
            s1 = np.float32(m[1, 0] * spacing[0])
            s2 = np.float32(m[2, 0] * spacing[0])
            s = (s0, s1, s2)
            image = flat[min(view, n_images - 1)]
            column = columns[min(view, len(columns) - 1)]
            sc = scale[view]
            for y in range(y0, y1):
                wy = origin[1] + y * spacing[1]
                h0 = np.float32(m[0, 0] * origin[0] + m[0, 1] * wy + m[0, 2] * wz + m[0, 3])
                h1 = np.float32(m[1, 0] * origin[0] + m[1, 1] * wy + m[1, 2] * wz + m[1, 3])
                h2 = np.float32(m[2, 0] * origin[0] + m[2, 1] * wy + m[2, 2] * wz + m[2, 3])
                d0[0] = origin[0] - sources[view, 0]
                d0[1] = wy - sources[view, 1]
                d0[2] = wz - sources[view, 2]
                # w > 0 on the grid, so 0 <= u <= umax is linear in x: h0 + x s0 >= 0 and
                # h0 + x s0 <= umax (h2 + x s2); likewise for v. Intersect the four half-lines.
                lo, hi = 0.0, nx - 1.0
                for a, b in (
                    (s0, h0),
                    (s1, h1),
                    (umax * s2 - s0, umax * h2 - h0),
                    (vmax * s2 - s1, vmax * h2 - h1),
                ):
                    lo, hi = _clip(lo, hi, a, b)
                x0 = max(0, math.ceil(lo))
                n = min(nx - 1, math.floor(hi)) - x0 + 1
                if n <= 0:
                    continue
                h = (h0, h1, h2)
                if mode == FDK_WEIGHT:  # the hot path, compiled with the weight's branch folded
                    _row_samples(
                        n, x0, h, s, umax, vmax, cols, 0, sc, d0, dd, ax32, idx, fu, fv, wt, cu
                    )
                else:
                    _row_samples(
                        n, x0, h, s, umax, vmax, cols, mode, sc, d0, dd, ax32, idx, fu, fv, wt, cu
                    )
                if mode == COUNT_WEIGHT and by_column:
                    _column_weights(n, column, cu, fu, wt)
                row_gather(n, image, idx, fu, fv, wt, upper, lower, acc[y - y0, x0:])
        for y in range(y0, y1):
            for x in range(nx):
                out[z, y, x] += acc[y - y0, x]


UPRIGHT_ROWS_BY_L2 = ((1 << 20, (32, 4)), (0, (16, 4)))
"""Voxel rows per job of :func:`_upright_kernel`, (z rows, y rows), by the smallest L2 cache
per core (bytes) they suit: the z rows share each (y, view)'s detector columns and weights, the
y rows are taken view by view together (the shapes measured on two hosts:
docs/algorithms/fdk.md)."""


def l2_cache_bytes() -> int:
    """The L2 cache of the first CPU in bytes, as Linux's sysfs tells it (0 elsewhere)."""
    units = {"K": 1 << 10, "M": 1 << 20}
    for index in Path("/sys/devices/system/cpu/cpu0/cache").glob("index*"):
        try:
            if (index / "level").read_text().strip() == "2":
                size = (index / "size").read_text().strip()
                return int(size.rstrip("KM")) * units.get(size[-1], 1)
        except (OSError, ValueError):
            return 0
    return 0


@functools.cache
def upright_rows() -> tuple[int, int]:
    """(z rows, y rows) of :data:`UPRIGHT_ROWS_BY_L2` for this machine's L2 cache."""
    return next(rows for size, rows in UPRIGHT_ROWS_BY_L2 if l2_cache_bytes() >= size)


@numba.njit(
    parallel=True, fastmath=True, cache=True, error_model="numpy", boundscheck=False, nogil=True
)
def _upright_kernel(quads, scale, mats, origin, spacing, zb, yb, out):  # pragma: no cover
    """:func:`_backproject_kernel` in ``FDK_WEIGHT`` mode for views whose u and w do not
    change along the grid's z (an orbit about z with upright panels): each (y, view) computes
    its detector columns, weights and the rows' start and step in z once, for
    ``zb`` rows of z, which then only step ``v``; a job takes ``zb`` x ``yb`` rows (z x y)."""
    n_images, rows, cols = quads.shape[:3]
    n_views = len(mats)
    nz, ny, nx = out.shape
    umax = np.float32(cols - 1.0)
    vmax = np.float32(rows - 1.0)
    zero = np.float32(0.0)
    flat = quads.reshape(n_images, rows * cols * 2)
    y_blocks = (ny + yb - 1) // yb
    for job in numba.prange(((nz + zb - 1) // zb) * y_blocks):
        z0 = (job // y_blocks) * zb
        y0 = (job % y_blocks) * yb
        z1 = min(nz, z0 + zb)
        y1 = min(ny, y0 + yb)
        wz = origin[2] + z0 * spacing[2]
        acc = np.zeros((zb, yb, nx), dtype=np.float32)
        col = np.zeros(nx, dtype=np.uint32)
        fu = np.empty(nx, dtype=np.float32)
        wt = np.empty(nx, dtype=np.float32)
        v0 = np.empty(nx, dtype=np.float32)
        dv = np.empty(nx, dtype=np.float32)
        idx = np.zeros(nx + 1, dtype=np.uint32)  # any entry is a valid pixel index
        fv = np.empty(nx, dtype=np.float32)
        upper = np.empty(nx + 1, dtype=np.complex64)
        lower = np.empty(nx + 1, dtype=np.complex64)
        for view in range(n_views):
            m = mats[view]
            s0 = np.float32(m[0, 0] * spacing[0])
            s1 = np.float32(m[1, 0] * spacing[0])
            s2 = np.float32(m[2, 0] * spacing[0])
            cz = np.float32(m[1, 2] * spacing[2])
            image = flat[min(view, n_images - 1)]
            sc = scale[view]
            for y in range(y0, y1):
                wy = origin[1] + y * spacing[1]
                h0 = np.float32(m[0, 0] * origin[0] + m[0, 1] * wy + m[0, 2] * wz + m[0, 3])
                h1 = np.float32(m[1, 0] * origin[0] + m[1, 1] * wy + m[1, 2] * wz + m[1, 3])
                h2 = np.float32(m[2, 0] * origin[0] + m[2, 1] * wy + m[2, 2] * wz + m[2, 3])
                # 0 <= u <= umax along x (w > 0): as in _backproject_kernel, for u only
                lo, hi = 0.0, nx - 1.0
                for a, b in ((s0, h0), (umax * s2 - s0, umax * h2 - h0)):
                    lo, hi = _clip(lo, hi, a, b)
                xa = max(0, math.ceil(lo))
                xb = min(nx - 1, math.floor(hi))
                if xb < xa:
                    continue
                xf = np.float32(xa)
                for k in range(xa, xb + 1):
                    w = h2 + xf * s2
                    inv = np.float32(1.0) / w
                    u = min(max((h0 + xf * s0) * inv, zero), umax)
                    iu = min(np.int32(u), np.int32(cols - 2))
                    col[k] = np.uint32(iu)
                    fu[k] = u - np.float32(iu)
                    wt[k] = inv * inv * sc
                    v0[k] = (h1 + xf * s1) * inv
                    dv[k] = cz * inv
                    xf += np.float32(1.0)
                for z in range(z0, z1):
                    zf = np.float32(z - z0)
                    hz = h1 + zf * cz
                    lo, hi = float(xa), float(xb)
                    for a, b in ((s1, hz), (vmax * s2 - s1, vmax * h2 - hz)):
                        lo, hi = _clip(lo, hi, a, b)
                    x0 = max(xa, math.ceil(lo))
                    n = min(xb, math.floor(hi)) - x0 + 1
                    if n <= 0:
                        continue
                    for k in range(n):
                        v = min(max(v0[x0 + k] + zf * dv[x0 + k], zero), vmax)
                        iv = min(np.int32(v), np.int32(rows - 2))
                        fv[k] = v - np.float32(iv)
                        idx[k] = np.uint32(iv * np.int32(cols)) + col[x0 + k]
                    row_gather(
                        n, image, idx, fu[x0:], fv, wt[x0:], upper, lower, acc[z - z0, y - y0, x0:]
                    )
        for z in range(z0, z1):
            for y in range(y0, y1):
                for x in range(nx):
                    out[z, y, x] += acc[z - z0, y - y0, x]


UPRIGHT_TOLERANCE_PX = 1e-3
"""How far a voxel's detector column and depth may move over the grid's z extent (in pixels)
for :func:`upright` to hold them still."""


def upright(geometry: Geometry, grid: VolumeGrid) -> bool:
    """Whether every view's u and w stay put along the grid's z axis: over the grid's z
    extent, u moves and v's scale changes by less than :data:`UPRIGHT_TOLERANCE_PX` pixels
    (so :func:`_upright_kernel` applies: orbits about z with upright panels)."""
    m = np.asarray(geometry.matrices)
    w_min = float(corner_depths(geometry, grid).min())
    extent = grid.shape[0] * grid.spacing_mm[2]
    drift = (np.abs(m[:, 0, 2]) + max(geometry.rows, geometry.cols) * np.abs(m[:, 2, 2])) * extent
    return w_min > 0 and float(drift.max()) / w_min < UPRIGHT_TOLERANCE_PX


@numba.njit(fastmath=True, error_model="numpy", inline="always")
def _quad_row(quad, below, a, b):  # pragma: no cover
    """Taps (2 below, 2 below + 1) of a row of pixel quads (cols, 4): ``a * b`` (two rows of
    ``cols`` values, either may be strided) and its right-hand neighbour, 0 after the last."""
    tap = 2 * below
    cols = quad.shape[0]
    for c in range(cols):
        quad[c, tap] = a[c] * b[c]
    for c in range(cols - 1):
        quad[c, tap + 1] = quad[c + 1, tap]
    quad[cols - 1, tap + 1] = 0.0


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy", nogil=True)
def quads_kernel(a, b, out, packed):  # pragma: no cover
    """out[k, r, c] = (p[r, c], p[r, c + 1], p[r + 1, c], p[r + 1, c + 1]) of the k-th image
    p = a * b (broadcast over axes 0 and 1), 0 past the last row and column. ``packed``: ``a``
    holds complex rows as interleaved float32, image rows 2j and 2j + 1 in the real and the
    imaginary parts of row j (:class:`recon.ramp.RowFilter`)."""
    n, rows, cols = out.shape[:3]
    for job in numba.prange(n * rows):
        k = job // rows
        r = job - k * rows
        for below in range(2):
            rr = r + below
            if rr == rows:
                out[k, r, :, 2:] = 0.0
                continue
            if packed:
                ra = a[k, rr // 2, rr % 2 : 2 * cols : 2]
            else:
                ra = a[min(k, a.shape[0] - 1), min(rr, a.shape[1] - 1)]
            _quad_row(out[k, r], below, ra, b[min(k, b.shape[0] - 1), min(rr, b.shape[1] - 1)])


def pixel_quads(images: np.ndarray, factor: np.ndarray | None = None) -> np.ndarray:
    """``images * factor`` laid out for :func:`backproject_weighted`: every pixel with its
    bilinear footprint, (p[r, c], p[r, c + 1], p[r + 1, c], p[r + 1, c + 1]) (0 past the last
    row and column), float32 (V, rows, cols, 4).

    ``images`` and ``factor`` are (V or 1, rows or 1, cols), broadcast against each other.
    """
    a = np.ascontiguousarray(images, dtype=np.float32)
    b = np.ones((1, 1, a.shape[-1]), np.float32) if factor is None else np.asarray(factor)
    b = b.astype(np.float32, copy=False)
    if a.ndim != 3 or b.ndim != 3 or a.shape[2] != b.shape[2]:
        raise ValueError(f"images {a.shape} and factor {b.shape} must be 3-d with equal columns")
    shape = np.broadcast_shapes(a.shape, b.shape)
    out = np.empty((*shape, 4), dtype=np.float32)
    quads_kernel(a, b, out, False)
    return out


def backproject_weighted(
    images: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    mode: int,
    out: np.ndarray,
    axis: np.ndarray | None = None,
    scale: np.ndarray | None = None,
    columns: np.ndarray | None = None,
) -> None:
    """Accumulate voxel-driven backprojections of ``images`` into ``out``.

    ``images`` are (V, rows, cols), one per view of ``geometry``, or (1, rows, cols), one for
    all of them; either laid out by :func:`pixel_quads` (a trailing axis of 4) or plain. Each
    voxel adds ``scale[view] * weight * bilinear(image)`` where its centre projects inside the
    panel; the weight is chosen by ``mode`` (:data:`FDK_WEIGHT`, :data:`ADJOINT_WEIGHT`,
    :data:`COUNT_WEIGHT`, the latter needing the rotation ``axis``); ``scale`` (V,) defaults
    to 1. In :data:`COUNT_WEIGHT` mode ``columns`` (V or 1, cols) multiplies each image along
    its columns, interpolated apart from it (for an image that is a row profile times a
    column profile, the same as the product's bilinear interpolation); default 1. float32
    throughout.
    """
    if out.shape != grid.shape or out.dtype != np.float32:
        raise ValueError(f"out must be float32 of shape {grid.shape}")
    quads = np.asarray(images)
    if quads.ndim == 3:
        quads = pixel_quads(quads)
    if quads.shape[1:] != (geometry.rows, geometry.cols, 4) or len(quads) not in (1, len(geometry)):
        raise ValueError(
            f"images of shape {quads.shape} for {len(geometry)} views of {geometry.rows} x "
            f"{geometry.cols} pixels"
        )
    quads = quad_pairs(quads)
    scale = np.ones(len(geometry), np.float32) if scale is None else np.asarray(scale, np.float32)
    if mode == FDK_WEIGHT and upright(geometry, grid):
        matrices = np.asarray(geometry.matrices)
        origin, spacing = np.array(grid.origin_mm), np.array(grid.spacing_mm)
        _upright_kernel(quads, scale, matrices, origin, spacing, *upright_rows(), out)
        return
    by_column = columns is not None
    columns = np.ones((1, geometry.cols)) if columns is None else columns
    columns = np.ascontiguousarray(columns, dtype=np.float32)
    if columns.shape[1:] != (geometry.cols,) or len(columns) not in (1, len(geometry)):
        raise ValueError(f"column weights of shape {columns.shape} for {len(geometry)} views")
    _backproject_kernel(
        quads,
        scale,
        np.asarray(geometry.matrices),
        np.asarray(geometry.sources_mm),
        np.zeros(3) if axis is None else np.ascontiguousarray(axis, dtype=np.float64),
        mode,
        columns,
        by_column,
        np.array(grid.origin_mm),
        np.array(grid.spacing_mm),
        out,
    )


def backproject(projections: np.ndarray, geometry: Geometry, grid: VolumeGrid) -> np.ndarray:
    """Voxel-driven backprojection, the adjoint of :func:`forward_project` (see module doc).

    Args:
        projections: float32 (views, rows, cols).
        geometry: the views, one per projection.
        grid: the voxel grid to backproject onto.

    Returns:
        float32 volume [z, y, x].
    """
    proj = np.ascontiguousarray(projections, dtype=np.float32)
    if proj.shape != (len(geometry), geometry.rows, geometry.cols):
        raise ValueError(
            f"projections have shape {proj.shape}, the geometry needs "
            f"({len(geometry)}, {geometry.rows}, {geometry.cols})"
        )
    check_in_front(geometry, grid)
    out = np.zeros(grid.shape, dtype=np.float32)
    backproject_weighted(
        proj, geometry, grid, ADJOINT_WEIGHT, out, scale=adjoint_scale(geometry, grid)
    )
    return out


def adjoint_scale(geometry: Geometry, grid: VolumeGrid) -> np.ndarray:
    """Per-view factors (float32) that make :data:`ADJOINT_WEIGHT` backprojection onto ``grid``
    the forward projector's adjoint: A^T y = V_voxel / pixel_area * y / (w^2 cos theta), with
    cos theta = w * sdd / |x - s|."""
    return np.array(
        [
            grid.voxel_volume_mm3
            / (v.pitch_u_mm * v.pitch_v_mm * np.linalg.norm(np.cross(v.e_u, v.e_v)) * v.sdd_mm)
            for v in geometry
        ],
        dtype=np.float32,
    )

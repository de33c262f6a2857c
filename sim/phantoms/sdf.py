"""Signed distance functions (SDF) over point arrays, and their partial-volume rasterisation.

Every primitive takes points ``p`` of shape (N, 3) in mm and returns signed distances (N,) in mm:
negative inside, positive outside (compiled loops: one pass over the points, no temporaries).
Exact distances where the closed form exists (sphere, capsule, torus); the ellipsoid and the
tapered capsule are first-order approximations that are accurate near the surface, which is
where partial volume and shell thickness are decided. Smooth booleans use the polynomial
smooth minimum (blend radius ``k`` mm).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numba
import numpy as np

from recon.volume import VolumeGrid

SdfFunction = Callable[[np.ndarray], np.ndarray]
"""Signed distance (mm) of local points (N, 3) mm, shape (N,)."""

_TARGET_POINTS = 1 << 20  # points per SDF call, bounds memory
_BLOCK = 4  # voxels per block edge of the coarse pass
_BAND_SAFETY = 1.5  # margin on half diagonals for the approximate SDFs


def _points(p: np.ndarray) -> np.ndarray:
    """``p`` as the kernels take it: C-contiguous float64 (one compiled signature)."""
    return np.ascontiguousarray(p, dtype=np.float64)


def _vector(v: Sequence[float] | np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(v, dtype=np.float64)


def sphere(p: np.ndarray, center: Sequence[float], radius: float) -> np.ndarray:
    """Sphere of ``radius`` mm about ``center``."""
    return _tapered_capsule(_points(p), _vector(center), np.zeros(3), float(radius), float(radius))


def capsule(p: np.ndarray, a: Sequence[float], b: Sequence[float], radius: float) -> np.ndarray:
    """Capsule: all points within ``radius`` mm of the segment a-b."""
    return tapered_capsule(p, a, b, radius, radius)


def tapered_capsule(
    p: np.ndarray, a: Sequence[float], b: Sequence[float], radius_a: float, radius_b: float
) -> np.ndarray:
    """Segment a-b swept by a radius varying linearly from ``radius_a`` to ``radius_b``.

    Exact for equal radii; for unequal radii the error is of order the taper slope squared.
    """
    a = _vector(a)
    return _tapered_capsule(_points(p), a, _vector(b) - a, float(radius_a), float(radius_b))


@numba.njit(cache=True, error_model="numpy")
def _tapered_capsule(p, a, ba, radius_a, radius_b):  # pragma: no cover
    """:func:`tapered_capsule` with ``ba = b - a`` (a zero ``ba``: a sphere about ``a``)."""
    bb = ba[0] * ba[0] + ba[1] * ba[1] + ba[2] * ba[2]
    out = np.empty(p.shape[0])
    for i in range(p.shape[0]):
        x, y, z = p[i, 0] - a[0], p[i, 1] - a[1], p[i, 2] - a[2]
        t = 0.0
        if bb > 0.0:
            t = min(max((x * ba[0] + y * ba[1] + z * ba[2]) / bb, 0.0), 1.0)
        x, y, z = x - t * ba[0], y - t * ba[1], z - t * ba[2]
        out[i] = math.sqrt(x * x + y * y + z * z) - (radius_a + (radius_b - radius_a) * t)
    return out


def ellipsoid(p: np.ndarray, center: Sequence[float], radii: Sequence[float]) -> np.ndarray:
    """Axis-aligned ellipsoid; the first-order distance k0 (k0 - 1) / k1 (exact for a sphere).

    Works in any dimension: ``p`` (N, D) with D-element ``center`` and ``radii``.
    """
    return _ellipsoid(_points(p), _vector(center), _vector(radii))


@numba.njit(cache=True, error_model="numpy")
def _ellipsoid(p, center, radii):  # pragma: no cover
    """:func:`ellipsoid`."""
    out = np.empty(p.shape[0])
    r_min = radii.min()
    for i in range(p.shape[0]):
        s0 = 0.0
        s1 = 0.0
        for k in range(p.shape[1]):
            q = (p[i, k] - center[k]) / radii[k]
            s0 += q * q
            q /= radii[k]
            s1 += q * q
        k0, k1 = math.sqrt(s0), math.sqrt(s1)
        out[i] = k0 * (k0 - 1.0) / k1 if k1 > 1e-12 else -r_min
    return out


def torus_x(p: np.ndarray, center: Sequence[float], major: float, minor: float) -> np.ndarray:
    """Torus about the line through ``center`` along x: a tube of radius ``minor`` mm around
    the circle of radius ``major`` mm in the y-z plane (``major < minor`` gives a closed,
    wheel-like spindle torus)."""
    return _torus_x(_points(p), _vector(center), float(major), float(minor))


@numba.njit(cache=True, error_model="numpy")
def _torus_x(p, center, major, minor):  # pragma: no cover
    """:func:`torus_x`."""
    out = np.empty(p.shape[0])
    for i in range(p.shape[0]):
        y, z, x = p[i, 1] - center[1], p[i, 2] - center[2], p[i, 0] - center[0]
        ring = math.sqrt(y * y + z * z) - major
        out[i] = math.sqrt(ring * ring + x * x) - minor
    return out


def smooth_union(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Union of two solids, blended over ``k`` mm (polynomial smooth minimum)."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    flat = _smooth_union(np.ascontiguousarray(a).ravel(), np.ascontiguousarray(b).ravel(), float(k))
    return flat.reshape(a.shape)


@numba.njit(cache=True, error_model="numpy")
def _smooth_union(a, b, k):  # pragma: no cover
    """:func:`smooth_union` of two (N,) distances."""
    out = np.empty(a.shape[0])
    for i in range(a.shape[0]):
        h = min(max(0.5 + 0.5 * (b[i] - a[i]) / k, 0.0), 1.0)
        out[i] = b[i] + (a[i] - b[i]) * h - k * h * (1.0 - h)
    return out


def smooth_intersection(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Intersection of two solids, blended over ``k`` mm."""
    return -smooth_union(-a, -b, k)


def smooth_subtraction(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Solid ``a`` minus solid ``b``, blended over ``k`` mm."""
    return smooth_intersection(a, -b, k)


def supersample_offsets(spacing_mm: Sequence[float], supersample: int) -> np.ndarray:
    """Offsets (n**3, 3) mm of the n x n x n sub-voxel sample centres from the voxel centre."""
    n = int(supersample)
    if n < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    f = (np.arange(n) + 0.5) / n - 0.5
    g = np.stack(np.meshgrid(f, f, f, indexing="ij"), axis=-1).reshape(-1, 3)
    return g * np.asarray(spacing_mm, dtype=np.float64)


def box_slices(grid: VolumeGrid, lo_mm: np.ndarray, hi_mm: np.ndarray) -> tuple[slice, ...] | None:
    """Index slices [z, y, x] of the voxels whose centres lie in the world box [lo, hi] mm.

    Args:
        grid: the voxel grid.
        lo_mm: the box's lower world corner (x, y, z), mm.
        hi_mm: its upper world corner (x, y, z), mm.

    Returns:
        The slices, or None when no voxel centre lies in the box.
    """
    lo = np.ceil(grid.world_to_index(lo_mm) - 1e-9).astype(int)
    hi = np.floor(grid.world_to_index(hi_mm) + 1e-9).astype(int) + 1
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, grid.size_xyz)
    if np.any(hi <= lo):
        return None
    return tuple(slice(int(lo[k]), int(hi[k])) for k in (2, 1, 0))


def layer_fractions(
    sdf: SdfFunction,
    T_world_local: np.ndarray,
    grid: VolumeGrid,
    levels_mm: Sequence[float],
    supersample: int,
    box_slices_zyx: tuple[slice, ...],
) -> np.ndarray:
    """Partial-volume fractions of the sub-level sets {sdf < level} on part of a grid.

    Coarse to fine: the SDF is first sampled at the centres of 4 x 4 x 4 voxel blocks, and a
    block lies wholly on one side of every level when its distance to each level exceeds
    1.5 half block diagonals (1.5: margin for the approximate SDFs). Voxel centres of the
    other blocks are classified directly, and only voxels within 1.5 half voxel diagonals of
    a level set are resolved with ``supersample**3`` sub-samples.

    Args:
        sdf: signed distance in the solid's local frame.
        T_world_local: 4x4 pose of the local frame in the world.
        grid: the voxel grid (world mm).
        levels_mm: iso-levels, e.g. ``(0, -shell_thickness)``.
        supersample: sub-samples per voxel edge.
        box_slices_zyx: the part of the grid to evaluate (see :func:`box_slices`).

    Returns:
        float32 (len(levels), nz, ny, nx) over the box: fraction of each voxel inside each level.
    """
    levels = np.asarray(levels_mm, dtype=np.float64)[:, None]
    R = np.asarray(T_world_local, dtype=np.float64)[:3, :3]
    t = np.asarray(T_world_local, dtype=np.float64)[:3, 3]
    ax, ay, az = grid.axes_mm()
    axes_zyx = (az[box_slices_zyx[0]], ay[box_slices_zyx[1]], ax[box_slices_zyx[2]])
    shape = tuple(a.size for a in axes_zyx)
    spacing_zyx = np.asarray(grid.spacing_mm)[::-1]
    diag = float(np.linalg.norm(grid.spacing_mm))

    def local(index_zyx: np.ndarray) -> np.ndarray:
        world = np.stack([a[i] for a, i in zip(axes_zyx, index_zyx.T, strict=True)][::-1], axis=1)
        return (world - t) @ R

    # blocks: centre distances decide whole blocks
    nb = tuple(-(-n // _BLOCK) for n in shape)
    centers = [
        a[0] + (np.arange(m) * _BLOCK + 0.5 * (_BLOCK - 1)) * s
        for a, m, s in zip(axes_zyx, nb, spacing_zyx, strict=True)
    ]
    cz, cy, cx = np.meshgrid(*centers, indexing="ij")
    d_block = sdf((np.stack((cx.ravel(), cy.ravel(), cz.ravel()), axis=1) - t) @ R)
    block_inside = (d_block < levels).astype(np.float32).reshape(-1, *nb)
    mixed = np.any(np.abs(d_block - levels) <= _BAND_SAFETY * 0.5 * _BLOCK * diag, axis=0)
    out = block_inside
    for axis, n in enumerate(shape):
        out = np.repeat(out, _BLOCK, axis=axis + 1).take(np.arange(n), axis=axis + 1)
    out = np.ascontiguousarray(out)
    # voxels of mixed blocks
    cells = np.stack(np.meshgrid(*[np.arange(_BLOCK)] * 3, indexing="ij"), -1).reshape(-1, 3)
    blocks = np.argwhere(mixed.reshape(nb))
    voxels = (blocks[:, None, :] * _BLOCK + cells[None, :, :]).reshape(-1, 3)
    voxels = voxels[np.all(voxels < shape, axis=1)]
    if len(voxels) == 0:
        return out
    offsets = supersample_offsets(grid.spacing_mm, supersample) @ R
    band = _BAND_SAFETY * 0.5 * diag
    chunk = max(1, _TARGET_POINTS // offsets.shape[0])
    for v in np.array_split(voxels, max(1, -(-len(voxels) // chunk))):
        p = local(v)
        d = sdf(p)
        frac = (d < levels).astype(np.float32)
        near = np.any(np.abs(d - levels) < band, axis=0)
        if supersample > 1 and np.any(near):
            ds = sdf((p[near][:, None, :] + offsets[None, :, :]).reshape(-1, 3))
            frac[:, near] = np.mean(ds.reshape(1, -1, offsets.shape[0]) < levels[:, :, None], 2)
        out[:, v[:, 0], v[:, 1], v[:, 2]] = frac
    return out

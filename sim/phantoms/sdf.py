"""Signed distance functions (SDF) over point arrays, and their partial-volume rasterisation.

Every primitive takes points ``p`` of shape (N, 3) in mm and returns signed distances (N,) in mm:
negative inside, positive outside. Exact distances where the closed form exists (sphere,
capsule, torus); the ellipsoid and the tapered capsule are first-order approximations
that are accurate near the surface, which is where partial volume and shell thickness are
decided. Smooth booleans use the polynomial smooth minimum (blend radius ``k`` mm).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from recon.volume import VolumeGrid

SdfFunction = Callable[[np.ndarray], np.ndarray]
"""Signed distance (mm) of local points (N, 3) mm, shape (N,)."""

_TARGET_POINTS = 1 << 20  # points per SDF call, bounds memory
_BLOCK = 4  # voxels per block edge of the coarse pass
_BAND_SAFETY = 1.5  # margin on half diagonals for the approximate SDFs


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", v, v))


def sphere(p: np.ndarray, center: Sequence[float], radius: float) -> np.ndarray:
    """Sphere of ``radius`` mm about ``center``."""
    return _norm(p - np.asarray(center)) - radius


def capsule(p: np.ndarray, a: Sequence[float], b: Sequence[float], radius: float) -> np.ndarray:
    """Capsule: all points within ``radius`` mm of the segment a-b."""
    return tapered_capsule(p, a, b, radius, radius)


def tapered_capsule(
    p: np.ndarray, a: Sequence[float], b: Sequence[float], radius_a: float, radius_b: float
) -> np.ndarray:
    """Segment a-b swept by a radius varying linearly from ``radius_a`` to ``radius_b``.

    Exact for equal radii; for unequal radii the error is of order the taper slope squared.
    """
    a = np.asarray(a, dtype=np.float64)
    ba = np.asarray(b, dtype=np.float64) - a
    pa = p - a
    t = np.clip(pa @ ba / float(ba @ ba), 0.0, 1.0)
    return _norm(pa - t[:, None] * ba) - (radius_a + (radius_b - radius_a) * t)


def ellipsoid(p: np.ndarray, center: Sequence[float], radii: Sequence[float]) -> np.ndarray:
    """Axis-aligned ellipsoid; the first-order distance k0 (k0 - 1) / k1 (exact for a sphere).

    Works in any dimension: ``p`` (N, D) with D-element ``center`` and ``radii``.
    """
    r = np.asarray(radii, dtype=np.float64)
    q = p - np.asarray(center)
    k0 = _norm(q / r)
    k1 = _norm(q / (r * r))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = k0 * (k0 - 1.0) / k1
    return np.where(k1 > 1e-12, d, -r.min())


def torus_x(p: np.ndarray, center: Sequence[float], major: float, minor: float) -> np.ndarray:
    """Torus about the line through ``center`` along x: a tube of radius ``minor`` mm around
    the circle of radius ``major`` mm in the y-z plane (``major < minor`` gives a closed,
    wheel-like spindle torus)."""
    q = p - np.asarray(center)
    ring = np.hypot(q[:, 1], q[:, 2]) - major
    return np.hypot(ring, q[:, 0]) - minor


def smooth_union(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Union of two solids, blended over ``k`` mm (polynomial smooth minimum)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


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
    """Index slices [z, y, x] of the voxels whose centres lie in the world box [lo, hi] mm."""
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
